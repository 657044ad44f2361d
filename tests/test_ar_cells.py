"""AR cell lists (Fortran core) against the NumPy reference, brute force, the uniform cell list and cKDTree."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import arpy
from arpy.reference import brute_force_cross_pairs, brute_force_pairs
from arpy.reference.ar import ARCellListRef
from conftest import clustered_points, fitted_root, kdtree_pairs, lattice_points, points_with_ties
from test_neighbors import assert_same_pairs, check_csr


def loguniform(rng, n, rmin, span):
    return rmin * np.exp(rng.uniform(0.0, np.log(span), n))


def assert_all_agree(x, rc, *, skin=0.0, with_kdtree=True, with_cell=True):
    """AR (Fortran, symmetric, full and cross) = brute force (NumPy and Fortran) = uniform cell list = cKDTree."""
    expected = brute_force_pairs(x, rc, skin)
    for full in (False, True):
        nl = arpy.neighbor_list(x, rc, method="ar", full=full, skin=skin)
        check_csr(nl, len(x))
        assert len(nl) == expected[0].size * (2 if full else 1)
        assert_same_pairs(nl.pairs(), expected)
    if len(x) <= 4000:
        assert_same_pairs(arpy.neighbor_list(x, rc, method="brute", skin=skin).pairs(), expected)
        # the set as queries against its own tree: every pair both ways and every particle itself
        rcs = np.broadcast_to(rc, (len(x),)) + skin
        own = np.arange(len(x))
        rows, cols = np.concatenate([expected[0], expected[1], own]), np.concatenate([expected[1], expected[0], own])
        order = np.lexsort((cols, rows))
        assert_same_pairs(arpy.ARCellList(x, rcs).cross_list(x, rcs).pairs(), (rows[order], cols[order]))
    if with_cell:
        assert_same_pairs(arpy.neighbor_list(x, rc, method="cell", skin=skin).pairs(), expected)
    if with_kdtree:
        assert_same_pairs(kdtree_pairs(x, rc, skin), expected)
    return expected


def assert_tree_matches_reference(x, rc, domain=None, skin=0.0):
    """Levels, cell table, finer flags and per-cell particle sets equal the reference's."""
    tree = arpy.ARCellList(x, rc, domain=None if domain is None else arpy.Domain(np.stack(domain)), skin=skin)
    rcs = np.broadcast_to(rc, (len(x),)) + skin
    ref = ARCellListRef(x, rcs, domain=domain)
    assert tree.edge == ref.edge and tree.maxlevel == ref.maxlevel
    np.testing.assert_array_equal(tree.lo, ref.lo)
    np.testing.assert_array_equal(tree.level, ref.level)
    # the same cells with the same particles; the slot ranges may differ in order
    # (Algorithm 2's Morton order on hashed levels, table order on dense ones)
    assert tree.cells.keys() == ref.cells.keys()
    assert tree.finer == ref.finer
    for J, (a, b) in tree.cells.items():
        ra, rb = ref.cells[J]
        assert b - a == rb - ra
        assert set(tree.order[a:b].tolist()) == set(ref.order[ra:rb].tolist())
    # own-level ranges tile the slots exactly once
    spans = sorted((a, b) for a, b in tree.cells.values() if b > a)
    assert [a for a, _ in spans] == [0] + [b for _, b in spans[:-1]] and (not spans or spans[-1][1] == len(x))
    return tree, ref


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("lam", [1.0, 3.65, 10.0, 100.0, 1000.0])
def test_paper_benchmark_distribution(d, lam):
    x, rc = arpy.ar_benchmark(2500 if d == 2 else 1500, lam, d=d)
    assert_all_agree(x, rc, with_cell=lam <= 100)
    assert_tree_matches_reference(x, rc)


@pytest.mark.parametrize("d", [2, 3])
def test_multiscale_cutoffs_spanning_1e4(rng, d):
    n = 4000 if d == 2 else 3000
    x = rng.random((n, d))
    rc = loguniform(rng, n, 2e-5 if d == 2 else 2e-4, 1e4)
    expected = assert_all_agree(x, rc, with_cell=False)
    assert expected[0].size > 100
    assert_tree_matches_reference(x, rc)


@pytest.mark.parametrize("d", [2, 3])
def test_clustered_points(rng, d):
    x = clustered_points(rng, 3000, d)
    rc = loguniform(rng, len(x), 1e-3, 100.0)
    assert_all_agree(x, rc)
    assert_tree_matches_reference(x, rc)


@pytest.mark.parametrize("d", [2, 3])
def test_points_on_cell_and_domain_boundaries(d):
    # dyadic lattice spanning [0, 1]: points sit on cell faces of every level
    # and on the domain faces; distances equal the cutoffs exactly
    x = lattice_points(d, m=9 if d == 2 else 5, h=0.125 if d == 2 else 0.25)
    for rc in (0.125, 0.25, np.where(np.arange(len(x)) % 3 == 0, 0.25, 0.125)):
        assert_all_agree(x, rc)
        assert_tree_matches_reference(x, rc)


@pytest.mark.parametrize("d", [2, 3])
def test_the_root_fits_the_smallest_cutoff_at_every_n(d):
    """One cutoff (the paper's distribution at lambda = 1) for N over a factor 7: the finest level's
    cells are exactly the double above the cutoff wide (the paper's D_m = extent gave anywhere
    between 1 and 2 cutoffs, with N), the tree is the reference's and the lists are brute force's;
    two resolutions put the small particles on their own fitted level too."""
    for n in ((600, 1500, 4000) if d == 2 else (300, 800, 2000)):
        x, rc = arpy.ar_benchmark(n, 1.0, d=d)
        tree, _ = assert_tree_matches_reference(x, rc)
        extent = float(np.max(x.max(axis=0) - x.min(axis=0)))
        assert tree.edge == fitted_root(extent, rc, arpy.lists.ar.MAX_LEVEL[d]) >= extent
        assert np.ldexp(tree.edge, -tree.maxlevel) == np.nextafter(rc.min(), np.inf)
        assert np.all(tree.level == tree.maxlevel)
        assert_all_agree(x, rc, with_kdtree=False)
    x, rc = arpy.ar_benchmark(2000 if d == 2 else 1000, 10.0, d=d)
    tree, _ = assert_tree_matches_reference(x, rc)
    small = rc == rc.min()
    assert np.all(tree.level[small] == tree.maxlevel)
    assert np.ldexp(tree.edge, -tree.maxlevel) == np.nextafter(rc.min(), np.inf)


@pytest.mark.parametrize("d", [2, 3])
def test_points_on_the_faces_of_fitted_cells(d):
    """A lattice whose spacing is the fitted cell edge r (the double above the cutoff rc), offset
    by whole cells from the lowest point: every point on cell faces of the finest level and of
    coarser ones; with rc = r exactly (pairs at distance exactly the cutoff) and with rc just
    below r (only diagonal pairs inside), and the same with mixed cutoffs."""
    rc0 = 0.1
    r = np.nextafter(rc0, np.inf)
    m = 12 if d == 2 else 6
    grid = np.array(list(itertools.product(range(m), repeat=d)), float)
    x = grid * r
    for rc in (np.full(len(x), rc0), np.full(len(x), r), np.where(np.arange(len(x)) % 4 == 0, 2 * r, rc0)):
        tree, _ = assert_tree_matches_reference(x, rc)
        assert_all_agree(x, rc, with_kdtree=False)
    exact = assert_all_agree(x, np.full(len(x), r), with_kdtree=False)
    assert exact[0].size > 0                                     # axis neighbours at exactly the cutoff


@pytest.mark.parametrize("d", [2, 3])
def test_coincident_particles_and_equal_cutoffs(rng, d):
    x = np.repeat(rng.random((400, d)), 3, axis=0)
    assert_all_agree(x, loguniform(rng, len(x), 0.01, 10.0))
    assert_all_agree(x, 0.05)                                   # all cutoffs equal
    same = np.zeros((5, d))                                     # all particles in one point
    nl = arpy.neighbor_list(same, 0.1, method="ar")
    assert len(nl) == 10
    assert_tree_matches_reference(same, np.full(5, 0.1))


def test_one_and_zero_particles():
    for d in (2, 3):
        nl = arpy.neighbor_list(np.zeros((1, d)), 0.1, method="ar")
        assert nl.n == 1 and len(nl) == 0
        assert arpy.neighbor_list(np.zeros((0, d)), 0.1, method="ar").n == 0
        tree = arpy.ARCellList(np.zeros((1, d)), 0.1)
        assert tree.maxlevel == 0 and tree.cells == {1: (0, 1)}


@pytest.mark.parametrize("d", [2, 3])
def test_non_cubic_domains(rng, d):
    # an elongated set, and an explicit domain larger than the set
    x = rng.random((2000, d)) * np.array([8.0, 1.0, 0.5][:d])
    rc = loguniform(rng, len(x), 0.003, 50.0)
    assert_all_agree(x, rc)
    domain = (np.full(d, -1.0), np.array([9.0, 2.0, 3.0][:d]))
    tree, _ = assert_tree_matches_reference(x, rc, domain=domain)
    assert tree.edge == fitted_root(10.0, rc, arpy.lists.ar.MAX_LEVEL[d]) >= 10.0
    assert_same_pairs(tree.verlet_list().pairs(), brute_force_pairs(x, rc))


@pytest.mark.parametrize("d", [2, 3])
def test_skin(rng, d):
    x = rng.random((1500, d))
    rc = loguniform(rng, len(x), 0.005, 20.0)
    assert_all_agree(x, rc, skin=0.01)
    tree = arpy.ARCellList(x, rc)
    for full in (False, True):
        nl = tree.verlet_list(skin=0.01, full=full)
        assert_same_pairs(nl.pairs(), brute_force_pairs(x, rc, 0.01))
    assert_tree_matches_reference(x, rc, skin=0.01)


@pytest.mark.parametrize("d", [2, 3])
def test_operations_match_reference(rng, d):
    x = clustered_points(rng, 1500, d)
    rc = loguniform(rng, len(x), 0.002, 200.0)
    tree, ref = assert_tree_matches_reference(x, rc)
    keys = list(tree.cells)[:: max(1, len(tree.cells) // 60)] + sorted(tree.finer)[:20]
    for J in keys:
        k = tree.cell_level(J)
        assert tree.parent(J) == ref.parent(J)
        if k < 20:
            assert tree.children(J) == ref.children(J)
            assert all(tree.parent(c) == J for c in tree.children(J))
        assert sorted(tree.neighbor_cells(J)) == sorted(ref.neighbor_cells(J))
        assert set(tree.particles_in_cell(J).tolist()) == set(ref.particles_in_cell(J).tolist())
        assert tree.has_finer(J) == ref.has_finer(J)
    for p in rng.integers(0, len(x), 50):
        for k in (0, 1, int(tree.level[p]), tree.maxlevel):
            J = tree.find_cell(x[p], k)
            assert J == ref.find_cell(x[p], k)
        # each particle lies in the cell of its own level that lists it
        J = tree.find_cell(x[p], int(tree.level[p]))
        assert p in tree.particles_in_cell(J)
    assert tree.find_cell(tree.lo - 1.0, 2) is None


@pytest.mark.parametrize("d", [2, 3])
def test_cross_set_lists(rng, d):
    x = clustered_points(rng, 2000, d)
    rc = loguniform(rng, len(x), 0.002, 100.0)
    xq = rng.random((700, d)) * 1.6 - 0.3          # also outside the reference domain
    rq = loguniform(rng, len(xq), 0.002, 200.0)
    nl = arpy.cross_neighbor_list(xq, rq, x, rc)
    assert nl.cross and nl.n == len(xq) and nl.n_ref == len(x)
    bi, bj = brute_force_cross_pairs(xq, rq, x, rc)
    qi, qj = nl.pairs()
    np.testing.assert_array_equal(qi, bi)
    np.testing.assert_array_equal(qj, bj)
    # each row ascending, so the canonical form is the list itself
    step = np.diff(nl.indices.astype(np.int64))
    inner = np.ones(step.size, bool)
    starts = nl.offsets[1:-1]
    inner[starts[(starts > 0) & (starts < len(nl))] - 1] = False      # (a pair across two rows)
    assert np.all(step[inner] > 0)
    canon = nl.canonical()
    np.testing.assert_array_equal(canon.indices, nl.indices)
    # the reference's cross list gives the same rows
    ref = ARCellListRef(x, rc)
    off, ind = ref.cross_list(xq, rq)
    np.testing.assert_array_equal(nl.offsets, off)
    # a set against itself: the full list plus every particle itself
    self_cross = arpy.ARCellList(x, rc).cross_list(x, rc)
    full = arpy.neighbor_list(x, rc, method="ar", full=True)
    np.testing.assert_array_equal(self_cross.counts(), full.counts() + 1)


@pytest.mark.parametrize("d", [2, 3])
def test_few_pairs_cross_lists_test_every_pair(rng, d):
    """Up to BRUTE_CROSS_PAIRS pairs the cross list tests all of them: its rows are the tree's bit
    for bit (graded cutoffs, queries outside, exact ties on a lattice, lengths far from 1) and brute
    force's; bad input still gets the tree's errors."""
    from arpy.lists import search

    limit = search.BRUTE_CROSS_PAIRS
    for scale, lattice in [(1.0, False), (1e-7, False), (3e6, False), (1.0, True)]:
        x = rng.random((400, d)) * scale
        rc = loguniform(rng, len(x), 0.01, 30.0) * scale
        xq = (rng.random((limit // 400, d)) * 1.4 - 0.2) * scale
        rq = loguniform(rng, len(xq), 0.01, 60.0) * scale
        if lattice:
            x, xq = np.round(x * 8) / 8, np.round(xq * 8) / 8
            rc, rq = np.full(len(x), 0.125), np.full(len(xq), 0.25)
        few = arpy.cross_neighbor_list(xq, rq, x, rc)
        assert search._cross_brute(xq, rq, x, rc) is not None          # (this size takes that path)
        tree = arpy.ARCellList(x, rc).cross_list(xq, rq)
        np.testing.assert_array_equal(few.offsets, tree.offsets)
        np.testing.assert_array_equal(few.indices, tree.indices)
        assert few.cross and few.n_ref == len(x)
        bi, bj = brute_force_cross_pairs(xq, rq, x, rc)
        np.testing.assert_array_equal(few.pairs()[0], bi)
        np.testing.assert_array_equal(few.pairs()[1], bj)
    # one query more than the limit allows goes to the tree, with the same rows
    xq = rng.random((limit // 400 + 1, d))
    assert search._cross_brute(xq, 0.1, x, rc) is None
    # invalid input: the tree's errors
    bad = x.copy()
    bad[7, 0] = np.nan
    with pytest.raises(ValueError, match="particle 7"):
        arpy.cross_neighbor_list(xq[:3], 0.1, bad, rc)
    with pytest.raises(ValueError):
        arpy.cross_neighbor_list(xq[:3], -0.1, x, rc)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("method", ["ar", "cell", "brute"])
def test_periodic_boxes(rng, d, method):
    length = np.array([2.0, 1.0, 1.5][:d])
    x = rng.random((1200, d)) * length
    rc = loguniform(rng, len(x), 0.004, 50.0)
    bi, bj = brute_force_pairs(x, rc, period=length)
    assert np.any(np.abs(x[bi] - x[bj]) > 0.5 * length), "no pair crosses the boundary"
    for full in (False, True):
        nl = arpy.neighbor_list(x, rc, method=method, full=full, domain=arpy.Domain(length, periodic=True))
        check_csr(nl, len(x))
        i, j = nl.pairs()
        np.testing.assert_array_equal(i, bi)
        np.testing.assert_array_equal(j, bj)
    lo = np.full(d, -3.0)
    shifted = arpy.neighbor_list(x + lo, rc, method=method, domain=arpy.Domain((lo, lo + length), periodic=True)).pairs()
    assert shifted[0].size == bi.size


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_uniform_grid_wraps_around_a_periodic_box(seed):
    """The uniform list in a periodic box wraps its grid instead of making images (at least 3
    cells per periodic axis): the same pairs as the images (method "brute") and brute force, with
    particles on both faces, ties at the cutoff, mixed axes, a box away from the origin; a box of
    2 cells per axis falls back to the images; rows the same at 1 and 2 threads.  (The images
    themselves are checked against brute force and cKDTree in the tests below.)"""
    rng = np.random.default_rng(seed)
    for d, per in ((2, True), (2, (True, False)), (3, (False, True, True)), (3, True)):
        lo, length = np.full(d, -1.25), np.array([1.0, 0.75, 0.5][:d])
        n = 2500
        x = lo + rng.random((n, d)) * length
        x[:40, 0], x[40:80, 0] = lo[0], lo[0] + length[0]                   # on both faces of axis 1
        x[80:120] = lo + np.round((x[80:120] - lo) / 0.05) * 0.05           # a lattice: ties at 0.05
        rc = np.where(rng.random(n) < 0.5, 0.05, rng.uniform(0.02, 0.12, n))
        box = arpy.Domain((lo, lo + length), periodic=per)
        want = arpy.neighbor_list(x, rc, method="brute", domain=box).pairs()
        for full in (False, True):
            got = arpy.neighbor_list(x, rc, method="cell", domain=box, full=full)
            assert all(np.array_equal(a, b) for a, b in zip(got.pairs(), want))
    x = rng.random((400, 2))                                      # max cutoff 0.45: 2 cells, images
    rc = rng.uniform(0.1, 0.45, 400)
    torus = arpy.Domain([1.0, 1.0], periodic=True)
    assert all(np.array_equal(a, b) for a, b in zip(arpy.neighbor_list(x, rc, domain=torus).pairs(),
                                                    arpy.neighbor_list(x, rc, method="brute", domain=torus).pairs()))
    x = rng.random((60_000, 2))                                   # parallel pencils
    lists = []
    for threads in (1, 2):
        with arpy.num_threads(threads):
            lists.append(arpy.neighbor_list(x, 0.006, domain=torus))
    assert np.array_equal(lists[0].offsets, lists[1].offsets) and np.array_equal(lists[0].indices, lists[1].indices)


@pytest.mark.parametrize("d", [2, 3])
def test_periodic_lists_equal_ckdtree_with_boxsize(rng, d):
    """Every method's periodic list (built in the core from images) holds the pairs scipy's cKDTree
    finds with boxsize, each once (symmetric) or in both rows (full); a lattice puts particles on
    the faces and distances exactly at the cutoff."""

    length = np.array([2.0, 1.0, 1.5][:d])
    sets = [(rng.random((3000, d)) * length, rng.uniform(0.02, 0.2, 3000)),
            (lattice_points(d, 8, 0.125), np.full(8 ** d, 0.25))]
    for x, rc in sets:
        box = length if len(x) == 3000 else np.full(d, 1.0)
        want = kdtree_pairs(x, rc, boxsize=box)
        assert want[0].size > 100
        for method in ("cell", "ar", "brute"):
            for full in (False, True):
                nl = arpy.neighbor_list(x, rc, method=method, full=full, domain=arpy.Domain(box, periodic=True))
                check_csr(nl, len(x))
                assert len(nl) == want[0].size * (2 if full else 1)
                i, j = nl.pairs()
                np.testing.assert_array_equal(i, want[0])
                np.testing.assert_array_equal(j, want[1])


def test_periodic_ghosts_only_within_own_cutoff_of_a_face(rng):
    length = np.array([1.0, 2.0])
    x = rng.random((500, 2)) * length
    rc = rng.uniform(0.01, 0.2, len(x))
    xg, src = arpy.periodic_ghosts(x, rc, arpy.Domain(length, periodic=True))
    shift = xg - x[src]
    # every ghost is its source moved by whole box edges, and lands outside the box
    np.testing.assert_allclose(shift / length, np.round(shift / length), atol=1e-12)
    assert np.all(np.any((xg < 0) | (xg > length), axis=1))
    # ...and the source was within its own cutoff of every face it was imaged across
    k = np.round(shift / length)
    near = np.where(k > 0, x[src], np.where(k < 0, length - x[src], 0.0))
    assert np.all(near <= rc[src][:, None] + 1e-15)
    # each particle near one face has exactly one image; near a corner three
    n_faces = ((x <= rc[:, None]) | (length - x <= rc[:, None])).sum(axis=1)
    np.testing.assert_array_equal(np.bincount(src, minlength=len(x)), 2 ** n_faces - 1)
    with pytest.raises(ValueError, match="box too small"):
        arpy.periodic_ghosts(x, 0.6, arpy.Domain(length, periodic=True))
    with pytest.raises(ValueError, match="outside the periodic box"):
        arpy.periodic_ghosts(x + 5.0, rc, arpy.Domain(length, periodic=True))


def test_periodic_nearest_is_the_minimum_image(rng):
    """arpy.domain.nearest against brute-force minimum-image distances, with the box
    given as edge lengths and as (lo, hi)."""
    from arpy.domain import nearest

    length = np.array([1.0, 2.0])
    x, y = rng.random((300, 2)) * length, rng.random((40, 2)) * length
    d = np.abs(y[:, None, :] - x[None, :, :])
    d = np.sqrt((np.minimum(d, length - d) ** 2).sum(axis=2))
    for box in (length, (np.full(2, -1.0), length - 1.0)):
        shift = 0.0 if box is length else -1.0
        dist, j = nearest(x + shift, 2, y=y + shift, domain=arpy.Domain(box, periodic=True))
        np.testing.assert_allclose(dist, np.sort(d, axis=1)[:, :2], atol=1e-12)
        np.testing.assert_allclose(d[np.arange(40)[:, None], j], dist, atol=1e-12)


class _SpyCore:
    """Stands in for arpy._core in arpy._bridge (the one module that calls the core): records the
    method code of every arpy_neighbors call and passes everything on to the real core."""

    def __init__(self, core):
        self._core, self.codes = core, []

    def arpy_neighbors(self, x, rc, skin, method, *rest):
        self.codes.append(int(method))
        return self._core.arpy_neighbors(x, rc, skin, method, *rest)

    def arpy_periodic_neighbors(self, x, rc, skin, method, *rest):
        self.codes.append(int(method))
        return self._core.arpy_periodic_neighbors(x, rc, skin, method, *rest)

    def __getattr__(self, name):
        return getattr(self._core, name)


def _capped_cells(pts, lo, ext, c, most):
    """The cells of points pts (k, d) on the grid over the box lo + [0, ext] with cells of edge c, or
    of edge (prod(ext) / most)**(1 / d) where that grid has more than ``most`` cells (points outside
    in its border cells, NaN in cell 0); (cells, g), or (None, g) when an axis still has more."""
    d = len(ext)
    g = c
    if np.prod(np.ceil(ext / c)) > most:
        g = max(c, (np.prod(ext) / most) ** (1.0 / d))
    if np.max(ext / g) > most:
        return None, g
    top = np.maximum(np.ceil(ext / g), 1) - 1
    return np.clip(np.floor(np.nan_to_num((pts - lo) / g, nan=0.0)), 0, top), g


def _near(ca, cb):
    """near[i, j]: cells ca[i] and cb[j] differ by at most 1 along every axis."""
    return np.all(np.abs(ca[:, None, :] - cb[None, :, :]) <= 1, axis=2)


def position_hashes(x):
    """The hash of auto_terms' samples (arpy_crowding.position_hashes), from each position's bits
    alone: int64 in [0, 2**53)."""
    bits = np.ascontiguousarray(x, dtype=np.float64).view(np.uint64)
    k = [np.uint64(0x9E3779B97F4A7C15), np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)]
    with np.errstate(over="ignore"):
        z = np.zeros(len(x), np.uint64)
        for a in range(x.shape[1]):
            z ^= bits[:, a] * k[a]
        z = (z ^ (z >> np.uint64(31))) * np.uint64(6364136223846793005)
        z = z ^ (z >> np.uint64(29))
        u = z >> np.uint64(11)
    return u.astype(np.int64)


def hash_sample(u, frac):
    """The indices (ascending) whose hash u is below the fraction frac of 2**53 (all for frac >= 1)."""
    return np.arange(len(u)) if frac >= 1 else np.flatnonzero(u < int(frac * 2.0 ** 53))


def documented_terms(x, rc, skin=0.0, rule="min"):
    """(W_cell, W_own, W_finer, W_look, W_hash, W_dense) as auto_work's docstring defines them (under the
    max and sum rules W_coarse and W_up in place of W_finer and W_look), computed independently in NumPy:
    levels from log2, the level sums written out, every count by comparing the grid cells of every two
    particles concerned, and the AR tree's dense and hashed levels by its rule written out."""
    s = arpy.lists.auto
    n, d = x.shape
    u = position_hashes(x)
    frac = min(n, s.AUTO_SAMPLE, max(s.AUTO_SAMPLE_LEAST, n // s.AUTO_SAMPLE_SHARE)) / n
    pick = hash_sample(u, frac)
    reach = (2.0 if rule == "sum" else 1.0) * rc + skin             # (the level reach: 2 rc + skin under the sum rule)
    xs, r = x[pick], reach[pick]
    m = len(xs)
    r_min, r_max = reach.min(), reach.max()
    low = xs.min(axis=0)
    edges = np.maximum(xs.max(axis=0) - low, r_max)
    occ = lambda c, k: k * np.prod(np.minimum(1.0, 3.0 * c / edges))   # noqa: E731
    base = np.nextafter(r_min, np.inf)
    level = np.floor(np.log2(r / base)).astype(int) + 1       # base * 2**level: the smallest such edge above r
    assert np.all(base * 2.0 ** level > r) and np.all(base * 2.0 ** (level - 1) <= r)
    k0 = level.min()
    held = sorted(set(level.tolist()))
    n_k = {k: np.count_nonzero(level == k) * n / m for k in held}
    finer = {k: sum(occ(base * 2.0 ** i, n_k[i]) for i in held if i < k) for k in held}
    if rule != "min":
        # searched from the fine side: every coarser level that holds particles, counted over all of them
        every = np.floor(np.log2(reach / base)).astype(int) + 1
        n_all = {j: np.count_nonzero(every == j) for j in set(every.tolist())}
        finer = {k: sum(occ(base * 2.0 ** j, c) for j, c in n_all.items() if j > k) for k in held}
        w_up = n * 3 ** d * np.mean([sum(j > k for j in n_all) for k in level])
    w_cell = n / 2 * occ(r_max, n)
    w_finer = n * np.mean([finer[k] for k in level])
    crowd = 1.0
    if occ(r_max, 1.0) > 0:
        # the crowding of every q-th sampled particle: the others among them in its 3**d cells of edge r_max
        q = max(1, int(m / np.sqrt(s.AUTO_CROWD_PAIRS / occ(r_max, 1.0))))
        sub = u[pick] * 2.0 ** -53 < frac / q                 # (the sampled particles of the smallest hashes)
        xc, lq = xs[sub], level[sub]
        cells, g = _capped_cells(xc, low, edges, r_max, s.AUTO_CROWD_CELLS * len(xc))
        if cells is not None:
            others = _near(cells, cells).sum(axis=1) - 1
            f = others * (n - 1) / max(len(xc) - 1, 1) * (occ(r_max, 1.0) / occ(g, 1.0)) / occ(r_max, n)
            crowd = f.mean()
            w_finer = n * np.mean([fi * finer[k] for fi, k in zip(f, lq)])
    # the AR tree's tables: from its coarsest level below the root (edge base 2**K, K the fewest doublings that
    # reach the sample's largest extent) to the finest, a level is dense if the box of the particles on it or
    # finer has at most 4 cells per such particle (+ 1024), within a total of 4 n + 4096 cells (W_dense: those
    # cells and a sentinel each), else hashed; a particle enters a cell on its own and every coarser level
    top = 0
    while base * 2.0 ** top < (xs.max(axis=0) - low).max():
        top += 1
    hashed, w_dense = set(), 0.0
    for k in range(top - 1, k0 - 1, -1):
        on = level <= k
        if not on.any():
            continue
        cells = np.prod(np.floor((xs[on].max(axis=0) - xs[on].min(axis=0)) / (base * 2.0 ** k)) + 1)
        if cells > 4 * n * on.sum() / m + 1024 or w_dense + cells > 4 * n + 4096:
            hashed.add(k)
        else:
            w_dense += cells + 1
    w_hash = n * np.mean([sum(j in hashed for j in range(k, top)) for k in level])
    w_look = 0.0 if rule == "min" else w_up
    if len(held) == 1:
        return w_cell * crowd, n / 2 * occ(base * 2.0 ** held[0], n) * crowd, w_finer, w_look, w_hash, w_dense
    # on its own level: the other sampled particles of its level in the 3**d cells of its edge, on a grid over
    # the level's box
    own = np.zeros(m)
    for k in held:
        at = np.flatnonzero(level == k)
        if at.size < 2:
            continue
        c = base * 2.0 ** k
        lo_k = xs[at].min(axis=0)
        ext_k = np.maximum(xs[at].max(axis=0) - lo_k, c)
        cells, g = _capped_cells(xs[at], lo_k, ext_k, c, s.AUTO_LEVEL_CELLS * at.size)
        if cells is not None:
            scale = np.prod(np.minimum(1.0, 3.0 * c / ext_k) / np.minimum(1.0, 3.0 * g / ext_k))
            own[at] = (_near(cells, cells).sum(axis=1) - 1) * scale
    w_own = n / 2 * (n / m) * own.mean()
    if rule != "min":
        return w_cell * crowd, w_own, w_finer, w_look, w_hash, w_dense
    # the levels it descends through: down to the finest among a second sample in its 3**d cells (by the
    # same hash: the sample's particles among them, on their own levels, do not change it)
    fine = hash_sample(u, min(n, s.AUTO_FINE_SAMPLE, max(s.AUTO_SAMPLE_LEAST, n // s.AUTO_FINE_SHARE)) / n)
    xf, rf = x[fine], rc[fine] + skin
    ok = (rf > 0) & np.isfinite(rf)
    lev_f = np.maximum(np.floor(np.log2(rf[ok] / base)).astype(int) + 1 - k0, 0)
    cells, g = _capped_cells(np.concatenate([xf[ok], xs]), low, edges, r_max, s.AUTO_FINE_CELLS * len(xf))
    if cells is not None:
        near = _near(cells[len(lev_f):], cells[:len(lev_f)])
        finest = np.array([lev_f[row].min() if row.any() else np.inf for row in near])
        depth = (level - k0) - np.minimum(finest, level - k0)
        w_look = n * 3 ** d * depth.mean()
    return w_cell * crowd, w_own, w_finer, w_look, w_hash, w_dense


def documented_auto_work(x, rc, skin=0.0, rule="min"):
    """(T_cell, T_ar) as auto_work's docstring defines them: its cost model applied to documented_terms."""
    s = arpy.lists.auto
    n, d = x.shape
    w_cell, w_own, w_finer, w_look, w_hash, w_dense = documented_terms(x, rc, skin, rule)
    cell, ar = s.AUTO_CELL_COST, s.AUTO_AR_COST
    decades = np.log10(max(n, ar["lookup_from"]) / ar["lookup_from"])
    search = (ar["finer"] * w_finer + (ar["lookup"] + ar["lookup_decade"] * decades) * w_look if rule == "min"
              else ar["coarse"] * w_finer + ar["up"] * w_look)
    return (cell["particle"][d] * n + cell["check"] * w_cell,
            ar["particle"][d] * n + ar["own"] * w_own + search
            + (ar["hashed"] + ar["hashed_decade"] * decades) * w_hash + ar["empty"] * max(w_dense - n, 0.0))


def adapted_cluster(rng, n, d, width=0.05):
    """Half of n particles uniform in the unit box, half in a Gaussian cluster of std ``width`` at its
    centre, each cutoff from the density there for about 16 neighbours: small cutoffs where the
    particles crowd, as in adapted sets."""
    m = n // 2
    x = np.concatenate([np.clip(0.5 + width * rng.standard_normal((n - m, d)), 0, 1), rng.random((m, d))])
    density = ((n - m) * np.exp(-0.5 * np.sum((x - 0.5) ** 2, axis=1) / width ** 2)
               / (2 * np.pi * width ** 2) ** (d / 2) + m)
    return x, (16 / (density * (np.pi if d == 2 else 4 * np.pi / 3))) ** (1 / d)


@pytest.mark.parametrize("d", [2, 3])
def test_auto_picks_ar_where_the_uniform_list_is_estimated_slower(rng, d, monkeypatch):
    """method="auto" passes the AR code to the core iff the uniform list's estimated time exceeds
    AUTO_AR_WORK times the AR list's (the model of auto_work's docstring, recomputed here), and its lists
    equal brute force either way: one cutoff, rare large cutoffs (2D: the AR list; 3D: the uniform list,
    the small ones sparse), the AR paper's benchmark, random log-uniform cutoffs, a skin, more particles
    than the sample, and a periodic box; in 2D an adapted cluster (small cutoffs where the particles
    crowd: the AR list, measured 2.7 times faster: benchmarks/results/auto_calibration.md) and the
    same with far outliers (coarse grids); cutoffs that are not all > 0 leave the choice to "cell"
    (whose search reports them)."""
    import arpy._bridge as bridge

    spy = _SpyCore(bridge._core)
    monkeypatch.setattr(bridge, "_core", spy)
    n = 1500 if d == 2 else 1000
    x = rng.random((n, d))
    few = np.where(rng.random(n) < 0.05, 0.2, 0.2 / 30)       # 5 % of the particles reach 30 times as far
    x_paper, rc_paper = arpy.ar_benchmark(2000, 50.0, d)
    cases_ = [("one cutoff", x, np.full(n, 0.05), 0.0, None),
              ("log-uniform, span 1e3", x, loguniform(rng, n, 0.002, 1e3), 0.0, None),
              ("log-uniform, span 10, skin", x, loguniform(rng, n, 0.01, 10.0), 0.01, None),
              # (in 3D the small particles have a few thousandths of a neighbour each: the AR tree hashes their
              # level, and the uniform list was measured 2.1 times faster, 0.36 ms against 0.75 ms; in 2D the
              # AR list 2.3 times faster)
              ("bimodal, 5 % large", x, few, 0.0, "ar" if d == 2 else "cell"),
              ("paper, lambda = 50", x_paper, rc_paper, 0.0, None)]
    if d == 2:
        x_crowd, rc_crowd = adapted_cluster(np.random.default_rng(5), 3000, d, 0.03)
        cases_.append(("adapted cluster", x_crowd, rc_crowd, 0.0, "ar"))
        # (five far particles widen the box: the crowding is counted on a grid coarser than r_max)
        far = np.concatenate([x_crowd, 300.0 * np.random.default_rng(6).random((5, d))])
        cases_.append(("adapted cluster, far outliers", far, np.concatenate([rc_crowd, np.full(5, 0.05)]), 0.0, None))
    for name, xc, rc, skin, want in cases_:
        w_cell, w_ar = arpy.lists.auto.auto_work(xc, rc, skin)
        assert (w_cell, w_ar) == pytest.approx(documented_auto_work(xc, rc, skin), rel=1e-12), name
        pick = "ar" if w_cell > arpy.AUTO_AR_WORK * w_ar else "cell"
        assert want in (None, pick), name
        expected = brute_force_pairs(xc, rc, skin)
        for full in (False, True):
            spy.codes.clear()
            nl = arpy.neighbor_list(xc, rc, method="auto", full=full, skin=skin)
            assert spy.codes == [arpy.METHODS[pick]], (name, spy.codes)
            assert len(nl) == expected[0].size * (2 if full else 1)
            assert_same_pairs(nl.pairs(), expected)
    # more particles than the sample: every k-th of them
    big = rng.random((2 * arpy.lists.auto.AUTO_SAMPLE + 7, d))
    rc_big = loguniform(rng, len(big), 0.01, 100.0)
    assert arpy.lists.auto.auto_work(big, rc_big) == pytest.approx(documented_auto_work(big, rc_big), rel=1e-12)
    # periodic box: the choice from the particles' own statistics
    box = arpy.Domain(np.ones(d), periodic=True)
    for rc in (np.full(n, 0.04), few):
        w_cell, w_ar = arpy.lists.auto.auto_work(x, rc)
        spy.codes.clear()
        got = arpy.neighbor_list(x, rc, method="auto", domain=box).pairs()
        assert spy.codes == [arpy.METHODS["ar" if w_cell > arpy.AUTO_AR_WORK * w_ar else "cell"]]
        assert_same_pairs(got, arpy.neighbor_list(x, rc, method="brute", domain=box).pairs())
    # cutoffs the search refuses: no estimate, "cell" reports them
    for bad in (np.where(np.arange(n) == 3, 0.0, 0.05), np.where(np.arange(n) == 3, np.nan, 0.05)):
        assert arpy.lists.auto.auto_work(x, bad) == (0.0, 0.0)
        spy.codes.clear()
        with pytest.raises(ValueError):
            arpy.neighbor_list(x, bad, method="auto")
        assert spy.codes in ([], [arpy.METHODS["cell"]])
    # an explicit method is passed through unchanged
    for method in ("brute", "cell", "ar"):
        spy.codes.clear()
        arpy.neighbor_list(x, 0.05, method=method)
        assert spy.codes == [arpy.METHODS[method]]


@pytest.mark.parametrize("d, side", [(2, 180), (2, 333), (3, 41)])
def test_auto_statistics_see_the_pairs_of_a_lattice_in_order(d, side):
    """auto_terms samples at random (a fixed hash), not every (n/m)-th particle: on a lattice given in
    row order a strided sample is a coarser lattice with no two particles near each other, and every
    statistic came out 0 (the AR paper's benchmark at N = 1e6).  Here the uniform list's estimated checks
    are within 25 % of its checks counted from the cells' occupancy, for lattices of several sizes, and
    the AR list's own-level checks (one cutoff: the same cells) within 25 % of them too."""
    from arpy._bench import uniform_checks

    axes = [np.arange(side, dtype=float)] * d
    x = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, d)      # (row order)
    rc = np.full(len(x), 1.5)
    w_cell, w_own, w_finer, w_look, _, _ = arpy.lists.auto.auto_terms(x, rc)
    want = uniform_checks(x, rc)
    assert 0.75 * want < w_cell < 1.25 * want
    assert 0.75 * want < w_own < 1.25 * want and w_finer == 0 and w_look == 0


@pytest.mark.parametrize("d", [2, 3])
def test_auto_statistics_do_not_depend_on_the_particles_order(rng, d):
    """auto_terms draws its samples by a hash of each position, not by index: the same particles in
    another order give the same statistics (up to the order of the sums) and the same choice, for sets
    larger than the sample (a clustered adapted set with several levels, a log-uniform one); and the
    same bits at 1 and 2 threads (its pass over the particles runs in parallel from 20,000 of them, in
    ranges joined in order)."""
    sets = [adapted_cluster(np.random.default_rng(11), 20000 if d == 2 else 12000, d, 0.05),
            (rng.random((30000, d)), loguniform(rng, 30000, 0.005, 50.0))]
    for x, rc in sets:
        perm = rng.permutation(len(x))
        with arpy.num_threads(2):
            a2 = arpy.lists.auto.auto_terms(x, rc)
        with arpy.num_threads(1):
            a = arpy.lists.auto.auto_terms(x, rc)
        assert a2 == a                                             # (bitwise)
        b = arpy.lists.auto.auto_terms(x[perm], rc[perm])
        assert a == pytest.approx(b, rel=1e-12) and min(a) >= 0 and a[0] > 0
        assert a == pytest.approx(documented_terms(x, rc), rel=1e-12)


@pytest.mark.parametrize("d", [2, 3])
def test_auto_statistics_see_the_ar_trees_hashed_levels(rng, d):
    """W_hash, the cells the particles enter on the levels the AR tree hashes: with one cutoff r on n
    uniform particles in the unit box they all sit on the level whose cells are just wider than r,
    (2**K)**d of them over the box (K the fewest doublings of r that reach the box), and the tree hashes
    that level when those cells are more than 4 n + 1024 (arpy_arbuild's plan_dense), the coarser ones
    staying dense: at 4 neighbours per particle every level dense (W_hash = 0), at 0.25 the particles'
    own level hashed (W_hash = n), where the AR list costs 4-5 times more per particle."""
    n = 20000
    x = rng.random((n, d))
    for neighbours, hashed in ((4.0, False), (0.25, True)):
        r = (neighbours / (n * (np.pi if d == 2 else 4 * np.pi / 3))) ** (1 / d)
        k = int(np.ceil(np.log2(1 / r)))
        assert (2 ** (k * d) > 4 * n + 1024) == hashed          # (the level's cells, by the tree's rule)
        w = arpy.lists.auto.auto_terms(x, np.full(n, r))
        assert w[4] == (n if hashed else 0.0) and 0 < w[5] <= 4 * n + 4096, (neighbours, w)
        assert w == pytest.approx(documented_terms(x, np.full(n, r)), rel=1e-12)


def contact_radii(r, d, contacts):
    """Radii r (n,) scaled for about ``contacts`` sum-rule contacts per particle among n uniform particles
    in the unit box (the mean ball of r_p + r_q from the radii's moments)."""
    n = len(r)
    m1, m2, m3 = (np.mean(r ** k) for k in (1, 2, 3))
    mean = 2 * m2 + 2 * m1 ** 2 if d == 2 else 2 * m3 + 6 * m2 * m1
    return r * (contacts / (n * (np.pi if d == 2 else 4 * np.pi / 3) * mean)) ** (1 / d)


@pytest.mark.parametrize("d", [2, 3])
def test_auto_statistics_under_the_max_and_sum_rules(rng, d):
    """Under the max and sum rules the AR list searches from the fine side: auto_terms gives W_coarse and
    W_up (the coarser levels' particles in the 3**d stencils, the stencil cells looked up there) in place
    of W_finer and W_look, with each particle's level that of its level reach (2 rc + skin under the sum
    rule) and the uniform list's cells as wide as the largest reach; equal to the NumPy reference of the
    documented model (log-uniform, log-normal and one radius, a skin), the same bits at 1 and 2 threads
    (its count of every level runs in parallel), and the min rule's statistics unchanged by the rule
    argument.  The levels the fine particles search are counted over every particle, not the sample: three
    huge radii among 30,000 (none of them sampled) put every particle one level below them (W_up = 3**d n)."""
    n = 30000
    x = rng.random((n, d))
    sets = [(loguniform(rng, n, 0.002, 100.0), 0.0), (contact_radii(np.exp(rng.normal(0, 1, n)), d, 6.0), 0.0),
            (np.full(n, 0.01), 0.002), (loguniform(rng, n, 0.003, 10.0), 0.001)]
    for rc, skin in sets:
        for rule in ("max", "sum"):
            with arpy.num_threads(2):
                w2 = arpy.lists.auto.auto_terms(x, rc, skin, rule)
            with arpy.num_threads(1):
                w = arpy.lists.auto.auto_terms(x, rc, skin, rule)
            assert w == w2, rule                                               # (bitwise)
            assert w == pytest.approx(documented_terms(x, rc, skin, rule), rel=1e-12), rule
            assert arpy.lists.auto.auto_work(x, rc, skin, rule) == pytest.approx(
                documented_auto_work(x, rc, skin, rule), rel=1e-12)
        assert arpy.lists.auto.auto_terms(x, rc, skin, "min") == arpy.lists.auto.auto_terms(x, rc, skin)
    rc = np.full(n, 0.004)
    s = arpy.lists.auto
    sample = hash_sample(position_hashes(x), min(n, s.AUTO_SAMPLE, max(s.AUTO_SAMPLE_LEAST, n // s.AUTO_SAMPLE_SHARE)) / n)
    rc[np.setdiff1d(np.arange(n), sample)[[5, 500, 5000]]] = 0.3
    for rule in ("max", "sum"):
        w = arpy.lists.auto.auto_terms(x, rc, 0.0, rule)
        assert w[3] == 3 ** d * n and w[2] > 0, (rule, w)
        assert w == pytest.approx(documented_terms(x, rc, 0.0, rule), rel=1e-12)


@pytest.mark.parametrize("d", [2, 3])
def test_auto_under_the_sum_and_max_rules_takes_the_list_measured_faster(rng, d, monkeypatch):
    """Under the sum and max rules "auto" takes the AR list where a few radii are very large (log-normal
    radii, ln(100) / 4.6 the logarithm's standard deviation: the uniform list's cells are as wide as the
    largest reach) and the uniform list for radii log-uniform over a factor 100, and its lists equal brute
    force (the core's, which tests/test_rules.py holds to the NumPy reference).  (Measured on such sets at N = 1e4, benchmarks/results/auto_rules.md: sum rule, the uniform list
    9.7x (2D) and 5.3x (3D) slower than the AR list on the log-normal radii, 2.2x and 1.3x faster on the
    log-uniform ones.)"""
    import arpy._bridge as bridge

    spy = _SpyCore(bridge._core)
    monkeypatch.setattr(bridge, "_core", spy)
    n = 10000
    x = rng.random((n, d))
    few_large = contact_radii(np.exp(rng.normal(0.0, np.log(100.0) / 4.6, n)), d, 6.0)
    log_uniform = contact_radii(np.exp(rng.uniform(0.0, np.log(100.0), n)), d, 6.0)
    for rule in ("sum", "max"):
        for rc, want in ((few_large, "ar"), (log_uniform, "cell")):
            spy.codes.clear()
            nl = arpy.neighbor_list(x, rc, method="auto", rule=rule)
            assert spy.codes == [arpy.METHODS[want]], (rule, want)
            assert_same_pairs(nl.pairs(), arpy.neighbor_list(x, rc, method="brute", rule=rule).pairs())


def test_crowding_counts_are_the_other_sampled_particles_in_the_block_around_each(rng):
    """The core's crowding statistic (auto_work): of each sampled particle x[::step], the other sampled
    particles whose grid cells differ from its own by at most 1 along every axis, particles outside the
    grid (and NaN) counted in its border cells; against every pair compared in NumPy."""
    from arpy import _bridge

    for d, step in ((2, 1), (2, 3), (3, 2)):
        x = rng.random((400, d)) * 1.6 - 0.3                    # (a margin outside the grid on every side)
        x[7] = np.nan
        lo, g, nc = np.zeros(d), 0.13, [8, 5, 6][:d]
        xs = x[::step]
        c = np.clip(np.nan_to_num((xs - lo) / g, nan=0.0), 0, np.array(nc) - 1).astype(int)
        want = np.all(np.abs(c[:, None, :] - c[None, :, :]) <= 1, axis=2).sum(axis=1) - 1
        np.testing.assert_array_equal(_bridge.crowding_counts(x, step, lo, g, nc), want)
    with pytest.raises(arpy.ArpyError):                          # (a grid of no extent)
        _bridge.crowding_counts(x, 1, lo, 0.0, nc)


def _deep_set(rng, d: int) -> tuple[np.ndarray, np.ndarray]:
    """Particles on every level of an AR tree over [0, 1]^d down to the deepest one
    (arpy.lists.ar.MAX_LEVEL): at each level k a cluster of cutoffs in [2^-(k+1), 2^-k)
    around one point, spread over a few cutoffs so that they have neighbours (on their
    own level and coarser ones); a dyadic lattice of spacing 2^-(K+1) with cutoff
    exactly 2^-(K+1) (pair distances equal to the cutoff, points on cell faces of every
    level) at the deepest level K; corners fix the domain to the unit cube."""
    K = arpy.lists.ar.MAX_LEVEL[d]
    c = np.array([0.3, 0.7, 0.55][:d])
    xs, rcs = [np.array(list(itertools.product([0.0, 1.0], repeat=d)))], [np.full(2 ** d, 0.9)]
    for k in range(K + 1):
        m = 6 if k < K - 3 else 14
        xs.append(np.clip(c + rng.uniform(-0.8, 0.8, (m, d)) * 2.0 ** -k, 0.0, 1.0))
        rcs.append(rng.uniform(0.5, 1.0, m) * 2.0 ** -k)
    anchor = np.full(d, 0.5) + 2.0 ** -K                       # a dyadic point: faces of every level
    grid = np.array(list(itertools.product(range(-2, 3), repeat=d)), float)
    xs.append(anchor + grid * 2.0 ** -(K + 1))
    rcs.append(np.full(len(grid), 2.0 ** -(K + 1)))
    xs.append(xs[-1][:3].copy())                               # coincident deepest particles
    rcs.append(np.full(3, 2.0 ** -(K + 1)))
    return np.concatenate(xs), np.concatenate(rcs)


@pytest.mark.parametrize("d", [2, 3])
def test_deepest_levels_match_brute_force(rng, d):
    """Cutoffs spanning every level down to MAX_LEVEL (30 in 2D, 20 in 3D): the tree puts
    each particle on the level of the rule D_m / 2^k > rc >= D_m / 2^(k+1) (here
    D_m = 1), and the AR lists (symmetric, full, the tree's Verlet list, a cross list)
    equal brute force, including pairs of particles both on the deepest level."""
    K = arpy.lists.ar.MAX_LEVEL[d]
    x, rc = _deep_set(rng, d)
    tree = arpy.ARCellList(x, rc)
    assert tree.edge == 1.0 and tree.maxlevel == K
    want_level = -np.frexp(rc)[1]                            # rc = m 2^e, m in [0.5, 1): level -e
    want_level = np.minimum(want_level, K)                    # (none is finer than K here)
    np.testing.assert_array_equal(tree.level, want_level)
    assert np.sum(tree.level == K) >= 20
    expected = brute_force_pairs(x, rc)
    deep = (tree.level[expected[0]] == K) & (tree.level[expected[1]] == K)
    assert deep.sum() >= 20 and (tree.level[expected[0]] != tree.level[expected[1]]).sum() >= 20
    for full in (False, True):
        nl = arpy.neighbor_list(x, rc, method="ar", full=full)
        check_csr(nl, len(x))
        assert len(nl) == expected[0].size * (2 if full else 1)
        assert_same_pairs(nl.pairs(), expected)
        assert_same_pairs(tree.verlet_list(full=full).pairs(), expected)
    assert_same_pairs(arpy.neighbor_list(x, rc, method="brute").pairs(), expected)
    # queries with deep cutoffs, near the deep clusters
    xq = x[-30:] + rng.normal(scale=2.0 ** -(K + 1), size=(30, d))
    rq = rng.uniform(0.5, 1.0, 30) * 2.0 ** -K
    bi, bj = brute_force_cross_pairs(xq, rq, x, rc)
    assert bi.size >= 30
    qi, qj = tree.cross_list(xq, rq).pairs()
    np.testing.assert_array_equal(qi, bi)
    np.testing.assert_array_equal(qj, bj)
    assert_tree_matches_reference(x, rc)


def test_depth_limit_and_bad_input():
    x = np.array([[0.0, 0.0], [1.0, 1.0]])
    # the smallest cutoff needs level 30 in 2D: fine; level 31: refused
    arpy.neighbor_list(x, np.array([1.0, 2.0 ** -31]), method="ar")
    with pytest.raises(ValueError, match="too deep"):
        arpy.neighbor_list(x, np.array([1.0, 2.0 ** -32]), method="ar")
    x3 = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    arpy.ARCellList(x3, np.array([1.0, 2.0 ** -21]))
    with pytest.raises(ValueError, match="too deep"):
        arpy.ARCellList(x3, np.array([1.0, 2.0 ** -22]))
    with pytest.raises(ValueError, match="outside the given domain"):
        arpy.ARCellList(x, 0.1, domain=arpy.Domain(([0.0, 0.0], [0.5, 0.5])))
    with pytest.raises(ValueError, match="hi > lo"):
        arpy.ARCellList(x, 0.1, domain=arpy.Domain(([0.0, 0.0], [-1.0, 1.0])))
    with pytest.raises(ValueError, match="periodic"):
        arpy.ARCellList(x, 0.1, domain=arpy.Domain([2.0, 2.0], periodic=True))
    with pytest.raises(ValueError, match="not finite"):
        arpy.ARCellList(np.array([[0.0, np.nan]]), 0.1)
    with pytest.raises(ValueError, match="particle 1"):
        arpy.cross_neighbor_list(np.zeros((2, 2)), np.array([0.1, -1.0]), x, 0.1)
    with pytest.raises(ValueError, match="d = 2 columns"):
        arpy.ARCellList(x, 0.1).cross_list(np.zeros((3, 3)), 0.1)


@st.composite
def multiscale_sets(draw):
    x = points_with_ties(draw, bound=3.0, n_min=1, n_max=50, pool_max=8)
    log_rc = draw(arrays(np.float64, (len(x),), elements=st.floats(min_value=-9.0, max_value=1.0)))
    return x, np.exp(log_rc)


@settings(deadline=None)                 # examples: the profile (tests/conftest.py)
@given(multiscale_sets(), st.randoms(use_true_random=False))
def test_properties_ar(case, rnd):
    x, rc = case
    sym = arpy.neighbor_list(x, rc, method="ar")
    full = arpy.neighbor_list(x, rc, method="ar", full=True)
    expected = brute_force_pairs(x, rc)
    assert_same_pairs(sym.pairs(), expected)
    # the symmetric list is half of the full list
    assert 2 * len(sym) == len(full)
    assert_same_pairs(full.pairs(), expected)
    # invariant under a permutation of the input order
    perm = np.array(rnd.sample(range(len(x)), len(x)), dtype=np.int64)
    pi, pj = arpy.neighbor_list(x[perm], rc[perm], method="ar").pairs()
    a, b = np.minimum(perm[pi], perm[pj]), np.maximum(perm[pi], perm[pj])
    order = np.lexsort((b, a))
    assert_same_pairs((a[order], b[order]), expected)


@pytest.mark.parametrize("d", [2, 3])
def test_the_direct_full_list_equals_brute_force(rng, d):
    """Algorithm 3's asymmetric branch (each particle searching its own neighbours from the root) gives
    the rows of brute force: clustered points over five decades of cutoffs, a lattice with exact ties
    on cell faces, and the one-level case; the same rows as the expanded symmetric list."""
    sets = [(clustered_points(rng, 3000, d), None), (lattice_points(d), 0.25), (rng.random((2000, d)), 0.03)]
    for x, single in sets:
        rc = np.full(len(x), single) if single is not None else loguniform(rng, len(x), 0.002, 200.0)
        tree = arpy.ARCellList(x, rc)
        direct = tree.verlet_list(full=True, direct=True)
        raw = direct.indices.copy()
        check_csr(direct, len(x))
        bi, bj = brute_force_pairs(x, rc)
        i, j = direct.pairs()                           # each unordered pair once, as brute force gives them
        np.testing.assert_array_equal(i, bi)
        np.testing.assert_array_equal(j, bj)
        expanded = tree.verlet_list(full=True)
        np.testing.assert_array_equal(direct.canonical().indices, expanded.canonical().indices)
        np.testing.assert_array_equal(direct.offsets, expanded.offsets)
        with arpy.num_threads(2):                      # blocks of rows joined in order: the same bits
            two = tree.verlet_list(full=True, direct=True)
        with arpy.num_threads(1):
            one = tree.verlet_list(full=True, direct=True)
        assert np.array_equal(two.indices, one.indices) and np.array_equal(two.indices, raw)
    with pytest.raises(ValueError, match="full list"):
        tree.verlet_list(direct=True)


@pytest.mark.parametrize("d", [2, 3])
def test_the_ghost_ghost_filter_counts_every_pair_of_a_decomposed_box_once(d):
    """§2.4 of the AR paper: a periodic box cut into subdomains along x, each with halo layers on its
    upper faces only (a ghost: a particle or periodic image within its own cutoff beyond an upper
    face), symmetric AR lists with the ghost-ghost filter (arpy.lists.ar.halo_bits).  Mapped to
    global particles, the pairs of all subdomains together are the brute-force pairs of the whole
    periodic box, each exactly once; without the filter, pairs of ghosts in one halo come twice."""
    rng = np.random.default_rng(d)
    edge = np.array([2.0] + [1.0] * (d - 1))
    n = 1500 if d == 2 else 2500
    x = rng.random((n, d)) * edge
    rc = 0.04 + 0.1 * rng.random(n) ** 3
    want = set(zip(*(a.tolist() for a in brute_force_pairs(x, rc, period=edge))))
    shifts = np.array(list(itertools.product((0.0, 1.0), repeat=d))) * edge      # images up and right only
    got, unfiltered = [], []
    for lo_x in (0.0, 1.0):
        lo, hi = np.array([lo_x] + [0.0] * (d - 1)), np.array([lo_x + 1.0] + [1.0] * (d - 1))
        xi = (x[None] + shifts[:, None]).reshape(-1, d)
        gid = np.tile(np.arange(n), len(shifts))
        ri = np.tile(rc, len(shifts))
        inside = np.all((xi >= lo) & (xi < hi), axis=1)
        halo = np.all((xi >= lo) & (xi < hi + ri[:, None]), axis=1) & ~inside
        keep = inside | halo
        xs, gs, rs = xi[keep], gid[keep], ri[keep]
        bits = arpy.lists.ar.halo_bits(xs, lo, hi)
        assert np.array_equal(bits == 0, inside[keep])
        tree = arpy.ARCellList(xs, rs, domain=arpy.Domain(np.stack([lo, hi + rs.max()])))
        for out, b in ((got, bits), (unfiltered, None)):
            nl = tree.verlet_list(ghost_bits=b)
            i, j = gs[nl.rows()], gs[nl.indices]
            out += list(zip(np.minimum(i, j).tolist(), np.maximum(i, j).tolist()))
    assert len(got) == len(set(got)) and set(got) == want
    assert len(unfiltered) > len(got) and set(unfiltered) == want
    tree = arpy.ARCellList(x, rc)
    full = tree.verlet_list(full=True, ghost_bits=np.zeros(n, int))      # no ghosts: nothing dropped
    np.testing.assert_array_equal(np.stack(full.pairs()), np.stack(brute_force_pairs(x, rc)))
    with pytest.raises(ValueError, match="ghost_bits"):
        tree.verlet_list(ghost_bits=np.full(n, 2 ** d))
    with pytest.raises(ValueError, match="ghost_bits"):
        tree.verlet_list(ghost_bits=np.zeros(n - 1, int))


@pytest.mark.parametrize("d", [2, 3])
def test_source_rows_are_the_cross_list_of_the_first_sources(rng, d):
    """source_rows (from the symmetric list) gives the rows of the first n sources against all of
    them exactly as the cross list does, and brute force: graded cutoffs, ties and coincident
    points, n = 0, n = m; without the particles themselves, the canonical full list."""
    from arpy.lists.search import source_rows

    for trial in range(6):
        m = int(rng.integers(2, 1500))
        x = rng.random((m, d)) ** (1 + trial % 3)
        if trial % 3 == 0:
            x = np.round(x * 8) / 8                                   # ties and coincident points
        rc = loguniform(rng, m, 0.01, 30.0)                          # 0.01 to 0.3
        for n in (0, int(rng.integers(1, m)), m):
            got = source_rows(x, rc, n)
            want = arpy.cross_neighbor_list(x[:n], rc[:n], x, rc).canonical()
            assert got.n == n and got.n_ref == m and got.full
            np.testing.assert_array_equal(got.offsets, want.offsets)
            np.testing.assert_array_equal(got.indices, want.indices)
            i, q = brute_force_cross_pairs(x[:n], rc[:n], x, rc)
            np.testing.assert_array_equal(got.rows(), i)
            np.testing.assert_array_equal(got.indices, q)
        full = source_rows(x, rc, m, itself=False)                        # the full list, canonical
        want = arpy.neighbor_list(x, rc, full=True).canonical()
        assert full.n == m and full.n_ref is None and full.full
        np.testing.assert_array_equal(full.offsets, want.offsets)
        np.testing.assert_array_equal(full.indices, want.indices)
    with pytest.raises(ValueError, match="n must lie"):
        source_rows(x, rc, m + 1)
    # lists of more entries than the core writes in order directly: written as held, then sorted
    m = 12_000
    x = rng.random((m, d))
    rc = loguniform(rng, m, 1.0, 1.5) * (30.0 / ((np.pi if d == 2 else 4.2) * m)) ** (1.0 / d)   # ~30 neighbours
    for n, itself in [(m, True), (m, False), (m // 2, True)]:
        got = source_rows(x, rc, n, itself=itself)
        assert len(got) > 250_000 or n < m                        # (above IN_ORDER_MAX)
        want = arpy.cross_neighbor_list(x[:n], rc[:n], x, rc).canonical()
        if not itself:
            want = arpy.neighbor_list(x, rc, full=True).canonical()
        np.testing.assert_array_equal(got.offsets, want.offsets)
        np.testing.assert_array_equal(got.indices, want.indices)
        with arpy.num_threads(2):                                 # (the rows sorted in parallel)
            two = source_rows(x, rc, n, itself=itself)
        assert two.offsets.tobytes() == got.offsets.tobytes() and two.indices.tobytes() == got.indices.tobytes()
    # the core checks what it is given: n outside [0, m] or itself not 0 or 1 is an error
    from arpy import _core
    for n, itself in [(-1, 1), (len(x) + 1, 0), (5, 2)]:
        assert _core.arpy_source_rows(x.T, rc, n, 2, itself)[2] != 0
