"""The package's layers, read from its source (nothing is imported): imports point one way, without circles.

Rules checked:

* no import circle among the modules of ``tiled_gridpull`` (every import counts: module level, inside functions
  and under ``TYPE_CHECKING``), so no function-local import is needed to hide one;
* the kernels (``tiled_gridpull.kernels``) import nothing of the package outside the kernels;
* no core module (``tiled_gridpull`` outside ``tiled_gridpull.pipeline``) imports ``tiled_gridpull.pipeline``,
  ``dask`` or ``distributed``, at module level or inside a function: the core runs without Dask. The one
  exception is ``tiled_gridpull.__main__``, the ``python -m tiled_gridpull`` entry point, which runs the CLI;
* ``distributed`` is imported by exactly one module, ``tiled_gridpull.pipeline.job`` (the Dask executor);
* no module imports a private name (leading underscore) of another module of the package.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CORE_EXCEPTIONS = {"tiled_gridpull.__main__"}
# Private names still imported across modules, each to be made public by its module's owner (io.atomic's JSON
# encoder is shared by resume's keys); nothing may be added here.
KNOWN_PRIVATE_IMPORTS: set[str] = set()


def _modules() -> dict[str, tuple[Path, bool]]:
    """Module name -> (source file, is a package ``__init__``).

    ``pipeline/`` installs as ``tiled_gridpull.pipeline``."""
    out = {}
    for root, prefix in ((REPO / "tiled_gridpull", "tiled_gridpull"), (REPO / "pipeline", "tiled_gridpull.pipeline")):
        for f in sorted(root.rglob("*.py")):
            rel = f.relative_to(root).with_suffix("")
            parts = [p for p in rel.parts]
            if "examples" in parts:  # user scripts beside the job layer, not part of the package
                continue
            is_pkg = parts[-1] == "__init__"
            if is_pkg:
                parts = parts[:-1]
            out[".".join([prefix, *parts])] = (f, is_pkg)
    return out


MODULES = _modules()


def _imports(name: str) -> list[tuple[str, list[str], int]]:
    """``(imported module, names taken from it, line)`` for every import statement of a module."""
    path, is_pkg = MODULES[name]
    tree = ast.parse(path.read_text(), str(path))
    package = name if is_pkg else name.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend((a.name, [], node.lineno) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module
            out.append((target, [a.name for a in node.names], node.lineno))
    return out


def _package_edges(name: str) -> set[str]:
    """Modules of the package that ``name`` imports (``from pkg import module`` counts the module)."""
    edges = set()
    for target, names, _ in _imports(name):
        submodules = [n for n in names if f"{target}.{n}" in MODULES]
        edges.update(f"{target}.{n}" for n in submodules)
        if submodules and len(submodules) == len(names):
            continue  # `from . import a, b` of submodules only: the package's own names are not read
        while target and target not in MODULES:
            target = target.rpartition(".")[0]
        if target and target != name:
            edges.add(target)
    return edges


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One circle of ``graph`` as a list of modules, or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state:
                found = visit(m)
                if found:
                    return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state:
            found = visit(n)
            if found:
                return found
    return None


def test_the_module_list_is_what_the_rules_read():
    assert "tiled_gridpull.tiled_job" in MODULES and "tiled_gridpull.pipeline.job" in MODULES
    assert "tiled_gridpull.kernels" in MODULES and MODULES["tiled_gridpull.kernels"][1]


def test_the_cycle_finder_finds_a_circle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_relative_imports_resolve_to_modules():
    edges = _package_edges("tiled_gridpull.tiled_job")
    assert {"tiled_gridpull.jobdir", "tiled_gridpull.resume", "tiled_gridpull.prepare"} <= edges
    assert "tiled_gridpull.kernels" in _package_edges("tiled_gridpull.tiling")


def test_no_import_circles():
    graph = {m: _package_edges(m) for m in MODULES}
    assert _cycle(graph) is None, " -> ".join(_cycle(graph))


def test_kernels_import_only_kernels():
    bad = [(m, e) for m in MODULES if m.startswith("tiled_gridpull.kernels")
           for e in _package_edges(m) if not e.startswith("tiled_gridpull.kernels")]
    assert bad == []


@pytest.mark.parametrize("forbidden", ["tiled_gridpull.pipeline", "dask", "distributed"])
def test_core_does_not_import_the_job_layer_or_dask(forbidden):
    bad = [(m, target, line) for m in MODULES
           if not m.startswith("tiled_gridpull.pipeline") and m not in CORE_EXCEPTIONS
           for target, _, line in _imports(m) if target == forbidden or target.startswith(forbidden + ".")]
    assert bad == []


def test_distributed_is_imported_by_one_module():
    users = {m for m in MODULES for target, _, _ in _imports(m)
             if target == "distributed" or target.startswith("distributed.")}
    assert users == {"tiled_gridpull.pipeline.job"}


def test_no_private_names_imported_across_modules():
    bad = []
    for m in MODULES:
        for target, names, _line in _imports(m):
            if target.startswith("tiled_gridpull"):
                bad += [f"{m} imports {target}.{n}" for n in names if n.startswith("_") and n != "__version__"]
    assert set(bad) <= KNOWN_PRIVATE_IMPORTS, "\n".join(sorted(set(bad) - KNOWN_PRIVATE_IMPORTS))
