"""pyproject.toml as pip and setuptools read it: an installation that prints no deprecation warning."""

from __future__ import annotations

import tomllib
from pathlib import Path

from packaging.requirements import Requirement

PYPROJECT = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())


def test_license_is_an_spdx_string_and_the_build_backend_reads_it():
    """The license is an SPDX expression (PEP 639): setuptools >= 77 warned about the TOML table
    ``{text = ...}`` on every install, and setuptools < 77 refuses the string, so the build requires 77."""
    assert PYPROJECT["project"]["license"] == "BSD-3-Clause"
    backend = [Requirement(r) for r in PYPROJECT["build-system"]["requires"]]
    setuptools = next(r for r in backend if r.name == "setuptools")
    assert "76.3" not in setuptools.specifier and "77.0" in setuptools.specifier
