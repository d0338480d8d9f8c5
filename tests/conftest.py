"""Shared fixtures: paths to ../shared/data, small synthetic clouds."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"


def shared_file(*parts: str) -> Path:
    """Path of a file in ../shared/data, skipping the test with a clear reason when it is absent."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not available: {p} (tests that read real files need ../shared beside the repo)")
    return p


@pytest.fixture(scope="session")
def rng():
    return np.random.default_rng(12345)


def unit_sphere_points(n: int, seed: int = 0, radius: float = 0.5) -> np.ndarray:
    r = np.random.default_rng(seed)
    p = r.normal(size=(n, 3))
    return radius * p / np.linalg.norm(p, axis=1, keepdims=True)


os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
