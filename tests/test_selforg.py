"""Self-organization building blocks: potentials, energy gradient (finite differences, NumPy reference), r*, D_p."""

from __future__ import annotations

import numpy as np
import pytest

import arpy
from arpy.adapt import forces
from arpy.adapt import resolution as res
from arpy.reference import selforg as ref


def smooth_D(p: np.ndarray) -> np.ndarray:
    return 0.05 + 0.03 * np.sin(3 * p[:, 0]) * np.cos(2 * p[:, 1])


def smooth_grad_D(p: np.ndarray) -> np.ndarray:
    g = np.zeros_like(p)
    g[:, 0] = 0.09 * np.cos(3 * p[:, 0]) * np.cos(2 * p[:, 1])
    g[:, 1] = -0.06 * np.sin(3 * p[:, 0]) * np.sin(2 * p[:, 1])
    return g


@pytest.mark.parametrize("pot", ["V1", "V2"])
def test_pair_potentials(pot):
    r = np.linspace(0.0, 3.0, 3001)
    v, dv = forces.pair_potential(r, pot)
    rv, rdv = ref.potential(r, pot)
    np.testing.assert_allclose(v, rv, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(dv, rdv, rtol=1e-13, atol=1e-15)
    # V' is the derivative of V (central differences away from r = 0.5)
    mid = (r[1:-1] != 0.5)
    fd = (v[2:] - v[:-2]) / (r[2:] - r[:-2])
    np.testing.assert_allclose(fd[mid & (np.abs(r[1:-1] - 0.5) > 2e-3)], dv[1:-1][mid & (np.abs(r[1:-1] - 0.5) > 2e-3)],
                               rtol=1e-4, atol=1e-6)
    # continuous at 0.5, linear to 0 below it (attraction: V' > 0 there)
    assert v[0] == 0.0
    core = r < 0.5
    np.testing.assert_allclose(v[core], r[core] * dv[core], rtol=1e-12)
    assert np.all(dv[core] > 0)
    assert abs(forces.pair_potential(np.array([0.5 - 1e-9]), pot)[0][0] - forces.pair_potential(np.array([0.5]), pot)[0][0]) < 1e-6
    if pot == "V1":
        assert abs(forces.pair_potential(np.array([1.0]), "V1")[1][0]) < 1e-14      # minimum at r = 1
        assert forces.pair_potential(np.array([1.0]), "V1")[0][0] == pytest.approx(-0.2 * 2.5 ** -4)
    else:
        assert np.all(dv[r > 0.5] < 0)                                           # purely repulsive


def test_pure_potentials_have_no_fusion_core():
    r = np.linspace(0.01, 3.0, 2000)
    for pot in ("V1", "V2"):
        v, dv = forces.pair_potential(r, pot + "-pure")
        rv, rdv = ref.potential(r, pot + "-pure")
        np.testing.assert_allclose(v, rv, rtol=1e-13)
        np.testing.assert_allclose(dv, rdv, rtol=1e-13, atol=1e-15)
        # the formulas of Eqs. 2.12-2.13 at every r, the core's line below 0.5 replaced
        cored, _ = forces.pair_potential(r, pot)
        np.testing.assert_array_equal(v[r >= 0.5], cored[r >= 0.5])
    v2, _ = forces.pair_potential(r, "V2-pure")
    np.testing.assert_allclose(v2, 0.5 / r ** 2 + 1 / (6 * r ** 6), rtol=1e-13)


@pytest.mark.parametrize("pot", ["V1", "V2", "V2-pure"])
@pytest.mark.parametrize("with_grad_D", [True, False])
@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("cutoff", [None, "r*"])
def test_energy_gradient_matches_finite_differences(rng, pot, with_grad_D, d, cutoff):
    n = 400 if d == 2 else 300
    x = rng.random((n, d))
    field = (lambda p: smooth_D(p)) if with_grad_D else (lambda p: np.full(len(p), 0.06))
    grad_field = smooth_grad_D if with_grad_D else None
    D = field(x)
    nl = arpy.neighbor_list(x, res.r_star(d) * D)          # the pair set stays fixed below
    cut = res.r_star(d) if cutoff else None
    W, g = forces.energy(x, D, nl, pot, grad_field(x) if grad_field else None, cutoff=cut)
    i, j = nl.pairs()
    rW, rg = ref.energy(x, D, i, j, pot, grad_field(x) if grad_field else None, cutoff=cut)
    assert W == pytest.approx(rW, rel=1e-12)
    np.testing.assert_allclose(g, rg, rtol=1e-10, atol=1e-12 * np.abs(rg).max())
    h = 1e-6
    for p in range(0, n, max(1, n // 15)):
        for k in range(d):
            xp, xm = x.copy(), x.copy()
            xp[p, k] += h
            xm[p, k] -= h
            fd = (forces.energy(xp, field(xp), nl, pot, cutoff=cut)[0]
                  - forces.energy(xm, field(xm), nl, pot, cutoff=cut)[0]) / (2 * h)
            assert fd == pytest.approx(g[p, k], rel=1e-5, abs=1e-7 * np.abs(g).max())


def test_shifted_energy_is_continuous_at_the_cutoff():
    """With cutoff = r*, a pair contributes 0 as it enters the list (r = r* D)."""
    rs = res.r_star(2)
    for pot in ("V1", "V2"):
        for gap in (1 - 1e-9, 1 + 1e-9):
            x = np.array([[0.0, 0.0], [rs * 0.05 * gap, 0.0]])
            D = np.full(2, 0.05)
            nl = arpy.neighbor_list(x, rs * D)
            W, _ = forces.energy(x, D, nl, pot, cutoff=rs)
            assert abs(W) < 1e-9
    # and the forces are those of the unshifted potential
    x = np.random.default_rng(0).random((200, 2))
    D = np.full(200, 0.05)
    nl = arpy.neighbor_list(x, rs * D)
    np.testing.assert_array_equal(forces.energy(x, D, nl, cutoff=rs)[1], forces.energy(x, D, nl)[1])


def test_dropping_the_grad_D_term_changes_the_gradient(rng):
    x = rng.random((300, 2))
    D = smooth_D(x)
    nl = arpy.neighbor_list(x, res.r_star(2) * D)
    _, g_full = forces.energy(x, D, nl, "V2", smooth_grad_D(x))
    _, g_plain = forces.energy(x, D, nl, "V2")
    assert np.abs(g_full - g_plain).max() > 1e-3 * np.abs(g_full).max()


@pytest.mark.parametrize("periodic", [False, True])
def test_energy_is_the_same_for_every_list_layout(rng, periodic):
    """W and its gradient are bitwise the same from half and full lists, from every list method,
    with each row's entries in any order, and equal the reference (W an exact sum)."""
    x = rng.random((500, 3))
    D = smooth_D(x)
    rc = res.r_star(3) * D
    box = arpy.Domain(np.ones(3), periodic=True) if periodic else None
    lists = [arpy.neighbor_list(x, rc, method=m, full=f, domain=box)
             for m in ("ar", "cell", "brute") for f in (False, True)]
    full = lists[1]
    idx = full.indices.copy()
    for p in range(full.n):
        rng.shuffle(idx[full.offsets[p]:full.offsets[p + 1]])
    lists.append(arpy.NeighborList(full.offsets, idx, full=True))
    W0, g0 = forces.energy(x, D, lists[0], "V1", smooth_grad_D(x), domain=box, cutoff=res.r_star(3))
    for nl in lists[1:]:
        W, g = forces.energy(x, D, nl, "V1", smooth_grad_D(x), domain=box, cutoff=res.r_star(3))
        assert W == W0
        np.testing.assert_array_equal(g, g0)
    i, j = lists[0].pairs()
    rW, _ = ref.energy(x, D, i, j, "V1", smooth_grad_D(x), period=np.ones(3) if periodic else None,
                       cutoff=res.r_star(3))
    assert W0 == pytest.approx(rW, rel=1e-12)


@pytest.mark.parametrize("pot", ["V1", "V2", "V1-pure", "V2-pure"])
def test_energy_without_gradient_is_the_same_energy(rng, pot):
    """energy_terms(gradient=False) (the line search's trials) gives the per-particle energies bit
    for bit as with the gradient, pairs in the fusion core and near coincident ones included, in a
    periodic box and in free space."""
    x = rng.random((600, 2))
    x[:40] = x[40:80] + 1e-3 * rng.random((40, 2))              # pairs inside the core (r < 0.5 D)
    x[80:90] = x[90:100]                                      # coincident pairs
    D = smooth_D(x)
    for box in (None, arpy.Domain(np.ones(2), periodic=True)):
        nl = arpy.neighbor_list(x, res.r_star(2) * D, full=True, domain=box).canonical()
        for cutoff in (None, res.r_star(2)):
            e, g = forces.energy_terms(x, D, nl, pot, smooth_grad_D(x), box, cutoff)
            e_only, none = forces.energy_terms(x, D, nl, pot, smooth_grad_D(x), box, cutoff, gradient=False)
            assert none is None and g is not None and np.abs(g).max() > 0
            np.testing.assert_array_equal(e_only, e)


def test_r_star_from_lattice_neighbour_counts():
    # the paper's list: 2D triangular r* = 1, sqrt3, 2, sqrt7, 3 -> 6, 12, 18, 30, 36 neighbours
    assert res.r_star(2, 6) == pytest.approx(1.0)
    assert res.r_star(2, 10) == pytest.approx(np.sqrt(3)) == res.r_star(2)
    assert res.r_star(2, 18) == pytest.approx(2.0)
    assert res.r_star(2, 30) == pytest.approx(np.sqrt(7))
    # 3D: r* = 1, sqrt2, sqrt3, 2 -> 12, 18, 42, 54
    assert res.r_star(3, 12) == pytest.approx(1.0)
    assert res.r_star(3, 18) == pytest.approx(np.sqrt(2))
    assert res.r_star(3, 20) == pytest.approx(np.sqrt(3)) == res.r_star(3)
    assert res.r_star(3, 54) == pytest.approx(2.0)


def test_monitor_function():
    g = np.array([[0.0, 0.0], [3.0, 4.0], [100.0, 0.0]])
    np.testing.assert_allclose(res.monitor_gradient(g, 0.2), [0.2, 0.2 / np.sqrt(26), 0.2 / np.sqrt(10001)])
    np.testing.assert_allclose(res.monitor_gradient(g, 0.2, Dmin=0.01), [0.2, 0.2 / np.sqrt(26), 0.01])
    with pytest.raises(ValueError):
        res.monitor_gradient(g, -1.0)
    with pytest.raises(ValueError):
        res.monitor_gradient(g, 0.2, Dmin=0.5)


def test_fourth_derivative_monitor():
    """Eq. B.13 for m = 4: D0 (1 + max_beta |d^beta f|)^(-1/4), and the multi-indices it takes."""
    d4 = np.array([[0.0, 0.0, 0.0, 0.0, 0.0], [15.0, -80.0, 3.0, 0.0, 1.0], [1e8, 0.0, 0.0, 0.0, 0.0]])
    np.testing.assert_allclose(res.monitor_fourth(d4, 0.2), [0.2, 0.2 / 81 ** 0.25, 0.2 / (1 + 1e8) ** 0.25])
    np.testing.assert_allclose(res.monitor_fourth(d4, 0.2, Dmin=0.005), [0.2, 0.2 / 3, 0.005])
    for d, k in ((2, 5), (3, 15)):
        b = res.fourth_multi_indices(d)
        assert len(b) == len(set(b)) == k and all(len(v) == d and sum(v) == 4 and min(v) >= 0 for v in b)
    assert res.fourth_multi_indices(2) == [(4, 0), (3, 1), (2, 2), (1, 3), (0, 4)]
    with pytest.raises(ValueError):
        res.monitor_fourth(d4, 0.0)
    with pytest.raises(ValueError):
        res.monitor_fourth(np.zeros(3), 0.2)
    with pytest.raises(ValueError):
        res.fourth_multi_indices(1)


@pytest.mark.parametrize("field", ["smooth", "spike"])
def test_resolution_solves_eq_2_9_like_bisection(rng, field):
    x = rng.random((700, 2))
    if field == "smooth":
        dt = 0.02 + 0.05 * x[:, 0] ** 2
    else:                                   # a sharp fine spot: D~ drops 20x within 0.05
        dt = 0.1 - 0.095 * np.exp(-(((x - 0.5) ** 2).sum(1)) / 0.05 ** 2)
    rs = res.r_star(2)
    D = res.graded_resolution(x, dt, rs)
    np.testing.assert_allclose(D, ref.resolution(x, dt, rs), rtol=1e-12)
    assert np.all(D <= dt) and np.any(D < dt)
    # consistency: the min of D~ within r* D_p is >= D_p, and equals it up to the next particle
    dist = np.sqrt(((x[:, None] - x[None]) ** 2).sum(-1))
    for p in range(0, 700, 7):
        assert dt[dist[p] <= rs * D[p] * (1 - 1e-12)].min() >= D[p] * (1 - 1e-12)
    # a callable target gives the same
    if field == "smooth":
        np.testing.assert_array_equal(res.graded_resolution(x, lambda p: 0.02 + 0.05 * p[:, 0] ** 2, rs), D)


@pytest.mark.parametrize("reading", ["implicit", "explicit", "pointwise"])
def test_resolution_of_some_particles_over_every_source(rng, reading):
    """graded_among grades some of the particles with every particle as a source (a rank's own ones
    among those it holds): the same D_p as grading all of them, the implicit reading also as the
    bisection reference over all sources."""
    x = rng.random((600, 2))
    dt = 0.1 - 0.095 * np.exp(-(((x - 0.5) ** 2).sum(1)) / 0.05 ** 2)
    rs = res.r_star(2)
    box = arpy.Domain(np.ones(2), periodic=[True, False])
    for m in (0, 1, 250, 600):
        D = res.graded_among(x[:m], dt[:m], x, dt, rs, domain=box, reading=reading)
        assert D.shape == (m,)
        np.testing.assert_array_equal(D, res.graded_resolution(x, dt, rs, domain=box, reading=reading)[:m])
    D = res.graded_among(x[:250], dt[:250], x, dt, rs)
    np.testing.assert_allclose(D, ref.resolution(x, dt, rs, rows=np.arange(250)), rtol=1e-12)
    assert reading != "implicit" or np.sum(D < dt[:250]) > 5       # (the grading acts on these rows)


@pytest.mark.parametrize("d", [2, 3])
def test_resolution_periodic_and_wide_span_like_bisection(rng, d):
    """A fine spot 500x finer than the rest, next to a periodic face: the result equals
    the bisection reference on the 3^d periodic copies of the set."""
    n = 500 if d == 2 else 700
    x = rng.random((n, d))
    x[: n // 5] = 0.02 + 0.04 * rng.random((n // 5, d))      # a dense cluster by the corner
    r2 = ((x - 0.04) ** 2).sum(1)
    dt = 0.2 - (0.2 - 0.0004) * np.exp(-r2 / 0.03 ** 2)
    rs = res.r_star(d)
    D = res.graded_resolution(x, dt, rs, domain=arpy.Domain(np.ones(d), periodic=True))
    shifts = np.array(list(np.ndindex(*([3] * d))), float) - 1.0
    tiled = (x[None] + shifts[:, None]).reshape(-1, d)
    centre = int(np.flatnonzero((shifts == 0).all(1))[0])
    rows = np.arange(centre * n, (centre + 1) * n)
    expected = ref.resolution(tiled, np.tile(dt, len(shifts)), rs, rows=rows)
    np.testing.assert_allclose(D, expected, rtol=1e-12)
    # the premises: a wide span, and many D_p set by the grading (s / r*), not by a D~_q
    assert D.max() / D.min() > 20 and np.sum(~np.isin(D, dt)) > 20


@pytest.mark.parametrize("d", [2, 3])
def test_the_core_scan_of_eq_2_9_is_the_exact_minimum(rng, d):
    """resolution.grade (the core's ring scan of a grid) against the O(n m) minimum over every
    source of max(D~_q, |x_p - x_q| / r*), distances summed in the same order: bitwise equal, on
    sources wider than the particles, with coincident points and exact ties, targets spread over 4
    decades (a coarse grid cell then holds many fine sources), on a flat set (one axis of zero
    extent), a graded set (D~ fine at a front, coarse far from it: the coarse particles' reach spans
    many cells, scanned by blocks), at 1 and 2 threads; bad input raises."""
    def exact(x, t, src, st, rs):
        out = np.empty(len(x))
        for lo in range(0, len(x), 256):
            diff = x[lo:lo + 256, None, :] - src[None, :, :]
            s2 = diff[..., 0] * diff[..., 0]
            for a in range(1, d):
                s2 = s2 + diff[..., a] * diff[..., a]
            out[lo:lo + 256] = np.minimum(t[lo:lo + 256], np.maximum(st[None, :], np.sqrt(s2) / rs).min(axis=1))
        return out

    for trial in range(12):
        m = int(rng.integers(1, 1500)) if trial < 11 else 4000    # the last: the parallel loop
        src = rng.random((m, d)) * [1e-3, 1.0, 40.0][trial % 3]
        if trial % 4 == 1:
            src = np.round(src * 8) / 8                           # duplicates and exact ties
        if trial % 4 == 2:
            src[:, -1] = 0.25                                     # a flat set
        st = np.exp(rng.uniform(np.log(1e-4), 0.0, m)) * (np.ptp(src) + 1e-3)
        n = int(rng.integers(1, m + 1)) if trial < 11 else m
        x, t = src[:n], st[:n]
        rs = float(rng.uniform(0.5, 4.0))
        cases = [(x, t, src, st, rs)]
        if trial == 0:                                            # graded from a front at x_0 = 0.5
            g = rng.random((2500, d))
            cases.append((g, 1e-3 + 0.2 * np.abs(g[:, 0] - 0.5), g, 1e-3 + 0.2 * np.abs(g[:, 0] - 0.5), 1.7))
        for case in cases:
            expected = exact(*case)
            for threads in (1, 2):
                with arpy.num_threads(threads):
                    np.testing.assert_array_equal(res.grade(*case), expected)
    x = rng.random((10, d))
    with pytest.raises(ValueError, match="particle 3"):
        res.grade(x, np.where(np.arange(10) == 3, 0.0, 0.1), x, np.full(10, 0.1), 2.0)
    with pytest.raises(ValueError, match="r\\*"):
        res.grade(x, np.full(10, 0.1), x, np.full(10, 0.1), -1.0)
    with pytest.raises(ValueError, match="source"):
        res.grade(x, np.full(10, 0.1), x[:0], np.zeros(0), 2.0)


@pytest.mark.parametrize("d", [2, 3])
def test_sampled_resolution_is_the_shepard_sum_of_the_reference(rng, d):
    """SampledResolution's Shepard interpolation (the core's sum over each row of a cross list, in
    ascending source order) against the O(n m) NumPy reference over every old particle in index order:
    bitwise equal, in free space and across periodic faces (the old particles' images appended as the
    class appends them), at 1 and 2 threads (2500 points: the parallel loop); points no old particle
    reaches take the D of the nearest by the minimum image (also across a periodic face, where the
    images within reach of the faces do not reach)."""
    from arpy.domain import Domain

    for periodic in (False, True):
        x = rng.random((400, d))
        D = np.exp(rng.uniform(np.log(0.02), np.log(0.1), 400))
        y = rng.random((2500, d)) * 1.2 - 0.1
        rstar = 2.0
        dom = Domain([1.0] * d, periodic=True) if periodic else None
        sr = res.SampledResolution(x, D, rstar, domain=dom)
        xs, Ds = x, D
        if periodic:
            y = np.mod(y, 1.0)
            xg, src = dom.images(x, rstar * D)
            xs, Ds = np.concatenate([x, xg]), np.concatenate([D, D[src]])
        want, reached = ref.shepard(xs, Ds, rstar * Ds, y)
        assert 0 < reached.sum() < len(y) or periodic
        for threads in (1, 2):
            with arpy.num_threads(threads):
                got, ok = sr.shepard(y)
                np.testing.assert_array_equal(ok, reached)
                np.testing.assert_array_equal(got[ok], want[reached])
                full = sr(y)
        np.testing.assert_array_equal(full[reached], want[reached])
        far = ~reached
        if far.any():                   # the nearest old particle by the minimum image (brute force)
            e = y[far][:, None, :] - x[None, :, :]
            if periodic:
                e -= np.round(e)
            np.testing.assert_array_equal(full[far], D[np.argmin((e ** 2).sum(axis=2), axis=1)])


def test_resolution_is_graded_not_flooded(rng):
    """Near a fine feature D_p falls gradually: a coarse particle whose reach
    r* D~ merely touches the feature keeps a coarse D_p (Eq. 2.9 read as a
    fixed point, not as a min over the coarse reach)."""
    x = np.stack(np.meshgrid(np.linspace(0, 1, 101), [0.0], indexing="ij"), -1).reshape(-1, 2)
    dt = np.where(x[:, 0] <= 0.1, 0.001, 0.1)
    rs = res.r_star(2)
    D = res.graded_resolution(x, dt, rs)
    far = x[:, 0] >= 0.1 + rs * 0.1 + 1e-9
    np.testing.assert_array_equal(D[far], 0.1)
    ramp = (x[:, 0] > 0.1) & ~far
    # between, D_p = (distance to the fine region) / r*, rounded down to the particle spacing
    gap = x[ramp, 0] - 0.1
    assert np.all(D[ramp] <= gap / rs + 1e-12) and np.all(D[ramp] >= (gap - 0.01) / rs - 1e-12)


def test_energy_input_checks(rng):
    x = rng.random((50, 2))
    nl = arpy.neighbor_list(x, 0.2)
    with pytest.raises(ValueError, match="potential"):
        forces.energy(x, np.full(50, 0.1), nl, "V3")
    with pytest.raises(ValueError, match="cross"):
        forces.energy(x, np.full(50, 0.1), arpy.cross_neighbor_list(x, 0.2, x, 0.2))
    with pytest.raises(ValueError, match="particle 3"):
        D = np.full(50, 0.1)
        D[3] = 0.0
        forces.energy(x, D, nl)


def test_the_explicit_reading_of_eq_2_9(rng):
    """reading="explicit": D_p = min of D~_q over the q within r* D~_p (the un-graded reach), checked
    against the O(n^2) minimum; on the line of test_resolution_is_graded_not_flooded every particle
    whose coarse reach touches the fine region jumps to the fine value.  Periodic: the reference over
    the 3^d copies."""
    x = rng.random((600, 2))
    dt = 0.1 - 0.095 * np.exp(-(((x - 0.5) ** 2).sum(1)) / 0.05 ** 2)
    rs = res.r_star(2)
    D = res.graded_resolution(x, dt, rs, reading="explicit")
    dist = np.sqrt(((x[:, None] - x[None]) ** 2).sum(-1))
    np.testing.assert_array_equal(D, np.array([dt[dist[p] <= rs * dt[p]].min() for p in range(len(x))]))
    assert np.all(D <= res.graded_resolution(x, dt, rs))           # never coarser than the implicit reading
    line = np.stack(np.meshgrid(np.linspace(0, 1, 101), [0.0], indexing="ij"), -1).reshape(-1, 2)
    dl = np.where(line[:, 0] <= 0.1, 0.001, 0.1)
    Dl = res.graded_resolution(line, dl, rs, reading="explicit")
    touches = line[:, 0] - 0.1 <= rs * 0.1 + 1e-12
    np.testing.assert_array_equal(Dl[touches], 0.001)
    np.testing.assert_array_equal(Dl[~touches], 0.1)
    box = arpy.Domain([1.0, 1.0], periodic=True)
    xp = x.copy()
    xp[:100] = 0.01 + 0.05 * rng.random((100, 2))                  # fine spot by the corner
    dtp = np.where(((xp - 0.03) ** 2).sum(1) < 0.03 ** 2, 0.002, 0.1)
    Dp = res.graded_resolution(xp, dtp, rs, domain=box, reading="explicit")
    shifts = np.array(list(np.ndindex(3, 3)), float) - 1.0
    tiled, dtiled = (xp[None] + shifts[:, None]).reshape(-1, 2), np.tile(dtp, len(shifts))
    want = [dtiled[np.sqrt(((tiled - xp[p]) ** 2).sum(1)) <= rs * dtp[p]].min() for p in range(len(xp))]
    np.testing.assert_array_equal(Dp, want)
    np.testing.assert_array_equal(res.graded_resolution(x, dt, rs, reading="pointwise"), dt)   # no ball
    with pytest.raises(ValueError, match="reading"):
        res.graded_resolution(x, dt, rs, reading="paper")
    with pytest.raises(ValueError, match="reading"):
        arpy.self_organize(x, lambda p: np.full(len(p), 0.1), domain=arpy.Domain([1.0, 1.0]), reading="paper")
