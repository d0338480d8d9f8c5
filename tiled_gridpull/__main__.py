"""``python -m tiled_gridpull`` runs the command line."""

import sys

from pipeline.cli import main

sys.exit(main())
