"""``python -m tiled_gridpull`` runs the command line."""

import sys

from tiled_gridpull.pipeline.cli import main

sys.exit(main())
