"""The adaptation loop (self_organize): stopping criteria checked by brute force, spacing
against the target field, line search, boundaries, determinism, the fusion scan against
its NumPy reference, periodic energies, interpolated resolution fields."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

import arpy
from arpy import _core
from arpy import forces
from arpy import resolution as res
from arpy.organize import EDGE_LAYER, Confinement
from arpy.resolution import n_star_for
from arpy.reference import brute_force_pairs
from arpy.reference import selforg as ref


def wavy(p: np.ndarray) -> np.ndarray:
    """A smooth periodic target resolution on [0, 1]^2 (0.02 .. 0.06)."""
    return 0.04 * (1 + 0.5 * np.sin(2 * np.pi * p[:, 0]) * np.cos(2 * np.pi * p[:, 1]))


def brute_pairs(x, rc, period=None):
    """All pairs (i < j) with |x_i - x_j| <= min(rc_i, rc_j), minimum image if periodic; and r."""
    i, j = brute_force_pairs(x, rc, period=period)
    e = x[j] - x[i]
    if period is not None:
        e -= period * np.round(e / period)
    return i, j, np.sqrt((e ** 2).sum(-1))


def mirrored_counts(x, rc, lo, hi):
    """Neighbours among the mirror images across the walls (method of images), brute force;
    a particle lying on a face is its own image there (not mirrored across it)."""
    n, d = x.shape
    extra = np.zeros(n, int)
    for flips in np.ndindex(*([3] * d)):
        if not any(flips):
            continue
        img = x.copy()
        exists = np.ones(n, bool)
        for a, f in enumerate(flips):
            if f == 1:
                img[:, a] = 2 * lo[a] - x[:, a]
                exists &= x[:, a] > lo[a]
            elif f == 2:
                img[:, a] = 2 * hi[a] - x[:, a]
                exists &= x[:, a] < hi[a]
        img[~exists] = np.inf
        r = np.sqrt(((x[:, None, :] - img[None, :, :]) ** 2).sum(-1))
        hit = r <= np.minimum(rc[:, None], rc[None, :])
        np.fill_diagonal(hit, False)
        extra += hit.sum(axis=1)
    return extra


@pytest.fixture(scope="module")
def periodic_set():
    x = np.random.default_rng(1).random((300, 2))
    return arpy.self_organize(x, wavy, domain=arpy.Domain([1.0, 1.0], periodic=True), seed=7, max_iter=100)


def test_periodic_adaptation_meets_the_stopping_rule(periodic_set):
    ps = periodic_set
    assert ps.converged and ps.log[-1]["n"] == ps.n
    assert ps.n_star == 10 and ps.rstar == pytest.approx(np.sqrt(3))
    assert np.all((ps.x >= 0) & (ps.x <= 1))
    i, j, r = brute_pairs(ps.x, ps.rc, period=np.ones(2))
    counts = np.bincount(i, minlength=ps.n) + np.bincount(j, minlength=ps.n)
    assert counts.min() >= ps.n_star
    assert (np.minimum(ps.D[i], ps.D[j]) / r).max() <= 2.5
    # the list the set hands out is the same
    nl = ps.neighbor_list()
    np.testing.assert_array_equal(nl.counts() + np.bincount(nl.indices, minlength=ps.n), counts)


def test_spacing_follows_the_target_resolution(periodic_set):
    """Documented bands: nearest-neighbour distance / D_p in [0.4, 1.0]
    (0.4 is the d_c bound; measured 0.54-0.91) and no hole wider than D~:
    every point of the box lies within 1.0 D~ of a particle (measured <= 0.64);
    D_p within [0.75, 1] D~ at the particle (Eq. 2.9 only lowers it)."""
    ps = periodic_set
    tree = cKDTree(ps.x, boxsize=1.0)
    nn = tree.query(ps.x, k=2)[0][:, 1] / ps.D
    assert nn.min() >= 0.4 and nn.max() <= 1.0
    probes = np.random.default_rng(5).random((20000, 2))
    assert (tree.query(probes)[0] / wavy(probes)).max() <= 1.0
    ratio = ps.D / wavy(ps.x)
    assert ratio.max() <= 1.0 + 1e-12 and ratio.min() >= 0.75
    # N follows the integral of D~^-2 (about 0.5 D^2 of area per particle, as in §4.3 of the paper)
    g = (np.arange(200) + 0.5) / 200
    area_per_particle = np.mean(wavy(np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)) ** -2.0) / ps.n
    assert 0.35 < area_per_particle < 0.7


def test_line_search_never_raises_the_energy(periodic_set):
    h = periodic_set.history()
    assert np.all(h["energy"] <= h["energy_before"])
    assert h["moved"].any()
    assert h["inserted"][0] > 0                                      # 300 particles are too few
    # the log's bookkeeping: each iteration's N is the last one's less the fused and removed
    # particles plus the inserted ones (from the 300 it started with)
    before = np.concatenate([[300], h["n"][:-1]])
    np.testing.assert_array_equal(h["n"], before - h["fused"] + h["inserted"] - h["removed"])


def test_walls_confine_and_neighbour_rule_counts_mirror_images():
    x = np.random.default_rng(2).random((300, 2))
    ps = arpy.self_organize(x, wavy, domain=arpy.Domain([1.0, 1.0]), seed=3, max_iter=150)
    assert ps.converged and not ps.domain.any_periodic
    assert np.all((ps.x >= 0) & (ps.x <= 1))
    i, j, r = brute_pairs(ps.x, ps.rc)
    counts = np.bincount(i, minlength=ps.n) + np.bincount(j, minlength=ps.n)
    lo, hi = np.zeros(2), np.ones(2)
    assert (counts + mirrored_counts(ps.x, ps.rc, lo, hi)).min() >= ps.n_star
    assert (np.minimum(ps.D[i], ps.D[j]) / r).max() <= 2.5
    np.testing.assert_array_equal(Confinement(arpy.Domain([1.0, 1.0]), None).mirror_counts(ps.x, ps.rc),
                                  mirrored_counts(ps.x, ps.rc, lo, hi))


def test_same_seed_same_result_other_seed_other_result():
    x = np.random.default_rng(4).random((200, 2))
    kw = dict(domain=arpy.Domain([1.0, 1.0], periodic=True), max_iter=30)
    a = arpy.self_organize(x, wavy, seed=11, **kw)
    b = arpy.self_organize(x, wavy, seed=11, **kw)
    c = arpy.self_organize(x, wavy, seed=12, **kw)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.D, b.D)
    assert a.n != c.n or not np.array_equal(a.x, c.x)


def test_monitor_from_grad_f_and_dmin():
    """grad_f + D0 gives D~ = D0 / sqrt(1 + |grad f|^2); Dmin bounds the particle number."""
    x0 = np.array([0.5, 0.5])

    def grad_f(p):
        r = p - x0
        return -400.0 * r * np.exp(-200.0 * (r ** 2).sum(1))[:, None]

    x = np.random.default_rng(3).random((200, 2))
    kw = dict(grad_f=grad_f, D0=0.08, domain=arpy.Domain([1.0, 1.0], periodic=True), seed=1, max_iter=150)
    fine = arpy.self_organize(x, **kw)
    capped = arpy.self_organize(x, Dmin=0.03, **kw)
    assert fine.converged and capped.converged
    assert fine.D.min() < 0.03 and capped.D.min() >= 0.03 * (1 - 1e-12)
    assert capped.n < fine.n
    dt = res.monitor_gradient(grad_f(fine.x), 0.08)
    assert np.all(fine.D <= dt * (1 + 1e-12))
    # near the bump the particles are finer than far from it
    dist = np.linalg.norm(fine.x - x0, axis=1)
    assert np.median(fine.D[dist < 0.05]) < 0.2 * np.median(fine.D[dist > 0.3])


def test_fixed_number_descent_with_V1_in_free_space():
    """Fig. 2.3 a-b style: a fixed number of particles relax under the Morse potential."""
    g = (np.arange(12) + 0.5) / 12 * 0.1 + 0.45       # spacing 0.0083 = 0.69 D: no pair in the fusion core
    x = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + np.random.default_rng(0).normal(0, 1e-4, (144, 2))
    ps = arpy.self_organize(x, lambda p: np.full(len(p), 0.012), potential="V1", adapt_number=False,
                            max_iter=400, tol=1e-5)
    assert ps.n == 144 and not ps.domain.bounded
    h = ps.history()
    assert np.all(h["energy"] <= h["energy_before"]) and h["energy"][-1] < h["energy_before"][0]
    # the Morse minimum is at r = D: the cloud expands to a nearest-neighbour spacing near D
    nn = cKDTree(ps.x).query(ps.x, k=2)[0][:, 1]
    assert 0.8 < np.median(nn) / 0.012 < 1.1


def test_region_in_free_space():
    """Free space limited to a disk: particles stay inside; the neighbour rule holds away from the edge."""
    inside = lambda p: np.linalg.norm(p, axis=1) <= 0.5  # noqa: E731
    x = np.random.default_rng(6).uniform(-0.3, 0.3, (150, 2))
    ps = arpy.self_organize(x, lambda p: np.full(len(p), 0.05), potential="V1", region=inside, seed=2,
                            max_iter=150)
    assert ps.converged
    assert np.all(inside(ps.x))
    i, j, r = brute_pairs(ps.x, ps.rc)
    counts = np.bincount(i, minlength=ps.n) + np.bincount(j, minlength=ps.n)
    interior = np.linalg.norm(ps.x, axis=1) <= 0.5 - ps.rc - EDGE_LAYER * ps.D - 1e-9
    assert interior.sum() > 20 and counts[interior].min() >= ps.n_star
    assert (np.minimum(ps.D[i], ps.D[j]) / r).max() <= 2.5


@pytest.mark.parametrize("periodic", [False, True])
def test_scan_matches_reference(rng, periodic):
    x = rng.random((400, 2))
    x[1] = x[0] + 1e-3                       # a pair to fuse
    x[2] = x[0] + [2e-3, 0.0]                # ... and a third particle close to both
    x[3] = [1e-3, 0.5]
    x[4] = [1 - 1e-3, 0.5]                   # a pair across the periodic face
    D = 0.03 + 0.02 * x[:, 1]
    domain = arpy.Domain([1.0, 1.0], periodic=True) if periodic else None
    nl = arpy.neighbor_list(x, res.r_star(2) * D, domain=domain)
    period = np.ones(2) if periodic else np.zeros(2)
    rcount = 0.9 * res.r_star(2)
    xo, alive, cnt, cnt_alive, ratio, nf, info, bad = _core.arpy_so_scan(x.T, D, period, rcount, nl.offsets,
                                                                         nl.indices)
    assert info == 0
    rx, ralive, rcnt, rcnt_alive, rratio, rnf = ref.scan(x, D, nl.offsets, nl.indices,
                                                         np.ones(2) if periodic else None, rcount)
    np.testing.assert_allclose(xo.T, rx, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(alive.astype(bool), ralive)
    np.testing.assert_array_equal(cnt, rcnt)
    np.testing.assert_array_equal(cnt_alive, rcnt_alive)
    assert ratio == pytest.approx(rratio, rel=1e-14) and nf == rnf
    assert nf >= (3 if periodic else 2)
    # counts against brute force
    i, j, _ = brute_pairs(x, res.r_star(2) * D, period=np.ones(2) if periodic else None)
    np.testing.assert_array_equal(cnt, np.bincount(i, minlength=400) + np.bincount(j, minlength=400))


def greedy_fusion(x, D, visits, period=None):
    """Greedy fusion from its definition (arpy.organize step i, fortran/arpy_selforg.f90
    so_scan): pairs are visited in the order ``visits`` (p, q); a pair whose particles are
    both still alive and whose separation in the input positions is below D_pq / 2,
    D_pq = min(D_p, D_q), fuses: q dies and p moves to the midpoint of the two particles'
    current positions (minimum image).  Pairs farther apart are skipped whatever the
    order, so ``visits`` may hold every pair of the set, not only those of a list."""
    x = np.asarray(x, dtype=np.float64)
    xo, alive = x.copy(), np.ones(len(x), bool)
    for p, q in visits:
        e = x[p] - x[q]
        if period is not None:
            e = e - period * np.round(e / period)
        if alive[p] and alive[q] and np.sqrt(e @ e) < 0.5 * min(D[p], D[q]):
            m = xo[q] - xo[p]
            if period is not None:
                m = m - period * np.round(m / period)
            xo[p] = xo[p] + 0.5 * m
            alive[q] = False
    return xo, alive


def small_fusion_sets(rng, d, count):
    """Small sets with coincident points, chains and clusters closer than D / 2."""
    for k in range(count):
        n = int(rng.integers(2, 28))
        pool = rng.random((max(1, n // 3), d))
        x = pool[rng.integers(0, len(pool), n)]                               # coincident points
        x = x + rng.choice([0.0, 0.01, 0.03, 0.2], size=(n, 1)) * rng.normal(size=(n, d))
        if k % 4 == 0:                                                         # a chain at spacing 0.4 D
            x[: min(n, 6)] = 0.5 + 0.02 * np.arange(min(n, 6))[:, None] * np.eye(d)[0]
        x = np.mod(x, 1.0)
        D = rng.choice([0.05, 0.08], size=n) if k % 2 else np.full(n, 0.05)
        yield x, D


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("periodic", [False, True])
def test_fusion_scan_is_greedy_matching_in_list_order(rng, d, periodic):
    """The core's fusion scan against greedy_fusion written from the definition: on lists
    with rows in index order (pair (p, q), p < q, in row p) the visiting order is every
    pair of the set in lexicographic order, no list involved; on arpy's own lists (a pair
    in the row of either particle) it is the list's order.  Survivors, fused positions,
    the number fused, the neighbour counts and max D_pq / r_pq (huge for coincident
    particles) agree; and no two survivors are closer than D_pq / 2."""
    period = np.ones(d) if periodic else None
    rs = res.r_star(d)
    rcount = 0.9 * rs
    seen_chain = seen_coincident = 0
    for x, D in small_fusion_sets(rng, d, 120):
        n = len(x)
        e = x[:, None, :] - x[None, :, :]
        if periodic:
            e -= np.round(e)
        r = np.sqrt((e ** 2).sum(-1))
        dpq = np.minimum(D[:, None], D[None, :])
        within = np.triu(r <= rs * dpq, k=1)
        bi, bj = np.nonzero(within)
        lex = arpy.NeighborList.from_pairs(n, bi, bj)
        own = arpy.neighbor_list(x, rs * D, domain=arpy.Domain(np.ones(d), periodic=True) if periodic else None)
        every_pair = [(p, q) for p in range(n) for q in range(p + 1, n)]
        in_list_order = [(p, int(q)) for p in range(n) for q in own.neighbors(p)]
        for nl, visits in ((lex, every_pair), (own, in_list_order)):
            xo, alive, cnt, cnt_alive, ratio, nf, info, bad = _core.arpy_so_scan(
                x.T, D, period if periodic else np.zeros(d), rcount, nl.offsets, nl.indices)
            assert info == 0
            bx, balive = greedy_fusion(x, D, visits, period)
            np.testing.assert_array_equal(alive.astype(bool), balive)
            np.testing.assert_allclose(xo.T[balive], bx[balive], rtol=0, atol=1e-15)
            assert nf == n - balive.sum()
            # counts and the stopping ratio over the list's pairs, by brute force
            np.testing.assert_array_equal(cnt, within.sum(0) + within.sum(1))
            both = within & balive[:, None] & balive[None, :] & (r <= rcount * dpq)
            np.testing.assert_array_equal(cnt_alive, both.sum(0) + both.sum(1))
            if np.any(r[within] == 0):
                assert ratio == np.finfo(np.float64).max
            elif within.any():
                assert ratio == pytest.approx((dpq[within] / r[within]).max(), rel=1e-14)
            # no two survivors closer than D_pq / 2 (in the input positions)
            close = np.triu(r < 0.5 * dpq, k=1)
            assert not np.any(close & balive[:, None] & balive[None, :])
        close = np.triu(r < 0.5 * dpq, k=1)
        seen_coincident += bool(np.any(np.triu(r == 0, k=1)))
        # a chain: a close pair (a, b) and (b, c) with (a, c) not close
        seen_chain += bool(np.any((close.astype(int) @ close.astype(int)) & ~(close | close.T)))
    assert seen_coincident > 50 and seen_chain > 10


def test_periodic_energy_uses_minimum_image(rng):
    x = rng.random((300, 2))
    D = np.full(300, 0.04)
    nl = arpy.neighbor_list(x, res.r_star(2) * D, domain=arpy.Domain([1.0, 1.0], periodic=True))
    W, g = forces.energy(x, D, nl, "V2", domain=arpy.Domain([1.0, 1.0], periodic=True))
    i, j = nl.pairs()
    rW, rg = ref.energy(x, D, i, j, "V2", period=np.ones(2))
    assert W == pytest.approx(rW, rel=1e-12)
    np.testing.assert_allclose(g, rg, rtol=1e-10, atol=1e-10)
    # invariant under a periodic translation
    y = np.mod(x + [0.37, 0.81], 1.0)
    W2, g2 = forces.energy(y, D, arpy.neighbor_list(y, res.r_star(2) * D, domain=arpy.Domain([1.0, 1.0], periodic=True)), "V2", domain=arpy.Domain([1.0, 1.0], periodic=True))
    assert W2 == pytest.approx(W, rel=1e-11)
    np.testing.assert_allclose(np.sort(np.abs(g2).ravel()), np.sort(np.abs(g).ravel()), rtol=1e-8, atol=1e-9)


def test_sampled_resolution_is_first_order_and_bounded(rng):
    x = rng.random((2000, 2))
    D = 0.03 + 0.02 * x[:, 0]
    field = arpy.SampledResolution(x, D, res.r_star(2))
    y = rng.random((500, 2)) * 0.8 + 0.1
    v = field(y)
    assert np.all(v >= D.min()) and np.all(v <= D.max())
    assert np.abs(v - (0.03 + 0.02 * y[:, 0])).max() < 0.02 * 0.1      # linear field: error O(h)
    np.testing.assert_allclose(arpy.SampledResolution(x, np.full(2000, 0.05), 1.7)(y), 0.05, rtol=1e-14)
    far = arpy.SampledResolution(x, D, res.r_star(2))(np.array([[5.0, 5.0]]))   # nobody reaches: nearest
    assert far[0] == D[np.argmin(np.linalg.norm(x - 5.0, axis=1))]


def test_field_resolution_from_dcpse_gradient():
    """Steps 4(a)-(c): the monitor from a DC-PSE gradient of sampled f is close to the analytic one."""
    g = (np.arange(60) + 0.5) / 60
    x = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + np.random.default_rng(1).normal(0, 0.002, (3600, 2))
    f = np.sin(2 * np.pi * x[:, 0]) * np.cos(2 * np.pi * x[:, 1])
    grad = 2 * np.pi * np.stack([np.cos(2 * np.pi * x[:, 0]) * np.cos(2 * np.pi * x[:, 1]),
                                 -np.sin(2 * np.pi * x[:, 0]) * np.sin(2 * np.pi * x[:, 1])], axis=1)
    D = np.full(3600, 1.25 / 60)
    field = arpy.field_resolution(np.mod(x, 1.0), f, D, D0=0.1, domain=arpy.Domain([1.0, 1.0], periodic=True))
    exact = res.graded_resolution(np.mod(x, 1.0), res.monitor_gradient(grad, 0.1), res.r_star(2), domain=arpy.Domain([1.0, 1.0], periodic=True))
    # the same first-order interpolation of the exact D_p: only the DC-PSE gradient differs
    smoothed = arpy.SampledResolution(np.mod(x, 1.0), exact, res.r_star(2), domain=arpy.Domain([1.0, 1.0], periodic=True))
    np.testing.assert_allclose(field(np.mod(x, 1.0)), smoothed(np.mod(x, 1.0)), rtol=0.01)


def test_field_resolution_from_dcpse_fourth_derivatives():
    """monitor='fourth' (Eq. B.13): the fourth derivatives by order-6 DC-PSE on widened
    stencils give D_p close to that of the exact ones, for f = sin(2 pi x) cos(2 pi y),
    whose fourth derivatives are (2 pi)^4 times +-sin cos or +-cos sin."""
    g = (np.arange(60) + 0.5) / 60
    x = np.mod(np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + np.random.default_rng(1).normal(0, 0.002, (3600, 2)),
               1.0)
    a = 2 * np.pi
    sx, cx, sy, cy = np.sin(a * x[:, 0]), np.cos(a * x[:, 0]), np.sin(a * x[:, 1]), np.cos(a * x[:, 1])
    # d^4 / dx^p dy^(4-p): the p-th derivative of sin and the (4-p)-th of cos
    dsin, dcos = [sx, cx, -sx, -cx, sx], [cy, -sy, -cy, sy, cy]
    d4 = a ** 4 * np.stack([dsin[p] * dcos[4 - p] for p in (4, 3, 2, 1, 0)], axis=1)
    D = np.full(3600, 1.25 / 60)
    field = arpy.field_resolution(x, sx * cy, D, D0=0.1, domain=arpy.Domain([1.0, 1.0], periodic=True), monitor="fourth")
    exact = res.graded_resolution(x, res.monitor_fourth(d4, 0.1), res.r_star(2), domain=arpy.Domain([1.0, 1.0], periodic=True))
    smoothed = arpy.SampledResolution(x, exact, res.r_star(2), domain=arpy.Domain([1.0, 1.0], periodic=True))
    assert exact.max() < 0.5 * 0.1                       # the monitor refines below D0 everywhere
    np.testing.assert_allclose(field(x), smoothed(x), rtol=0.01)
    with pytest.raises(ValueError, match="order"):
        arpy.field_resolution(x, sx * cy, D, D0=0.1, domain=arpy.Domain([1.0, 1.0], periodic=True), monitor="fourth", order=3)
    with pytest.raises(ValueError, match="monitor"):
        arpy.field_resolution(x, sx * cy, D, D0=0.1, domain=arpy.Domain([1.0, 1.0], periodic=True), monitor="hessian")


def test_reach_widens_the_ball_of_eq_2_9():
    """reach = kappa: D_p solves Eq. 2.9 with the ball kappa r* D_p (NumPy bisection
    reference), both in field_resolution and at the end of self_organize."""
    from arpy.reference import selforg as ref

    rs = res.r_star(2)
    spot = lambda p: 0.012 + 0.05 * (1 - np.exp(-((p - 0.5) ** 2).sum(1) / 0.1 ** 2))  # noqa: E731
    ps1 = arpy.self_organize(np.random.default_rng(4).random((400, 2)), spot, domain=arpy.Domain([1.0, 1.0]), seed=4)
    ps2 = arpy.self_organize(np.random.default_rng(4).random((400, 2)), spot, domain=arpy.Domain([1.0, 1.0]), seed=4, reach=2.0)
    assert ps1.converged and ps2.converged
    np.testing.assert_allclose(ps2.D, ref.resolution(ps2.x, spot(ps2.x), 2 * rs), rtol=1e-12)
    np.testing.assert_allclose(ps1.D, ref.resolution(ps1.x, spot(ps1.x), rs), rtol=1e-12)
    assert ps2.n > ps1.n                                                   # slower grading: more particles
    # field_resolution: D_p from the gradient of sampled f, then Eq. 2.9 with 2 r*
    f = np.exp(-((ps1.x - 0.5) ** 2).sum(1) / 0.1 ** 2)
    a = arpy.field_resolution(ps1.x, f, ps1.D, D0=0.1, domain=arpy.Domain([1.0, 1.0]), strict=False, widen=3)
    b = arpy.field_resolution(ps1.x, f, ps1.D, D0=0.1, domain=arpy.Domain([1.0, 1.0]), strict=False, widen=3, reach=2.0)
    assert np.all(b(ps1.x) <= a(ps1.x) + 1e-15) and np.any(b(ps1.x) < 0.9 * a(ps1.x))
    with pytest.raises(ValueError, match="reach"):
        arpy.self_organize(ps1.x, spot, domain=arpy.Domain([1.0, 1.0]), reach=0.5)


def test_n_star_and_bad_input():
    assert n_star_for(4, 2) == 10 and n_star_for(4, 3) == 20 and n_star_for(2, 2) == 3
    x = np.random.default_rng(0).random((50, 2))
    with pytest.raises(ValueError, match="exactly one"):
        arpy.self_organize(x, wavy, grad_f=lambda p: p, D0=0.1, domain=arpy.Domain([1, 1]))
    with pytest.raises(ValueError, match="exactly one"):
        arpy.self_organize(x, domain=arpy.Domain([1, 1]))
    with pytest.raises(ValueError, match="D0"):
        arpy.self_organize(x, grad_f=lambda p: p, domain=arpy.Domain([1, 1]))
    with pytest.raises(ValueError, match="region"):
        arpy.self_organize(x, wavy)
    with pytest.raises(ValueError, match="needs a box"):
        arpy.self_organize(x, wavy, domain=arpy.Domain(periodic=True))
    with pytest.raises(ValueError, match="potential"):
        arpy.self_organize(x, wavy, domain=arpy.Domain([1, 1]), potential="V9")
    with pytest.raises(ValueError, match="d_c"):
        arpy.self_organize(x, wavy, domain=arpy.Domain([1, 1]), d_c=1.5)
    with pytest.raises(ValueError, match="shape"):
        arpy.self_organize(x, lambda p: np.ones(3), domain=arpy.Domain([1, 1]))
    with pytest.raises(ValueError, match="finite"):
        arpy.self_organize(x, lambda p: np.zeros(len(p)), domain=arpy.Domain([1, 1]))
    with pytest.raises(ValueError, match="outside"):
        arpy.self_organize(x + 5, wavy, domain=arpy.Domain([1, 1]), region=lambda p: p[:, 0] < 1)
    with pytest.raises(ValueError, match="Dmin"):
        arpy.self_organize(x, wavy, domain=arpy.Domain([1, 1]), D0=0.01, Dmin=0.1)
