"""arpy.Domain: free space, walls and periodic axes, each axis on its own, checked against references
written here and in arpy.reference (a box periodic along x with walls in y is a case the papers do
not show)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import arpy
from arpy.domain import h_min, nearest
from arpy.reference import brute_force_pairs

MIXED = arpy.Domain(([0.0, -1.0], [2.0, 1.0]), periodic=(True, False))


def test_construction_and_validation():
    free = arpy.Domain()
    assert not free.bounded and free.periodic == () and free.for_dim(3).d == 3
    box = arpy.Domain([2.0, 3.0])
    np.testing.assert_array_equal(box.lo, [0, 0])
    np.testing.assert_array_equal(box.hi, [2, 3])
    assert box.has_walls and not box.any_periodic
    torus = arpy.Domain(([-1, -1, -1], [1, 1, 1]), periodic=True)
    assert torus.all_periodic and not torus.has_walls
    np.testing.assert_array_equal(torus.period, [2, 2, 2])
    np.testing.assert_array_equal(MIXED.period, [2, 0])
    assert MIXED.any_periodic and MIXED.has_walls and not MIXED.all_periodic
    for bad in ([1.0], [[0, 0], [1, -1]], [np.inf, 1.0], [[0, 0, 0, 0]]):
        with pytest.raises(ValueError):
            arpy.Domain(bad)
    with pytest.raises(ValueError, match="needs a box"):
        arpy.Domain(periodic=True)
    with pytest.raises(ValueError, match="periodic"):
        arpy.Domain([1.0, 1.0], periodic=(True, False, True))
    with pytest.raises(ValueError, match="dimensional"):
        box.for_dim(3)


def test_wrap_confine_reflect_contains_per_axis():
    x = np.array([[2.5, 0.5], [-0.25, 1.5], [1.0, -1.25], [4.0, 0.0]])
    np.testing.assert_allclose(MIXED.wrap(x), [[0.5, 0.5], [1.75, 1.5], [1.0, -1.25], [0.0, 0.0]])
    np.testing.assert_allclose(MIXED.confine(x), [[0.5, 0.5], [1.75, 1.0], [1.0, -1.0], [0.0, 0.0]])
    np.testing.assert_allclose(MIXED.reflect(x), [[0.5, 0.5], [1.75, 0.5], [1.0, -0.75], [0.0, 0.0]])
    np.testing.assert_array_equal(MIXED.contains(x), [True, False, False, True])   # x is periodic: no bound


def test_neighbor_lists_use_the_minimum_image_only_along_periodic_axes(rng):
    for seed in range(3):
        g = np.random.default_rng(seed)
        x = np.column_stack([g.uniform(0, 2, 600), g.uniform(-1, 1, 600)])
        rc = g.uniform(0.02, 0.2, 600)
        want = brute_force_pairs(x, rc, period=MIXED.period)
        for method in ("cell", "ar", "brute"):
            got = arpy.neighbor_list(x, rc, method=method, domain=MIXED).pairs()
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
    # pairs across the periodic x faces are found, across the walled y faces not
    x = np.array([[0.01, 0.0], [1.99, 0.0], [1.0, -0.99], [1.0, 0.99]])
    i, j = arpy.neighbor_list(x, 0.1, domain=MIXED).pairs()
    assert list(zip(i, j)) == [(0, 1)]


@pytest.mark.parametrize("d", [2, 3])
def test_periodic_ar_lists_over_several_levels_equal_brute_force(d):
    """The periodic AR list (the particles' own list plus their band's images queried against
    their tree): cutoffs over a decade and a half (several levels), a skin, some axes periodic and
    others walled, both forms, at 1 and 2 threads, against brute force by the minimum image (the
    lists at 2 threads past the parallel thresholds: tests/test_threads.py)."""
    g = np.random.default_rng(40 + d)
    n = 4000 if d == 2 else 3000
    edges = np.array([1.0, 0.75, 0.6][:d])
    x = g.random((n, d)) * edges
    rc = np.exp(g.uniform(np.log(0.002), np.log(0.06), n)) * (1.0 if d == 2 else 2.0)
    periodic = [True, False, True][:d]
    box = arpy.Domain((np.zeros(d), edges), periodic=periodic)
    want = brute_force_pairs(x, rc + 0.001, period=np.where(periodic, edges, 0.0))
    got = {}
    for threads in (1, 2):
        with arpy.num_threads(threads):
            for full in (False, True):
                nl = arpy.neighbor_list(x, rc, method="ar", skin=0.001, full=full, domain=box)
                i, j = nl.pairs()
                np.testing.assert_array_equal(i, want[0])
                np.testing.assert_array_equal(j, want[1])
                assert len(nl) == want[0].size * (2 if full else 1)
                got[threads, full] = nl.offsets.tobytes() + nl.indices.tobytes()
    assert got[1, True] == got[2, True] and got[1, False] == got[2, False]


@pytest.mark.parametrize("d", [2, 3])
def test_periodic_lists_with_cutoffs_near_half_the_box(d):
    """Cutoffs up to 0.45 of the periodic edge: the uniform grid has 2 cells along it and cannot
    wrap, so every method goes through the images; each pair by the minimum image once, both forms."""
    g = np.random.default_rng(50 + d)
    n = 400
    edges = np.array([1.0, 3.0, 2.0][:d])
    x = g.random((n, d)) * edges
    rc = g.uniform(0.05, 0.45, n)
    box = arpy.Domain((np.zeros(d), edges), periodic=[True] + [False] * (d - 1))
    want = brute_force_pairs(x, rc, period=np.where(box.periodic, edges, 0.0))
    for method in ("cell", "ar", "brute"):
        for full in (False, True):
            nl = arpy.neighbor_list(x, rc, method=method, full=full, domain=box)
            i, j = nl.pairs()
            np.testing.assert_array_equal(i, want[0], err_msg=method)
            np.testing.assert_array_equal(j, want[1], err_msg=method)
            assert len(nl) == want[0].size * (2 if full else 1)


def test_images_mirrors_and_nearest():
    x = np.array([[0.05, 0.95], [1.0, 0.0]])
    xg, src = MIXED.images(x, 0.1)
    np.testing.assert_allclose(xg, [[2.05, 0.95]])          # only across x (periodic)
    np.testing.assert_array_equal(src, [0])
    xm, msrc = MIXED.mirrors(x, 0.1)
    np.testing.assert_allclose(xm, [[0.05, 1.05]])           # only across the wall y = 1
    xgm, gsrc = MIXED.ghosts(x, 0.1)                         # the corner: the periodic image mirrored too
    assert {tuple(np.round(p, 12)) for p in xgm} == {(2.05, 0.95), (0.05, 1.05), (2.05, 1.05)}
    assert set(gsrc.tolist()) == {0}
    y = np.array([[1.95, 0.9], [0.5, -0.98]])
    dist, idx = nearest(x, y=y, domain=MIXED)
    np.testing.assert_allclose(dist, [np.hypot(0.1, 0.05), np.hypot(0.5, 0.98)])
    np.testing.assert_array_equal(idx, [0, 1])


def mirrors_by_loop(dom, x, rc, faces):
    """Domain.mirrors written per particle and per wall combination: the images (first axis's flip
    slowest; 0 as is, 1 across lo, 2 across hi), each combination's particles in order."""
    lo, hi, w = dom.lo, dom.hi, np.asarray(dom.walls)
    out, src = [], []
    for flips in list(itertools.product((0, 1, 2), repeat=x.shape[1]))[1:]:
        for p in range(x.shape[0]):
            if not np.all((x[p] >= lo) | ~w) or not np.all((x[p] <= hi) | ~w):
                continue
            ok, img = True, x[p].copy()
            for a, f in enumerate(flips):
                if f == 1:
                    ok &= bool(w[a] and faces[a, 0] and 0 < x[p, a] - lo[a] <= rc[p])
                    img[a] = 2 * lo[a] - x[p, a]
                elif f == 2:
                    ok &= bool(w[a] and faces[a, 1] and 0 < hi[a] - x[p, a] <= rc[p])
                    img[a] = 2 * hi[a] - x[p, a]
            if ok:
                out.append(img)
                src.append(p)
    return np.array(out).reshape(-1, x.shape[1]), np.array(src, np.int64)


@pytest.mark.parametrize("d", [2, 3])
def test_mirrors_equal_a_loop_over_particles_and_walls(d):
    """Mirror images across walls, edges and corners, in their order: particles on a wall (not
    mirrored across it), outside the walls (none), near both walls of an axis, some faces only."""
    g = np.random.default_rng(10 + d)
    for dom in (arpy.Domain([1.0, 0.5, 0.8][:d]), arpy.Domain([1.0, 0.5, 0.8][:d], periodic=[True] + [False] * (d - 1))):
        x = g.random((400, d)) * dom.edge
        x[:20, 0] = 0.0                                  # on the wall x = 0
        x[20:30, d - 1] = dom.hi[d - 1]                  # on the last axis's upper wall
        x[30:35, 1] = -0.01                              # outside the walls
        rc = g.uniform(0.01, 0.3, 400)
        rc[35:45] = 0.6                                  # near both walls of the narrow axis
        some = np.zeros((d, 2), bool)
        some[1, 1] = some[d - 1, 0] = True               # walls of axis 1 and the last axis only
        for faces in (np.ones((d, 2), bool), some):
            xm, src = dom.mirrors(x, rc, faces)
            want_x, want_src = mirrors_by_loop(dom, x, rc, faces)
            assert xm.shape[0] > 0
            np.testing.assert_array_equal(src, want_src)
            np.testing.assert_array_equal(xm, want_x)


@pytest.mark.parametrize("d", [2, 3])
def test_nearest_equals_ckdtree_and_brute_force(d):
    """arpy.domain.nearest (the core's grid search) gives cKDTree.query's distances bit for bit, in
    free space (also queries far outside the points, a flat set, a graded set, a lattice with ties), in a periodic
    box and in a box periodic along one axis; its indices are brute force's nearest, ties by index;
    k = 1 gives 1-D arrays, k > n pads with inf and n as cKDTree does; 1 and 2 threads agree."""
    from scipy.spatial import cKDTree

    g = np.random.default_rng(d)
    box = arpy.Domain([1.0, 2.0, 1.5][:d], periodic=True)
    mixed = arpy.Domain([1.0, 2.0, 1.5][:d], periodic=[True] + [False] * (d - 1))
    lattice = np.array(list(itertools.product(range(6), repeat=d)), float) / 5
    flat = g.random((700, d))
    flat[:, 1] = 0.25
    cases = [(g.normal(size=(1200, d)), g.normal(size=(2100, d)) * 3, None),     # (2000 queries and more: threaded)
             (flat, g.random((300, d)), None),
             (g.random((1500, d)) ** 4, g.random((600, d)) ** 2, None),                 # graded: finer cells
             (lattice, np.round(g.random((400, d)) * 10) / 10, None),
             (g.random((1000, d)) * box.edge, g.random((2100, d)) * box.edge, box),
             (np.round(g.random((900, d)) * 8) / 8 * box.edge, g.random((400, d)) * box.edge, box),
             (g.random((1000, d)) * mixed.edge, g.random((900, d)) * mixed.edge, mixed)]
    for x, y, dom in cases:
        # brute force: by (distance, index), the minimum image along the periodic axes
        e = y[:, None, :] - x[None, :, :]
        if dom is not None:
            e = e - dom.whole_periods(e.reshape(-1, d)).reshape(e.shape)
        squared = (e ** 2).sum(axis=2)
        dist = np.sqrt(squared)
        ranked = np.argsort(squared, axis=1, kind="stable")[:, :8]        # (squared: as compared there)
        for k in (1, 2, 7):
            got = nearest(x, k, y=y, domain=dom)
            with arpy.num_threads(1):
                one = nearest(x, k, y=y, domain=dom)
            assert all(a.tobytes() == b.tobytes() for a, b in zip(got, one))
            if dom is None:
                want, _ = cKDTree(x).query(y, k=k)
            else:
                want, _ = cKDTree(dom.box_coordinates(x), boxsize=dom.period).query(dom.box_coordinates(y), k=k)
            assert got[0].shape == want.shape and got[0].tobytes() == np.asarray(want).tobytes()
            near, idx, order = got[0].reshape(len(y), k), got[1].reshape(len(y), k), ranked[:, :k]
            np.testing.assert_allclose(near, np.take_along_axis(dist, order, 1), rtol=1e-14)
            # the same points where the k-th is not tied with the next
            firm = np.take_along_axis(dist, ranked[:, k:k + 1], 1)[:, 0] > near[:, -1] * (1 + 1e-12)
            np.testing.assert_array_equal(np.sort(idx[firm], 1), np.sort(order[firm], 1))
            if dom is None:                  # (the same sums as here: ties broken by index, exactly)
                np.testing.assert_array_equal(idx, order)
            # nearest first: in the same order where no two of the first k + 1 distances are close
            lead = np.take_along_axis(dist, ranked[:, :k + 1], 1)
            apart = (np.diff(lead, axis=1) > lead[:, 1:] * 1e-12).all(axis=1)
            np.testing.assert_array_equal(idx[apart], order[apart])
    dist, idx = nearest(np.zeros((2, d)), 4, y=np.ones((3, d)))
    assert np.isinf(dist[:, 2:]).all() and (idx[:, 2:] == 2).all() and np.isfinite(dist[:, :2]).all()
    with pytest.raises(ValueError, match="finite"):
        nearest(np.array([[0.0, np.nan] + [0.0] * (d - 2)]), y=np.zeros((1, d)))


@pytest.mark.parametrize("d", [2, 3])
def test_h_min_is_the_least_nearest_neighbour_distance(d):
    """h_min (the core's scan of neighbouring cells) equals brute force's least pairwise distance and,
    bit for bit, the least second-nearest distance of nearest(x, 2, y=x): uniform, graded, lattice
    (ties) and coincident points, free, periodic (also boxes of fewer than three cells per axis, and
    sets so sparse that no pair is closer than a cell edge) and mixed; 1 and 2 threads agree."""
    g = np.random.default_rng(10 + d)
    edge = np.array([1.0, 2.0, 1.5][:d])
    box, mixed = arpy.Domain(edge, periodic=True), arpy.Domain(edge, periodic=[True] + [False] * (d - 1))
    lattice = np.array(list(itertools.product(range(7), repeat=d)), float) / 7 * edge
    sets = [g.random((2100, d)) * edge, g.random((2100, d)) ** 4 * edge, lattice,
            np.concatenate([g.random((300, d)), g.random((5, d))]) * edge, g.random((3, d)) * edge,
            np.array([[0.01] + [0.5] * (d - 1), [0.99 * edge[0]] + [0.5] * (d - 1)]),
            np.array(list(itertools.product(range(3), repeat=d)), float) / 2]     # no pair within a cell edge
    sets[3][-1] = sets[3][0]                                     # two coincident particles
    for x in sets:
        for dom in (None, box, mixed):
            got = h_min(x, dom)
            with arpy.num_threads(1):
                assert h_min(x, dom) == got
            assert got == nearest(x, 2, y=x, domain=dom)[0][:, 1].min()
            if len(x) <= 400:
                e = x[:, None, :] - x[None, :, :]
                if dom is not None:
                    e = e - dom.whole_periods(e.reshape(-1, d)).reshape(e.shape)
                dist = np.sqrt((e ** 2).sum(axis=2))
                np.fill_diagonal(dist, np.inf)
                assert got == pytest.approx(dist.min(), rel=1e-14, abs=1e-300)
    assert h_min(np.zeros((1, d))) == np.inf


def test_dcpse_laplacian_in_a_channel_periodic_in_x_with_walls_in_y():
    """f = cos(pi x) cos(pi y) on [0, 2] x [-1, 1]: periodic in x, zero normal derivative at the walls
    y = +-1, so the periodic images and the mirror images (and the images of images at the corners)
    give a consistent Laplacian everywhere, -2 pi^2 f."""
    for seed in (0, 1):
        g = np.random.default_rng(seed)
        x = np.column_stack([g.uniform(0, 2, 6000), g.uniform(-1, 1, 6000)])
        f = np.cos(np.pi * x[:, 0]) * np.cos(np.pi * x[:, 1])
        op = arpy.DomainDCPSE(x, np.full(len(x), 0.08), domain=MIXED, widen=2)
        lap = op.laplacian() @ op.extend(f)
        assert np.abs(lap + 2 * np.pi ** 2 * f).max() < 0.05 * 2 * np.pi ** 2
        corner = (np.minimum(x[:, 0], 2 - x[:, 0]) < 0.08) & (np.abs(x[:, 1]) > 0.92)
        assert corner.sum() > 5


def test_self_organize_in_a_channel():
    """Particles adapt in the channel: they stay between the walls, cross the periodic faces, and meet
    the stopping rule with N* neighbours counted by the minimum image in x and mirror images in y."""
    wavy = lambda p: 0.06 * (1 + 0.5 * np.sin(np.pi * p[:, 0]))  # noqa: E731
    for seed in (1, 2):
        x = np.column_stack([np.random.default_rng(seed).uniform(0, 2, 400),
                             np.random.default_rng(seed + 10).uniform(-1, 1, 400)])
        ps = arpy.self_organize(x, wavy, domain=MIXED, seed=seed, max_iter=150)
        assert ps.converged
        assert np.all(MIXED.contains(ps.x)) and np.all((ps.x[:, 0] >= 0) & (ps.x[:, 0] < 2))
        i, j = ps.neighbor_list().pairs()
        assert np.any(np.abs(ps.x[i, 0] - ps.x[j, 0]) > 1.0)        # pairs across the periodic faces


@pytest.mark.parametrize("periodic", [False, True])
def test_top_level_nearest_of_every_particle_leaves_itself_out(periodic):
    """arpy.nearest(x, k, domain=) without query points: every particle's k nearest others, cKDTree's
    query for k + 1 without the particle itself (coincident particles are others, at distance 0);
    with y, cKDTree's query of y; one function, arpy.domain.nearest."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(21)
    x = np.concatenate([rng.random((300, 3)), np.zeros((3, 3)) + 0.25])      # three coincident points
    dom = arpy.Domain([1.0, 1.0, 1.0], periodic=True) if periodic else None
    tree = cKDTree(x, boxsize=1.0 if periodic else None)
    want_d, want_i = tree.query(x, k=5)
    for k in (1, 4):
        dist, idx = arpy.nearest(x, k, domain=dom)
        others = want_i != np.arange(len(x))[:, None]
        dist, idx = dist.reshape(len(x), k), idx.reshape(len(x), k)
        for p in range(len(x)):
            np.testing.assert_array_equal(dist[p], want_d[p, np.flatnonzero(others[p])[:k]])
        assert not np.any(idx == np.arange(len(x))[:, None])
        e = x[idx] - x[:, None, :]
        if periodic:
            e -= np.round(e)
        np.testing.assert_allclose(np.linalg.norm(e, axis=2), dist, rtol=1e-14, atol=1e-15)
    assert arpy.nearest(x, 2)[0][-3:, 0].tolist() == [0.0] * 3
    d1, i1 = arpy.nearest(x, 2, y=x[:7], domain=dom)
    assert np.array_equal(d1, want_d[:7, :2]) and arpy.nearest is nearest
    assert arpy.nearest(x[:2], 3)[1].tolist() == [[1, 2, 2], [0, 2, 2]]
