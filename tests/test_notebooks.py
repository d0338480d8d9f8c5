"""Every notebook in notebooks/ runs top to bottom (tiny data) and shows pictures; the saved ones carry outputs.

The quickstart runs first; its finished job is handed to the notebooks that inspect a job
(``TILED_GRIDPULL_JOB``) so the suite reconstructs only once.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((REPO / "notebooks").glob("*.ipynb"), key=lambda p: (p.stem != "quickstart", p.name))
TINY = {"TILED_GRIDPULL_NB_POINTS": "12000"}
_state: dict = {}


def _images(nb) -> int:
    return sum(1 for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
               if "image/png" in o.get("data", {}))


def test_there_are_notebooks():
    assert {p.name for p in NOTEBOOKS} >= {"quickstart.ipynb", "inspect_tiles.ipynb"}


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path_factory, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")

    for k, v in TINY.items():
        monkeypatch.setenv(k, v)
    out = tmp_path_factory.mktemp(path.stem)
    monkeypatch.setenv("TILED_GRIDPULL_NB_DIR", str(out))
    job = _state.get("job")
    if job is not None:
        monkeypatch.setenv("TILED_GRIDPULL_JOB", str(job))
    else:
        monkeypatch.delenv("TILED_GRIDPULL_JOB", raising=False)
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    nb = nbformat.read(path, as_version=4)
    for c in nb.cells:
        if c.cell_type == "code":
            c.outputs, c.execution_count = [], None
    # raises CellExecutionError (with the cell and traceback) on the first failing cell
    nbclient.NotebookClient(nb, timeout=180, kernel_name="python3", allow_errors=False,
                            resources={"metadata": {"path": str(path.parent)}}).execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.get("output_type") == "error"]
    assert not errors
    assert _images(nb) >= 3, f"{path.name}: expected rendered pictures in the outputs"
    if path.stem == "quickstart":
        job_dir = out / "street_mesh.job"
        assert (job_dir / "report.json").is_file() and (job_dir / "tiles.png").is_file()
        _state["job"] = job_dir


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_saved_notebook_has_its_outputs(path):
    """The notebooks are committed executed, pictures included (they read without running)."""
    nbformat = pytest.importorskip("nbformat")
    nb = nbformat.read(path, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(c.execution_count is not None for c in code), "save the notebook executed"
    assert not [o for c in code for o in c.outputs if o.get("output_type") == "error"]
    assert _images(nb) >= 3
    assert os.path.getsize(path) < 1_500_000  # pictures at screen resolution, not posters
