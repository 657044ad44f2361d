"""Shared fixtures: particle sets that stress neighbour searches."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20121121)


def uniform_points(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    """n points uniformly random in [0, 1]^d."""
    return rng.random((n, d))


def clustered_points(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    """n points in a few tight Gaussian clusters plus a sparse background."""
    centres = rng.random((5, d))
    k = rng.integers(0, 5, size=n)
    x = centres[k] + rng.normal(scale=rng.choice([0.003, 0.02, 0.1], size=(n, 1)), size=(n, d))
    x[: n // 10] = rng.random((n // 10, d))
    return x


def lattice_points(d: int, m: int = 9, h: float = 0.125) -> np.ndarray:
    """A Cartesian lattice of spacing h (exact in binary): with cutoff 2h many
    points sit exactly on cell faces, and pair distances equal the cutoff exactly."""
    axis = np.arange(m) * h
    return np.stack(np.meshgrid(*([axis] * d), indexing="ij"), axis=-1).reshape(-1, d)
