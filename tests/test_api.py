"""The public API: everything a user needs importable from the package root, documented."""

import inspect

import pytest

import tiled_gridpull


@pytest.mark.parametrize("name", tiled_gridpull.__all__)
def test_every_public_name_resolves_and_is_documented(name):
    obj = getattr(tiled_gridpull, name)
    assert name in dir(tiled_gridpull)
    if name == "__version__":
        assert isinstance(obj, str) and obj
        return
    doc = inspect.getdoc(obj) or ""
    assert len(doc.splitlines()) >= 1 and doc.strip(), f"{name} has no docstring"
    if inspect.isfunction(obj) and inspect.signature(obj).parameters:
        # numpydoc: functions that take arguments describe them
        assert "Parameters\n----------" in doc, f"{name}'s docstring has no numpydoc Parameters section"


def test_lazy_names_are_the_objects_of_their_modules():
    from tiled_gridpull.metrics import evaluate
    from tiled_gridpull.tiled_job import reconstruct_scene
    from tiled_gridpull.tiling import TilingConfig

    assert tiled_gridpull.reconstruct_scene is reconstruct_scene
    assert tiled_gridpull.TilingConfig is TilingConfig
    assert tiled_gridpull.evaluate is evaluate


def test_unknown_attribute_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        tiled_gridpull.nope  # noqa: B018
    assert not hasattr(tiled_gridpull, "reconstruct_scenes")
