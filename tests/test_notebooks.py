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


def _notebook_imports(path: Path) -> set[str]:
    """Modules a notebook's code cells import (``tiled_gridpull.x`` as such, others by their top-level name)."""
    import ast
    import json

    names: set[str] = set()
    for cell in json.loads(path.read_text())["cells"]:
        if cell["cell_type"] != "code":
            continue
        src = "".join(cell["source"])
        # IPython magics and shell lines are not Python
        src = "\n".join(ln for ln in src.splitlines() if not ln.lstrip().startswith(("%", "!")))
        for node in ast.walk(ast.parse(src)):
            if isinstance(node, ast.Import):
                names.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                names.add(node.module)
    return {n if n.startswith("tiled_gridpull.") else n.split(".")[0] for n in names}


def _extra_closure(extra: str) -> set[str]:
    """Distributions (normalised names) that ``pip install tiled-gridpull[extra]`` installs, read from this
    checkout's pyproject.toml (its own extras expanded) and, past it, from the installed packages' metadata."""
    import importlib.metadata as md
    import tomllib

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    todo = [Requirement(r) for r in [*project["dependencies"], *project["optional-dependencies"][extra]]]
    seen: set[str] = set()
    while todo:
        req = todo.pop()
        name = canonicalize_name(req.name)
        if name == canonicalize_name(project["name"]):
            todo += [Requirement(r) for e in req.extras for r in project["optional-dependencies"][e]]
            continue
        if name in seen:
            continue
        seen.add(name)
        try:
            requires = md.requires(req.name) or []
        except md.PackageNotFoundError:
            continue
        for r in map(Requirement, requires):
            if r.marker is None or any(r.marker.evaluate({"extra": e}) for e in (req.extras or {""})):
                todo.append(r)
    return seen


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebooks_extra_installs_what_the_notebook_imports(path):
    """``pip install -e ".[notebooks]"`` (the README's advice) installs every package the notebook imports, and
    every optional package that a tiled_gridpull module it imports asks for (``_optional.require``): the
    render cells need pyvista through tiled_gridpull.render, which the extra had left out."""
    import importlib.metadata as md
    import importlib.util
    import re
    import sys

    from packaging.utils import canonicalize_name

    needed: set[str] = set()
    for name in _notebook_imports(path):
        if name.startswith("tiled_gridpull."):
            source = Path(importlib.util.find_spec(name).origin).read_text()
            needed.update(m.split(".")[0] for m in re.findall(r"""require\(\s*["']([\w.]+)["']""", source))
        elif name != "tiled_gridpull" and name not in sys.stdlib_module_names:
            needed.add(name)
    assert "pyvista" in needed or path.stem != "quickstart"  # the scan above sees through the package
    providers = md.packages_distributions()
    installed = _extra_closure("notebooks")
    missing = {m for m in needed if not {canonicalize_name(d) for d in providers.get(m, [m])} & installed}
    assert not missing, f"{path.name} imports {sorted(missing)}, which the notebooks extra does not install"
