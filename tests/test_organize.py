"""The adaptation loop (self_organize): stopping criteria checked by brute force, spacing
against the target field, line search, boundaries, determinism, the fusion scan against
its NumPy reference, periodic energies, interpolated resolution fields."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

import arpy
from arpy import _core
from arpy.adapt import adaptation, forces, organize, view
from arpy.adapt import resolution as res
from arpy.adapt.view import EDGE_LAYER, Confinement, Near, View
from arpy.adapt.resolution import n_star_for
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
    np.testing.assert_array_equal(nl.stored_counts() + np.bincount(nl.indices, minlength=ps.n), counts)
    np.testing.assert_array_equal(nl.counts(), counts)


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


@pytest.mark.parametrize("domain", [arpy.Domain([1.0, 1.0], periodic=True), arpy.Domain([1.0, 1.0])],
                         ids=["periodic", "walls"])
def test_adaptation_does_not_depend_on_the_list_method(monkeypatch, domain):
    """Fusion, insertion, energy and descent read every list in a canonical order: forcing the AR
    lists or the uniform cell lists everywhere gives bitwise the same particles."""
    x = np.random.default_rng(4).random((300, 2))
    runs, calls = [], {"ar": 0, "cell": 0}
    for method in ("ar", "cell"):
        def forced(*args, _m=method, **kw):
            calls[_m] += 1
            return arpy.neighbor_list(*args, **{**kw, "method": _m})
        monkeypatch.setattr(view, "neighbor_list", forced)
        runs.append(arpy.self_organize(x, wavy, domain=domain, seed=3, max_iter=40))
    assert calls["ar"] > 0 and calls["cell"] > 0                 # (the loop's lists were the forced ones)
    assert runs[0].log[0]["fused"] > 0 and sum(e["inserted"] for e in runs[0].log) > 0
    for ps in runs[1:]:
        np.testing.assert_array_equal(ps.x, runs[0].x)
        np.testing.assert_array_equal(ps.D, runs[0].D)


def test_counter_draws_depend_only_on_their_key():
    """The insertion draws of a particle are a function of (seed, iteration, key, slot): the same
    whichever other keys are drawn for and in which order; other seeds, iterations or keys differ."""
    keys = np.array([5, 17, 3, 2 ** 40], np.int64)
    u = adaptation.counter_uniforms(7, 2, keys, 9)
    assert u.shape == (4, 9) and np.all((u >= 0) & (u < 1))
    np.testing.assert_array_equal(adaptation.counter_uniforms(7, 2, keys[::-1], 9), u[::-1])
    np.testing.assert_array_equal(adaptation.counter_uniforms(7, 2, keys[1:2], 9), u[1:2])
    for other in (adaptation.counter_uniforms(8, 2, keys, 9), adaptation.counter_uniforms(7, 3, keys, 9),
                  adaptation.counter_uniforms(7, 2, keys + 1, 9)):
        assert not np.any(other == u)
    big = adaptation.counter_uniforms(1, 1, np.arange(20000), 5).ravel()
    assert abs(big.mean() - 0.5) < 0.005 and abs(big.var() - 1 / 12) < 0.002


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


def _scan_with(x, D, nl, periodic):
    period = np.ones(x.shape[1]) if periodic else np.zeros(x.shape[1])
    near = Near(x, D, np.arange(len(x), dtype=np.int64), len(x), nl)
    one = arpy.distributed.SerialComm()
    dom = arpy.Domain([1.0] * x.shape[1], periodic=True) if periodic else arpy.Domain()
    view = View(Confinement(dom, None), one, arpy.distributed.bisect(x, 1, domain=dom)[0])
    return adaptation._scan(near, period, 0.9 * res.r_star(x.shape[1]), view)


@pytest.mark.parametrize("periodic", [False, True])
def test_scan_matches_reference(rng, periodic):
    x = rng.random((400, 2))
    x[1] = x[0] + 1e-3                       # a pair to fuse
    x[2] = x[0] + [2e-3, 0.0]                # ... and a third particle close to both
    x[3] = [1e-3, 0.5]
    x[4] = [1 - 1e-3, 0.5]                   # a pair across the periodic face
    D = 0.03 + 0.02 * x[:, 1]
    domain = arpy.Domain([1.0, 1.0], periodic=True) if periodic else None
    nl = arpy.neighbor_list(x, res.r_star(2) * D, domain=domain, full=True)
    xo, alive, cnt, cnt_alive, ratio, nf = _scan_with(x, D, nl, periodic)
    rx, ralive, rcnt, rcnt_alive, rratio, rnf = ref.scan(x, D, res.r_star(2), np.ones(2) if periodic else None,
                                                         0.9 * res.r_star(2))
    np.testing.assert_allclose(xo, rx, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(alive, ralive)
    np.testing.assert_array_equal(cnt, rcnt)
    np.testing.assert_array_equal(cnt_alive, rcnt_alive)
    assert ratio == pytest.approx(rratio, rel=1e-14) and nf == rnf
    assert nf >= (2 if periodic else 1)
    # counts against brute force
    i, j, _ = brute_pairs(x, res.r_star(2) * D, period=np.ones(2) if periodic else None)
    np.testing.assert_array_equal(cnt, np.bincount(i, minlength=400) + np.bincount(j, minlength=400))


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


def _shuffled_rows(nl, rng):
    """The same full list with every row's entries in a random order."""
    idx = nl.indices.copy()
    for p in range(nl.n):
        rng.shuffle(idx[nl.offsets[p]:nl.offsets[p + 1]])
    return arpy.NeighborList(nl.offsets, idx, full=True)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("periodic", [False, True])
def test_fusion_is_a_matching_independent_of_the_list(rng, d, periodic):
    """The fusion scan against the brute-force reference (every pair of the set, no list, greedy
    matching in the order of r / D_pq, then the indices), on sets with coincident points, chains
    and clusters: the same survivors, fused positions, counts and max D_pq / r_pq (huge for
    coincident particles); bitwise the same for arpy's lists, the lists with rows shuffled and
    lists built from the brute-force pairs.  In a chain of close pairs each particle fuses at most
    once: of three particles a chain apart two survive."""
    period = np.ones(d) if periodic else None
    rs = res.r_star(d)
    seen_chain = seen_coincident = 0
    for x, D in small_fusion_sets(rng, d, 120):
        n = len(x)
        e = x[:, None, :] - x[None, :, :]
        if periodic:
            e -= np.round(e)
        r = np.sqrt((e ** 2).sum(-1))
        dpq = np.minimum(D[:, None], D[None, :])
        within = np.triu(r <= rs * dpq, k=1)
        own = arpy.neighbor_list(x, rs * D, full=True,
                                 domain=arpy.Domain(np.ones(d), periodic=True) if periodic else None)
        lex = arpy.NeighborList.from_pairs(n, *np.nonzero(within), full=True)
        rx, ralive, rcnt, rcnt_alive, rratio, rnf = ref.scan(x, D, rs, period, 0.9 * rs)
        first = _scan_with(x, D, own, periodic)
        for nl in (own, own.canonical(), _shuffled_rows(own, rng), lex):
            xo, alive, cnt, cnt_alive, ratio, nf = out = _scan_with(x, D, nl, periodic)
            for a, b in zip(out, first):
                np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(alive, ralive)
        np.testing.assert_allclose(xo[ralive], rx[ralive], rtol=0, atol=1e-15)
        assert nf == rnf == n - ralive.sum()
        np.testing.assert_array_equal(cnt, rcnt)
        np.testing.assert_array_equal(cnt, within.sum(0) + within.sum(1))
        np.testing.assert_array_equal(cnt_alive, rcnt_alive)
        if np.any(r[within] == 0):
            assert ratio == np.finfo(np.float64).max and rratio == np.inf
        elif within.any():
            assert ratio == pytest.approx(rratio, rel=1e-14)
            assert ratio == pytest.approx((dpq[within] / r[within]).max(), rel=1e-14)
        close = np.triu(r < 0.5 * dpq, k=1)
        seen_coincident += bool(np.any(np.triu(r == 0, k=1)))
        # a chain: a close pair (a, b) and (b, c) with (a, c) not close
        seen_chain += bool(np.any((close.astype(int) @ close.astype(int)) & ~(close | close.T)))
    assert seen_coincident > 50 and seen_chain > 10


def test_fusion_of_a_chain_fuses_each_particle_once():
    """Three particles in a row, 0.3 D and 0.29 D apart: the closer pair (1, 2) fuses at its midpoint,
    particle 0 stays where it is (its partner has fused) until the next pass."""
    x = np.array([[0.5, 0.5], [0.53, 0.5], [0.559, 0.5]])
    D = np.full(3, 0.1)
    nl = arpy.neighbor_list(x, res.r_star(2) * D, full=True)
    xo, alive, *_, nf = _scan_with(x, D, nl, False)
    assert nf == 1 and alive.tolist() == [True, True, False]
    np.testing.assert_array_equal(xo[0], x[0])
    np.testing.assert_allclose(xo[1], [0.5445, 0.5], rtol=0, atol=1e-15)


def test_an_unconverged_adaptation_warns_and_says_where_it_stood(recwarn):
    """self_organize stopped by max_iter before its stopping rule holds warns NotConvergedWarning, with
    the iterations, the last iteration's N and insertions and the neighbour count against N* (those of
    its log), and, still adding particles, that more iterations would help; the same start given the
    iterations it needs (the default) converges without a warning; a run whose insertions and fusions
    balance (Eq. 2.9 read pointwise next to a wall) is told it cycles; a fixed-number descent stopped
    by max_iter, that the energy still falls."""
    x = np.random.default_rng(1).random((300, 2))
    torus = arpy.Domain([1.0, 1.0], periodic=True)
    with pytest.warns(arpy.NotConvergedWarning) as caught:
        ps = arpy.self_organize(x, wavy, domain=torus, seed=7, max_iter=3)
    assert not ps.converged and len(ps.log) == 3 and len(caught) == 1
    last = ps.log[-1]
    said = str(caught[0].message)
    assert "after 3 iterations (max_iter = 3)" in said and f"N = {last['n']}," in said
    assert f"inserted {last['inserted']} and fused {last['fused']}" in said
    assert f"fewest neighbours {last['min_neighbors']} (N* = {ps.n_star})" in said
    assert f"It still added {ps.n - 300} particles in its last 3 iterations" in said and "larger max_iter" in said
    recwarn.clear()
    assert arpy.self_organize(x, wavy, domain=torus, seed=7).converged
    assert not [w for w in recwarn if issubclass(w.category, arpy.NotConvergedWarning)]
    from arpy.cases.reversing_vortex import blob_monitor

    with pytest.warns(arpy.NotConvergedWarning, match="it cycles, and more iterations will not settle it") as caught:
        ps = arpy.self_organize(np.random.default_rng(2).random((100, 2)), resolution=lambda p: blob_monitor(p, 0.4),
                                domain=arpy.Domain([1.0, 1.0]), seed=1, reading="pointwise", max_iter=60)
    h = ps.history()
    churn, grew = int(h["inserted"][-10:].sum() + h["fused"][-10:].sum()), int(h["n"][-1] - h["n"][-11])
    assert f"({churn} in all, N changed by {grew})" in str(caught[0].message) and abs(grew) <= churn // 4
    with pytest.warns(arpy.NotConvergedWarning, match="the energy still fell by more than tol after 2 iterations"):
        arpy.self_organize(x, wavy, domain=torus, seed=7, adapt_number=False, max_iter=2, tol=0.0)
