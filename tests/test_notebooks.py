"""Every notebook in notebooks/ runs top to bottom (tiny data) and shows pictures; the saved ones carry outputs.

The quickstart is executed once per module by a fixture; its finished job is handed to the notebooks that inspect a
job (``TILED_GRIDPULL_JOB``) so the module reconstructs only once. Each test asks for the fixtures it needs, so any
one of them runs alone (``-k inspect_tiles`` executes the quickstart first, through the fixture).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((REPO / "notebooks").glob("*.ipynb"), key=lambda p: (p.stem != "quickstart", p.name))
QUICKSTART = REPO / "notebooks" / "quickstart.ipynb"
TINY = {"TILED_GRIDPULL_NB_POINTS": "12000"}


def _images(nb) -> int:
    return sum(1 for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
               if "image/png" in o.get("data", {}))


def execute_notebook(path: Path, out: Path, job: Path | None = None):
    """Run a notebook from scratch (saved outputs cleared) with tiny data writing to ``out``; return it executed.

    Raises nbclient's CellExecutionError (with the cell and traceback) on the first failing cell."""
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    with pytest.MonkeyPatch.context() as mp:  # the kernel inherits this environment when it starts
        for k, v in TINY.items():
            mp.setenv(k, v)
        mp.setenv("TILED_GRIDPULL_NB_DIR", str(out))
        if job is not None:
            mp.setenv("TILED_GRIDPULL_JOB", str(job))
        else:
            mp.delenv("TILED_GRIDPULL_JOB", raising=False)
        mp.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
        nb = nbformat.read(path, as_version=4)
        for c in nb.cells:
            if c.cell_type == "code":
                c.outputs, c.execution_count = [], None
        nbclient.NotebookClient(nb, timeout=180, kernel_name="python3", allow_errors=False,
                                resources={"metadata": {"path": str(path.parent)}}).execute()
    return nb


@pytest.fixture(scope="module")
def quickstart_run(tmp_path_factory):
    """The quickstart executed once: ``{"nb": notebook, "out": its output folder, "job": its job directory}``."""
    out = tmp_path_factory.mktemp("quickstart")
    nb = execute_notebook(QUICKSTART, out)
    return {"nb": nb, "out": out, "job": out / "street_mesh.job"}


@pytest.fixture(scope="module")
def executed(request, tmp_path_factory):
    """Executed notebooks by stem, each run at most once per module (the inspecting ones on the quickstart's job)."""
    cache: dict = {}

    def get(path: Path):
        if path.stem not in cache:
            quick = request.getfixturevalue("quickstart_run")
            if path == QUICKSTART:
                cache[path.stem] = quick["nb"]
            else:
                cache[path.stem] = execute_notebook(path, tmp_path_factory.mktemp(path.stem), job=quick["job"])
        return cache[path.stem]

    return get


def test_there_are_notebooks():
    assert {p.name for p in NOTEBOOKS} >= {"quickstart.ipynb", "inspect_tiles.ipynb"}


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, executed):
    nb = executed(path)
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.get("output_type") == "error"]
    assert not errors
    assert _images(nb) >= 3, f"{path.name}: expected rendered pictures in the outputs"


@pytest.mark.slow
def test_quickstart_leaves_a_finished_job(quickstart_run):
    job_dir = quickstart_run["job"]
    assert (job_dir / "report.json").is_file() and (job_dir / "tiles.png").is_file()


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
