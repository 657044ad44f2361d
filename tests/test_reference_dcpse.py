"""Tests of the pure-NumPy DC-PSE reference (arpy.reference.dcpse).

Reboux, Schrader & Sbalzarini, JCP 2012, §2.2 and Appendices A/B.  Checked here:
exact reproduction of polynomials of degree < m (interpolation, every ∂^α with
|α| < m, Laplacian, gradient) on irregular particles with variable spacing,
off-particle (form (a)) and at source particles (form (b)), 2D/3D, m = 3, 4;
the Kronecker-delta property of the interpolating kernel; observed convergence
orders under refinement; an independent per-point implementation; degenerate
stencils raising ValueError.
"""

from __future__ import annotations

from math import comb, factorial

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial import cKDTree

import arpy.reference.dcpse as D
from arpy.cases import slope
from arpy.reference.dcpse import (
    DEFAULT_C,
    dcpse_weights,
    moment_matrices,
    monomial_exponents,
    quartic_spline,
)

# --------------------------------------------------------------------------
# particle sets: jittered lattice mapped through a smooth stretching, so the
# spacing varies by a factor 3 across the unit cube
# --------------------------------------------------------------------------

BETA = 0.5


def _g(xi):
    return xi + BETA * np.sin(2 * np.pi * xi) / (2 * np.pi)


def _gp(xi):
    return 1.0 + BETA * np.cos(2 * np.pi * xi)


def _particles(h0, d, seed, jitter=0.3):
    """Sources on [0,1]^d; returns x (n, d), xi (n, d), local spacing h (n,)."""
    rng = np.random.default_rng(seed)
    n = int(round(1 / h0)) + 1
    grid = np.stack(np.meshgrid(*[np.linspace(0, 1, n)] * d, indexing="ij"), -1).reshape(-1, d)
    xi = np.clip(grid + rng.uniform(-jitter, jitter, grid.shape) * h0, 0.0, 1.0)
    return _g(xi), xi, h0 * _gp(xi).max(axis=1)


def _offgrid(h0, d, seed, n, lo, hi):
    """Random off-particle points with xi in [lo, hi]^d; x (n, d), h (n,)."""
    rng = np.random.default_rng(seed)
    xi = rng.uniform(lo, hi, (n, d))
    return _g(xi), h0 * _gp(xi).max(axis=1)


def _csr(src, col, rc):
    """CSR neighbour lists: sources q with |x_p - x_q| <= rc_p (cKDTree)."""
    lists = cKDTree(src).query_ball_point(col, rc)
    counts = np.array([len(lst) for lst in lists], dtype=np.int64)
    offsets = np.zeros(len(lists) + 1, dtype=np.int64)
    offsets[1:] = np.cumsum(counts)
    indices = np.concatenate([np.sort(np.asarray(lst, dtype=np.int64)) for lst in lists])
    return offsets, indices


def _interior(xi, lo=0.15, hi=0.85):
    return np.flatnonzero(np.all((xi >= lo) & (xi <= hi), axis=1))


# r_c / h chosen so every stencil has at least twice as many neighbours as
# monomials (asserted in the tests); the paper's convention eps = r_c is used.
KAPPA = {(2, 3): 2.6, (2, 4): 3.0, (3, 3): 2.3, (3, 4): 2.8}
H0 = {2: 1 / 16, 3: 1 / 8}

# --------------------------------------------------------------------------
# polynomials
# --------------------------------------------------------------------------


def _poly_values(x, x0, exps):
    """F[:, j] = prod_i (x_i - x0_i)^exps[j, i]."""
    y = x - x0
    return np.stack([np.prod(y ** k, axis=1) for k in exps], axis=1)


def _poly_derivative(x, x0, exps, alpha):
    """Analytic ∂^alpha of every shifted monomial, (n, n_mono)."""
    y = x - x0
    out = np.zeros((x.shape[0], len(exps)))
    for j, k in enumerate(exps):
        if np.any(k < alpha):
            continue
        coef = np.prod([factorial(int(ki)) // factorial(int(ki - ai)) for ki, ai in zip(k, alpha)])
        out[:, j] = coef * np.prod(y ** (k - alpha), axis=1)
    return out


def _poly_laplacian(x, x0, exps):
    d = x.shape[1]
    return sum(_poly_derivative(x, x0, exps, 2 * np.eye(d, dtype=np.int64)[i]) for i in range(d))


def _all_alphas(d, m, at_sources):
    al = [tuple(int(v) for v in k) for k in monomial_exponents(d, m)]
    return al[1:] if at_sources else al


def _assert_exact(mat, F, exact, rtol=1e-8, what=""):
    """|mat F - exact| <= rtol * (|mat| |F|) entrywise (rounding-level check)."""
    got = mat @ F
    scale = abs(mat) @ np.abs(F) + np.abs(exact) + 1e-300
    rel = np.abs(got - exact) / scale
    assert rel.max() <= rtol, f"{what}: max relative error {rel.max():.3e}"


def _setup(d, m, at_sources, seed=0):
    h0 = H0[d]
    kappa = KAPPA[(d, m)]
    src, xi, hs = _particles(h0, d, seed)
    if at_sources:
        col_src = _interior(xi)
        col = src[col_src]
        eps = kappa * hs[col_src]
    else:
        col_src = None
        col, hc = _offgrid(h0, d, seed + 100, 200, 0.15, 0.85)
        eps = kappa * hc
    offsets, indices = _csr(src, col, eps)
    n_mono = comb(m - 1 + d, d)
    assert np.diff(offsets).min() >= 2 * n_mono  # test set-up guard
    return src, col, col_src, eps, offsets, indices


# --------------------------------------------------------------------------
# tests
# --------------------------------------------------------------------------


def test_monomial_exponents():
    e = monomial_exponents(2, 4)
    assert e.tolist() == [[0, 0], [1, 0], [0, 1], [2, 0], [1, 1], [0, 2],
                          [3, 0], [2, 1], [1, 2], [0, 3]]
    assert monomial_exponents(3, 4).shape == (20, 3)
    assert monomial_exponents(3, 3)[4:].tolist() == [[2, 0, 0], [1, 1, 0], [1, 0, 1],
                                                     [0, 2, 0], [0, 1, 1], [0, 0, 2]]
    for d in (1, 2, 3):
        for m in (1, 2, 3, 4, 5, 6):
            e = monomial_exponents(d, m)
            assert e.shape == (comb(m - 1 + d, d), d)
            assert len({tuple(r) for r in e}) == e.shape[0]
            assert e.sum(axis=1).max() == m - 1
            assert np.all(np.diff(e.sum(axis=1)) >= 0)


def test_quartic_spline():
    r = np.array([0.0, 0.25, 0.5, 1.0, 1.5, -0.5])
    np.testing.assert_allclose(quartic_spline(r)[:4], 1 - 6 * r[:4] ** 2 + 8 * r[:4] ** 3
                               - 3 * r[:4] ** 4)
    assert quartic_spline(1.0) == 0.0 and quartic_spline(1.5) == 0.0
    assert quartic_spline(0.0) == 1.0 and quartic_spline(-0.5) == quartic_spline(0.5)


@pytest.mark.parametrize("at_sources", [False, True], ids=["off_particle", "at_sources"])
@pytest.mark.parametrize("m", [3, 4])
@pytest.mark.parametrize("d", [2, 3])
def test_polynomial_reproduction(d, m, at_sources):
    src, col, col_src, eps, offsets, indices = _setup(d, m, at_sources)
    x0 = np.array([0.31, 0.57, 0.43][:d])
    exps = monomial_exponents(d, m)
    F = _poly_values(src, x0, exps)
    alphas = _all_alphas(d, m, at_sources)
    ops = list(alphas) + ["laplacian"] + ([] if at_sources else ["interp"])
    res = dcpse_weights(src, None if at_sources else col, eps, offsets, indices, ops,
                        order=m, at_sources=at_sources, col_src=col_src)
    assert res.data.shape == (len(ops), indices.size)
    for i, op in enumerate(ops):
        mat = res.matrix(i)
        assert mat.shape == (col.shape[0], src.shape[0])
        if op == "laplacian":
            exact = _poly_laplacian(col, x0, exps)
        elif op == "interp":
            exact = _poly_values(col, x0, exps)
        else:
            exact = _poly_derivative(col, x0, exps, np.array(op))
        _assert_exact(mat, F, exact, what=f"op {op}")
        np.testing.assert_allclose(res.apply(F[:, -1], i), mat @ F[:, -1], rtol=1e-12,
                                   atol=1e-12 * np.abs(mat).max())

    # negative control: degree-m monomials are NOT reproduced (the check can fail)
    Fm = _poly_values(src, x0, [np.eye(d, dtype=np.int64)[0] * m])
    mat = res.matrix(ops.index("laplacian"))
    exact = _poly_laplacian(col, x0, [np.eye(d, dtype=np.int64)[0] * m])
    with pytest.raises(AssertionError):
        _assert_exact(mat, Fm, exact)

    # the gradient and the Laplacian alone agree with the multi-index operators
    units = [tuple(int(i == j) for j in range(d)) for i in range(d)]
    grads = dcpse_weights(src, None if at_sources else col, eps, offsets, indices, units,
                          order=m, at_sources=at_sources, col_src=col_src)
    for i, ei in enumerate(units):
        grad = grads.matrix(i)
        diff = grad - res.matrix(ops.index(ei))
        assert abs(diff).max() <= 1e-12 * abs(grad).max()
        _assert_exact(grad, F, _poly_derivative(col, x0, exps, np.array(ei)))
    lap = dcpse_weights(src, None if at_sources else col, eps, offsets, indices, ["laplacian"],
                        order=m, at_sources=at_sources, col_src=col_src).matrix()
    lap_sum = sum(res.matrix(ops.index(tuple(2 * int(i == j) for j in range(d))))
                  for i in range(d))
    assert abs(lap - lap_sum).max() <= 1e-10 * abs(lap).max()


def test_form_a_vanishing_zeroth_moment_and_form_b_diagonal():
    d, m = 2, 4
    src, col, _, eps, offsets, indices = _setup(d, m, at_sources=False)
    res = dcpse_weights(src, col, eps, offsets, indices, [(1, 0), "laplacian"], order=m)
    rows = np.repeat(np.arange(col.shape[0]), np.diff(offsets))
    for i in range(2):
        s = np.bincount(rows, weights=res.data[i], minlength=col.shape[0])
        s_abs = np.bincount(rows, weights=np.abs(res.data[i]), minlength=col.shape[0])
        assert np.all(np.abs(s) <= 1e-12 * s_abs)          # zeroth moment b_0 = 0
    assert np.all(res.diag == 0)

    src, col, col_src, eps, offsets, indices = _setup(d, m, at_sources=True)
    res = dcpse_weights(src, None, eps, offsets, indices, [(0, 1), "laplacian"], order=m,
                        at_sources=True, col_src=col_src)
    rows = np.repeat(np.arange(col.shape[0]), np.diff(offsets))
    self_entry = indices == col_src[rows]
    assert self_entry.sum() == col.shape[0]                 # lists contain the particle
    assert np.all(res.data[:, self_entry] == 0.0)           # ... with weight exactly 0
    for i in range(2):
        np.testing.assert_allclose(
            res.diag[i], -np.bincount(rows, weights=res.data[i], minlength=col.shape[0]))
        mat = res.matrix(i)
        np.testing.assert_allclose(mat[np.arange(col.shape[0]), col_src].A1, res.diag[i])
        row_sum = np.asarray(mat.sum(axis=1)).ravel()
        assert np.all(np.abs(row_sum) <= 1e-12 * np.asarray(abs(mat).sum(axis=1)).ravel())
    # the zeroth moment of form (b) is free: sum of neighbour weights is not 0
    assert np.abs(res.diag[1]).min() > 1.0


def test_one_sided_stencil_reproduces_polynomials():
    # collocation point at a corner, all neighbours in one quadrant
    d, m = 2, 4
    src, xi, hs = _particles(1 / 16, d, seed=5)
    col = np.array([[0.0, 0.0], [1.0, 0.0]])
    eps = np.array([0.3, 0.3])
    offsets, indices = _csr(src, col, eps)
    exps = monomial_exponents(d, m)
    x0 = np.array([0.2, 0.1])
    F = _poly_values(src, x0, exps)
    res = dcpse_weights(src, col, eps, offsets, indices, ["interp", (1, 1), "laplacian"],
                        order=m)
    _assert_exact(res.matrix(0), F, _poly_values(col, x0, exps))
    _assert_exact(res.matrix(1), F, _poly_derivative(col, x0, exps, np.array([1, 1])))
    _assert_exact(res.matrix(2), F, _poly_laplacian(col, x0, exps))


@pytest.mark.parametrize("d", [2, 3])
def test_kronecker_delta(d):
    m = 4
    src, xi, hs = _particles(H0[d], d, seed=3)
    eps = KAPPA[(d, m)] * hs
    offsets, indices = _csr(src, src, eps)
    mat = dcpse_weights(src, src, eps, offsets, indices, ["interp"], order=m).matrix()
    eye = sp.identity(src.shape[0], format="csr")
    assert abs(mat - eye).max() <= 1e-14
    # with caller-given radii a_q (any a_q <= nearest-neighbour distance works)
    nn = cKDTree(src).query(src, k=2)[0][:, 1]
    m2 = dcpse_weights(src, src, eps, offsets, indices, ["interp"], order=m, a=0.9 * nn).matrix()
    assert abs(m2 - eye).max() <= 1e-14
    # negative control: the plain alpha = 0 kernel (Eq. A.4) is not interpolating
    plain = dcpse_weights(src, src, eps, offsets, indices, [(0,) * d], order=m).matrix()
    assert abs(plain - eye).max() > 1e-3


def test_interpolating_kernel_off_particle_is_corrected():
    d, m = 2, 4
    src, xi, hs = _particles(H0[d], d, seed=4)
    # points close to sources, where the quartic-spline correction is active
    rng = np.random.default_rng(9)
    sel = _interior(xi)[:100]
    nn = cKDTree(src).query(src, k=2)[0][:, 1]
    col = src[sel] + 0.2 * nn[sel, None] * rng.uniform(-1, 1, (sel.size, d)) / np.sqrt(d)
    eps = KAPPA[(d, m)] * hs[sel]
    offsets, indices = _csr(src, col, eps)
    res = dcpse_weights(src, col, eps, offsets, indices, ["interp", (0, 0)], order=m)
    assert np.abs(res.data[0] - res.data[1]).max() > 1e-2
    exps = monomial_exponents(d, m)
    x0 = np.array([0.5, 0.5])
    F = _poly_values(src, x0, exps)
    _assert_exact(res.matrix(0), F, _poly_values(col, x0, exps))


def _per_point_reference(src, xp, eps_p, nbrs, alpha, m, c):
    """Independent single-point DC-PSE weights using the Appendix-B convention:
    z' = (x_p - x_q)/eps_p and b'_k = (-1)^|alpha| alpha! delta_{k,alpha}."""
    exps = monomial_exponents(src.shape[1], m)
    zp = (xp - src[nbrs]) / eps_p
    V = np.array([[np.prod(z ** k) for k in exps] for z in zp])
    w = np.exp(-0.5 * c * c * np.sum(zp * zp, axis=1))
    WV = w[:, None] * V
    A = WV.T @ WV
    b = np.zeros(len(exps))
    j = [tuple(k) for k in exps].index(tuple(alpha))
    b[j] = (-1) ** sum(alpha) * np.prod([factorial(a) for a in alpha])
    coef = np.linalg.solve(A, b)
    return eps_p ** (-sum(alpha)) * w * w * (V @ coef), A


def test_matches_independent_per_point_implementation(monkeypatch):
    d, m = 3, 4
    src, col, _, eps, offsets, indices = _setup(d, m, at_sources=False, seed=7)
    alpha = (1, 0, 2)
    res = dcpse_weights(src, col, eps, offsets, indices, [alpha], order=m)
    A_all = moment_matrices(src, col, eps, offsets, indices, order=m)
    S = np.diag([(-1.0) ** k.sum() for k in monomial_exponents(d, m)])
    for p in range(0, col.shape[0], 7):
        nb = indices[offsets[p]:offsets[p + 1]]
        ref, A = _per_point_reference(src, col[p], eps[p], nb, alpha, m, DEFAULT_C)
        got = res.data[0, offsets[p]:offsets[p + 1]]
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-11 * np.abs(ref).max())
        np.testing.assert_allclose(A_all[p], S @ A @ S, rtol=1e-12, atol=1e-14)
    # batching in many small chunks gives the same answer
    orig = D._chunks
    monkeypatch.setattr(D, "_chunks", lambda counts, n_mono: orig(counts, n_mono, budget=5000))
    res2 = dcpse_weights(src, col, eps, offsets, indices, [alpha], order=m)
    np.testing.assert_allclose(res2.data, res.data, rtol=1e-10,
                               atol=1e-12 * np.abs(res.data).max())


def test_convergence_orders_2d_m4():
    d, m, kappa = 2, 4, KAPPA[(2, 4)]

    def f(x):
        return np.sin(2 * np.pi * x[:, 0]) * np.cos(np.pi * x[:, 1])

    def grad(x):
        return np.stack([2 * np.pi * np.cos(2 * np.pi * x[:, 0]) * np.cos(np.pi * x[:, 1]),
                         -np.pi * np.sin(2 * np.pi * x[:, 0]) * np.sin(np.pi * x[:, 1])], 1)

    def lap(x):
        return -5 * np.pi ** 2 * f(x)

    hs_list = [1 / 20, 1 / 40, 1 / 80]
    errs = {k: [] for k in ("interp", "grad_a", "lap_a", "grad_b", "lap_b")}
    for level, h0 in enumerate(hs_list):
        src, xi, hsrc = _particles(h0, d, seed=11 + level)
        fs = f(src)
        col, hc = _offgrid(h0, d, 50 + level, 2000, 0.2, 0.8)
        offsets, indices = _csr(src, col, kappa * hc)
        res = dcpse_weights(src, col, kappa * hc, offsets, indices,
                            ["interp", (1, 0), (0, 1), "laplacian"], order=m)
        g = grad(col)
        errs["interp"].append(np.abs(res.apply(fs, 0) - f(col)).max())
        errs["grad_a"].append(max(np.abs(res.apply(fs, i + 1) - g[:, i]).max() for i in range(2)))
        errs["lap_a"].append(np.abs(res.apply(fs, 3) - lap(col)).max())

        inner = _interior(xi, 0.2, 0.8)
        offsets, indices = _csr(src, src[inner], kappa * hsrc[inner])
        res = dcpse_weights(src, None, kappa * hsrc[inner], offsets, indices,
                            [(1, 0), (0, 1), "laplacian"], order=m, at_sources=True,
                            col_src=inner)
        g = grad(src[inner])
        errs["grad_b"].append(max(np.abs(res.apply(fs, i) - g[:, i]).max() for i in range(2)))
        errs["lap_b"].append(np.abs(res.apply(fs, 2) - lap(src[inner])).max())

    expected = {"interp": m, "grad_a": m - 1, "lap_a": m - 2, "grad_b": m - 1, "lap_b": m - 2}
    orders = {k: slope(hs_list, v) for k, v in errs.items()}
    for k, p in orders.items():
        assert abs(p - expected[k]) <= 0.5, f"{k}: observed order {p:.2f}, errors {errs[k]}"


def test_degenerate_stencils_raise():
    d, m = 2, 4
    src, xi, hs = _particles(1 / 16, d, seed=1)
    col = np.array([[0.5, 0.5], [0.3, 0.3], [0.7, 0.2]])
    eps = np.full(3, 0.25)
    offsets, indices = _csr(src, col, eps)
    # truncate point 1's list to 6 neighbours (< 10 monomials)
    counts = np.diff(offsets)
    keep = np.ones(indices.size, bool)
    keep[offsets[1] + 6:offsets[2]] = False
    counts[1] = 6
    offs2 = np.concatenate([[0], np.cumsum(counts)])
    with pytest.raises(ValueError, match=r"1 of 3 collocation points have fewer than 10 "
                                         r"neighbours.*\b1 \(neighbours=6\)"):
        dcpse_weights(src, col, eps, offs2, indices[keep], ["laplacian"], order=m)

    # collinear stencil: 30 sources on a line
    line = np.stack([np.linspace(0, 1, 30), np.full(30, 0.5)], 1)
    col = np.array([[0.5, 0.52], [0.2, 0.49]])
    offsets, indices = _csr(line, col, np.full(2, 0.3))
    assert np.diff(offsets).min() >= 10
    with pytest.raises(ValueError, match=r"2 of 2 collocation points have a singular or "
                                         r"ill-conditioned"):
        dcpse_weights(line, col, np.full(2, 0.3), offsets, indices, [(1, 0)], order=m)

    # coplanar 3D stencil
    rng = np.random.default_rng(0)
    plane = np.column_stack([rng.uniform(0, 1, (200, 2)), np.full(200, 0.5)])
    col = np.array([[0.5, 0.5, 0.55]])
    offsets, indices = _csr(plane, col, np.full(1, 0.4))
    with pytest.raises(ValueError, match="ill-conditioned"):
        dcpse_weights(plane, col, np.full(1, 0.4), offsets, indices, ["interp"], order=3)

    # form (b): the particle itself does not count as a neighbour
    src3 = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    offsets, indices = _csr(src3, src3, np.full(4, 2.0))
    with pytest.raises(ValueError, match="fewer than 9 neighbours at non-zero distance"):
        dcpse_weights(src3, None, np.full(4, 2.0), offsets, indices, [(1, 0)], order=4,
                      at_sources=True)


def test_bad_input_raises():
    src, xi, hs = _particles(1 / 8, 2, seed=2)
    eps = 3 * hs
    offsets, indices = _csr(src, src, eps)
    with pytest.raises(ValueError, match="must be < order"):
        dcpse_weights(src, src, eps, offsets, indices, [(2, 2)], order=4)
    with pytest.raises(ValueError, match="form \\(b\\)"):
        dcpse_weights(src, src[::-1], eps, offsets, indices, [(1, 0)], at_sources=True)
    with pytest.raises(ValueError, match="alpha = 0"):
        dcpse_weights(src, None, eps, offsets, indices, [(0, 0)], at_sources=True)
    with pytest.raises(ValueError, match="interpolating kernel"):
        dcpse_weights(src, None, eps, offsets, indices, ["interp"], at_sources=True)
    with pytest.raises(ValueError, match="col_eps"):
        dcpse_weights(src, src, -eps, offsets, indices, [(1, 0)])
    with pytest.raises(ValueError, match="offsets"):
        dcpse_weights(src, src, eps, offsets[:-1], indices, [(1, 0)])
    with pytest.raises(ValueError, match="indices"):
        dcpse_weights(src, src, eps, offsets, indices + src.shape[0], [(1, 0)])
    with pytest.raises(ValueError, match="NaN"):
        bad = src.copy()
        bad[0, 0] = np.nan
        dcpse_weights(bad, src, eps, offsets, indices, [(1, 0)])
    with pytest.raises(ValueError, match="Laplacian needs order"):
        dcpse_weights(src, src, eps, offsets, indices, ["laplacian"], order=2)


def test_higher_order_m5_reproduces_quartics():
    # "any order m >= 2": spot check m = 5 (and m = 2) in 2D
    d = 2
    src, xi, hs = _particles(1 / 16, d, seed=8)
    for m, kappa in ((5, 3.6), (2, 2.0)):
        col, hc = _offgrid(1 / 16, d, 21, 100, 0.25, 0.75)
        offsets, indices = _csr(src, col, kappa * hc)
        exps = monomial_exponents(d, m)
        x0 = np.array([0.4, 0.6])
        F = _poly_values(src, x0, exps)
        ops = [tuple(int(v) for v in k) for k in exps[1:]] + ["interp"]
        res = dcpse_weights(src, col, kappa * hc, offsets, indices, ops, order=m)
        for i, op in enumerate(ops):
            exact = (_poly_values(col, x0, exps) if op == "interp"
                     else _poly_derivative(col, x0, exps, np.array(op)))
            _assert_exact(res.matrix(i), F, exact, what=f"m={m} op {op}")
