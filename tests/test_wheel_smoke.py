"""A quick check of an installed arpy, without the test suite's fixtures: the compiled core loads
with the libraries it links (LAPACK, OpenMP, the Fortran runtime) and its neighbour lists and
DC-PSE operators agree with plain NumPy.

It is the test of every wheel that cibuildwheel builds ([tool.cibuildwheel] in pyproject.toml) and
of the repaired wheel in .ci/check-wheel, run as ``pytest --noconftest tests/test_wheel_smoke.py``
(so only pytest is needed next to the wheel), and a part of the test suite.
"""

from __future__ import annotations

import numpy as np

import arpy


def _pairs_by_numpy(x: np.ndarray, rc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every pair i < j with |x_i - x_j| <= min(rc_i, rc_j), sorted (all n^2 distances)."""
    dist = np.sqrt(((x[:, None, :] - x[None, :, :]) ** 2).sum(axis=-1))
    i, j = np.nonzero(np.triu(dist <= np.minimum(rc[:, None], rc[None, :]), k=1))
    return i, j


def test_neighbor_lists_match_all_pairs():
    rng = np.random.default_rng(7)
    x = rng.random((400, 2))
    rc = np.where(x[:, 0] < 0.5, 0.02, 0.15)      # two resolutions: an AR tree of several levels
    i, j = _pairs_by_numpy(x, rc)
    assert i.size > 1000
    for method in ("ar", "cell", "brute"):
        a, b = arpy.neighbor_list(x, rc, method=method).pairs()
        assert np.array_equal(a, i) and np.array_equal(b, j), method


def test_periodic_neighbor_list_finds_pairs_across_the_faces():
    torus = arpy.Domain([1.0, 1.0], periodic=True)
    x = np.array([[0.01, 0.5], [0.99, 0.5], [0.5, 0.5]])
    a, b = arpy.neighbor_list(x, 0.05, domain=torus).pairs()
    assert a.tolist() == [0] and b.tolist() == [1]


def test_dcpse_differentiates_a_cubic_exactly():
    """Order 4 reproduces polynomials of degree < 4: derivatives of a cubic to rounding (the
    stencils are solved by LAPACK's Cholesky factorisation in the core; order 3 misses them by
    1e-2 on these particles)."""
    rng = np.random.default_rng(3)
    h = 1.0 / 16
    g = np.arange(17) * h
    x = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    x = x + rng.uniform(-0.2 * h, 0.2 * h, x.shape)
    op = arpy.DCPSE(x, 3.5 * h, order=4)
    assert op.failed.size == 0
    X, Y = x[:, 0], x[:, 1]
    f = 1 + 2 * X - 3 * Y + X ** 2 - X * Y + 2 * Y ** 2 + X ** 3 - 2 * X * Y ** 2
    fx, fy = (m @ f for m in op.gradient())
    np.testing.assert_allclose(fx, 2 + 2 * X - Y + 3 * X ** 2 - 2 * Y ** 2, atol=1e-9)
    np.testing.assert_allclose(fy, -3 - X + 4 * Y - 4 * X * Y, atol=1e-9)
    np.testing.assert_allclose(op.laplacian() @ f, 6 + 2 * X, atol=1e-7)


def test_threads_can_be_set():
    with arpy.num_threads(2):
        assert arpy.get_num_threads() == 2
    assert arpy.get_num_threads() >= 1
