"""Neighbour lists (Fortran brute force and uniform cell list) against independent references."""

from __future__ import annotations

import numpy as np
import pytest

import arpy
from arpy.reference import brute_force_pairs, cell_list_pairs
from conftest import clustered_points, kdtree_pairs, lattice_points, uniform_points


def assert_same_pairs(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> None:
    assert a[0].shape == b[0].shape, f"{a[0].size} pairs vs {b[0].size}"
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def check_csr(nl: arpy.NeighborList, n: int) -> None:
    """Structural invariants of a CSR neighbour list."""
    assert nl.offsets.shape == (n + 1,)
    assert nl.offsets[0] == 0 and nl.offsets[-1] == len(nl)
    assert np.all(np.diff(nl.offsets) >= 0)
    assert len(nl) == 0 or (nl.indices.min() >= 0 and nl.indices.max() < n)
    assert not np.any(nl.rows() == nl.indices), "a particle is listed as its own neighbour"


def particle_sets(rng: np.random.Generator, d: int):
    """(name, x, rc) cases: single and per-particle cutoffs on several distributions."""
    n = 1500 if d == 2 else 1200
    xu = uniform_points(rng, n, d)
    xc = clustered_points(rng, n, d)
    xl = lattice_points(d, m=9 if d == 2 else 6)
    xdup = np.repeat(uniform_points(rng, n // 3, d), 3, axis=0)  # every point three times
    span = np.exp(rng.uniform(np.log(0.004), np.log(0.12), n))  # cutoffs spanning a factor 30
    return [
        ("uniform, one cutoff", xu, 0.06),
        ("uniform, per-particle", xu, span),
        ("clustered, one cutoff", xc, 0.03),
        ("clustered, per-particle", xc, span),
        ("lattice on cell faces, rc = 2h", xl, 0.25),
        ("lattice on cell faces, rc = h", xl, 0.125),
        ("lattice, per-particle 0.125/0.25", xl, np.where(np.arange(len(xl)) % 2 == 0, 0.125, 0.25)),
        ("coincident points", xdup, span[: len(xdup)]),
    ]


@pytest.mark.parametrize("d", [2, 3])
def test_all_methods_find_the_same_pairs(rng, d):
    for name, x, rc in particle_sets(rng, d):
        expected = brute_force_pairs(x, rc)
        assert expected[0].size > 0, name
        assert_same_pairs(cell_list_pairs(x, rc), expected)
        assert_same_pairs(kdtree_pairs(x, rc), expected)
        for method in ("brute", "cell"):
            for full in (False, True):
                nl = arpy.neighbor_list(x, rc, method=method, full=full)
                check_csr(nl, len(x))
                assert len(nl) == expected[0].size * (2 if full else 1), (name, method, full)
                assert_same_pairs(nl.pairs(), expected)


@pytest.mark.parametrize("d", [2, 3])
def test_cell_order_lists_are_the_lists_of_the_sorted_particles(rng, d):
    """neighbor_list_in_cell_order: a permutation and the pairs of the particles in it (brute force
    on the reordered set), for every method and both forms; the AR order is the tree's own; and
    particles already in that order give the identity and, bitwise, neighbor_list's list of them."""
    for name, x, rc in particle_sets(rng, d):
        for method in ("brute", "cell", "ar", "auto"):
            first = None
            for full in (False, True):
                order, nl = arpy.neighbor_list_in_cell_order(x, rc, method=method, full=full)
                assert order.dtype == np.int64
                np.testing.assert_array_equal(np.sort(order), np.arange(len(x)))
                check_csr(nl, len(x))
                if first is None:                     # (the order is the same for both forms)
                    first, expected = order, brute_force_pairs(x[order], np.broadcast_to(rc, len(x))[order])
                np.testing.assert_array_equal(order, first)
                assert len(nl) == expected[0].size * (2 if full else 1), (name, method, full)
                assert_same_pairs(nl.pairs(), expected)
                if method == "brute":
                    np.testing.assert_array_equal(order, np.arange(len(x)))
                if method == "ar":
                    np.testing.assert_array_equal(order, arpy.ARCellList(x, rc).order)
                xs, rs = x[order], np.broadcast_to(rc, len(x))[order]
                again, same = arpy.neighbor_list_in_cell_order(xs, rs, method=method, full=full)
                np.testing.assert_array_equal(again, np.arange(len(x)), err_msg=f"{name}, {method}")
                plain = arpy.neighbor_list(xs, rs, method=method, full=full)
                assert same.offsets.tobytes() == plain.offsets.tobytes()
                assert same.indices.tobytes() == plain.indices.tobytes()


def test_cell_order_lists_over_hashed_levels():
    """Cutoffs over three decades put the AR tree's coarse levels in its hash (the recursive
    partition): the order is still the tree's, and a fixed point."""
    g = np.random.default_rng(7)
    x = g.random((4000, 2)) ** 3
    rc = 0.0002 * np.exp(g.uniform(0.0, np.log(1000.0), len(x)))
    order, nl = arpy.neighbor_list_in_cell_order(x, rc, method="ar")
    np.testing.assert_array_equal(order, arpy.ARCellList(x, rc).order)
    assert_same_pairs(nl.pairs(), brute_force_pairs(x[order], rc[order]))
    again, _ = arpy.neighbor_list_in_cell_order(x[order], rc[order], method="ar")
    np.testing.assert_array_equal(again, np.arange(len(x)))


@pytest.mark.parametrize("d", [2, 3])
def test_full_list_rows_hold_every_neighbour(rng, d):
    x = clustered_points(rng, 800, d)
    rc = rng.uniform(0.01, 0.08, len(x))
    full = arpy.neighbor_list(x, rc, full=True)
    i, j = brute_force_pairs(x, rc)
    rows, cols = np.concatenate([i, j]), np.concatenate([j, i])          # each pair in both rows
    for p in range(0, len(x), 37):
        np.testing.assert_array_equal(np.sort(full.neighbors(p)), np.sort(cols[rows == p]))
    np.testing.assert_array_equal(full.counts(), np.bincount(rows, minlength=len(x)))


def test_skin_is_added_to_every_cutoff(rng):
    x = uniform_points(rng, 1000, 2)
    rc = rng.uniform(0.01, 0.05, len(x))
    for method in ("brute", "cell"):
        got = arpy.neighbor_list(x, rc, method=method, skin=0.02).pairs()
        assert_same_pairs(got, kdtree_pairs(x, rc, skin=0.02))


def test_exact_distance_equal_to_cutoff_is_a_neighbour():
    x = np.array([[0.0, 0.0], [0.25, 0.0], [0.25, 0.375], [0.0, 0.0]])
    nl = arpy.neighbor_list(x, np.array([0.25, 0.5, 0.375, 0.25]), method="cell")
    i, j = nl.pairs()
    # 0-1 at 0.25 = min(0.25, 0.5); 1-2 at 0.375 = min(0.5, 0.375); 0-3 coincident; 1-3 at 0.25
    assert list(zip(i.tolist(), j.tolist())) == [(0, 1), (0, 3), (1, 2), (1, 3)]


def test_sparse_set_with_tiny_cutoff_and_far_offset():
    # cell count is capped: two far-apart points with a tiny cutoff cost no memory
    x = np.array([[0.0, 0.0], [1e6, 1e6], [1e6, 1e6 + 5e-7]])
    for method in ("brute", "cell"):
        i, j = arpy.neighbor_list(x, 1e-6, method=method).pairs()
        assert (i.tolist(), j.tolist()) == ([1], [2])
    x3 = np.array([[1e9, 0, 0], [1e9 + 1, 0, 0], [1e9, 1e-9, 0.0]])
    assert_same_pairs(arpy.neighbor_list(x3, 1e-3).pairs(), brute_force_pairs(x3, 1e-3))


@pytest.mark.parametrize("n", [0, 1])
@pytest.mark.parametrize("method", ["brute", "cell"])
def test_empty_and_single_particle(n, method):
    nl = arpy.neighbor_list(np.zeros((n, 3)), 0.1, method=method)
    assert nl.n == n and len(nl) == 0
    np.testing.assert_array_equal(nl.offsets, np.zeros(n + 1))
    i, j = nl.pairs()
    assert i.size == 0 and j.size == 0
    order, nl = arpy.neighbor_list_in_cell_order(np.zeros((n, 3)), 0.1, method=method)
    assert order.tolist() == list(range(n)) and order.dtype == np.int64 and nl.n == n and len(nl) == 0


def test_input_dtypes_are_converted(rng):
    x = uniform_points(rng, 300, 2)
    ref = arpy.neighbor_list(x, 0.1).pairs()
    assert_same_pairs(arpy.neighbor_list(x.astype(np.float32).astype(np.float64), 0.1).pairs(),
                      brute_force_pairs(x.astype(np.float32).astype(np.float64), 0.1))
    assert_same_pairs(arpy.neighbor_list(np.asfortranarray(x), 0.1).pairs(), ref)
    assert_same_pairs(arpy.neighbor_list(x.tolist(), 0.1).pairs(), ref)
    xi = (x * 100).astype(np.int64)
    assert_same_pairs(arpy.neighbor_list(xi, 10).pairs(), brute_force_pairs(xi.astype(float), 10.0))
    big = np.zeros((len(x), 4))
    big[:, :2] = x
    assert_same_pairs(arpy.neighbor_list(big[:, :2], 0.1).pairs(), ref)  # non-contiguous view


BAD_INPUTS = [
    (np.array([[0.0, np.nan], [1.0, 1.0]]), 0.1, {}, ValueError, "particle 0 is not finite"),
    (np.array([[0.0, 0.0], [np.inf, 1.0]]), 0.1, {}, ValueError, "particle 1 is not finite"),
    (np.zeros((3, 2)), np.array([0.1, np.nan, 0.1]), {}, ValueError, "particle 1"),
    (np.zeros((3, 2)), np.array([0.1, 0.1, 0.0]), {}, ValueError, "particle 2"),
    (np.zeros((3, 2)), -1.0, {}, ValueError, "particle 0"),
    (np.zeros((3, 2)), np.array([0.1, 0.1]), {}, ValueError, "shape"),
    (np.zeros((3, 2)), np.ones((3, 1)), {}, ValueError, "shape"),
    (np.zeros(6), 0.1, {}, ValueError, "shape"),
    (np.zeros((3, 1)), 0.1, {}, ValueError, "d = 2 or d = 3"),
    (np.zeros((3, 4)), 0.1, {}, ValueError, "d = 2 or d = 3"),
    (np.array([["a", "b"]]), 0.1, {}, TypeError, "real numeric"),
    (np.zeros((3, 2), dtype=complex), 0.1, {}, TypeError, "real numeric"),
    (np.zeros((3, 2)), "0.1", {}, TypeError, "real numbers"),
    (np.zeros((3, 2)), 0.1, {"skin": -0.1}, ValueError, "skin"),
    (np.zeros((3, 2)), 0.1, {"skin": np.nan}, ValueError, "skin"),
    (np.zeros((3, 2)), 0.1, {"method": "octree"}, ValueError, "unknown method"),
]


@pytest.mark.parametrize("x, rc, kwargs, exc, message", BAD_INPUTS)
@pytest.mark.parametrize("method", ["brute", "cell"])
def test_bad_input_raises_clear_error(x, rc, kwargs, exc, message, method):
    kwargs = {"method": method, **kwargs}
    with pytest.raises(exc, match=message):
        arpy.neighbor_list(x, rc, **kwargs)
    with pytest.raises(exc, match=message):
        arpy.neighbor_list_in_cell_order(x, rc, **kwargs)


def test_core_recovers_after_an_error(rng):
    with pytest.raises(ValueError):
        arpy.neighbor_list(np.array([[np.nan, 0.0]]), 0.1)
    x = uniform_points(rng, 200, 2)
    assert_same_pairs(arpy.neighbor_list(x, 0.1).pairs(), brute_force_pairs(x, 0.1))


def test_ar_benchmark_distribution_has_eight_neighbours_inside():
    for lam in (1.0, 10.0, 100.0):
        x, rc = arpy.ar_benchmark(4000, lam)
        assert x.shape == (4100, 2)
        assert rc.max() / rc.min() == pytest.approx(lam)
        counts = arpy.neighbor_list(x, rc, full=True).counts()
        assert counts.max() == 8
        # away from the block edges every particle has exactly 8 neighbours
        inner_big = (np.abs(x[:100] - 0.5) < 0.35).all(axis=1)
        assert np.all(counts[:100][inner_big] == 8)
        xs, hs = x[100:], 0.1 / lam
        inner_small = ((xs[:, 1] > hs) & (xs[:, 1] < 1 - hs) & (xs[:, 0] > 1 + hs)
                       & (xs[:, 0] < xs[:, 0].max() - hs))
        assert inner_small.sum() >= 1000
        assert np.all(counts[100:][inner_small] == 8)
    x3, rc3 = arpy.ar_benchmark(2000, 10.0, d=3)
    assert x3.shape == (3000, 3)
    # rc = 1.5 h admits the 6 face and 12 edge neighbours in 3D, not the corners (sqrt(3) h)
    assert arpy.neighbor_list(x3, rc3, full=True).counts().max() == 18


@pytest.mark.parametrize("domain", [None, arpy.Domain([1.0, 1.0], periodic=True)])
def test_canonical_layout_is_one_for_every_method(domain):
    """canonical() gives the same arrays whatever built the list (rows ascending, a symmetric pair
    in the row of its smaller index), equal to from_pairs of brute force; the pairs are unchanged."""

    rng = np.random.default_rng(4)
    x = rng.random((2000, 2))
    rc = rng.uniform(0.01, 0.06, len(x))
    period = None if domain is None else np.ones(2)
    want = brute_force_pairs(x, rc, period=period)
    for full in (False, True):
        ref = arpy.NeighborList.from_pairs(len(x), *want, full=full)
        for method in ("cell", "ar", "brute"):
            nl = arpy.neighbor_list(x, rc, method=method, full=full, domain=domain)
            before = nl.indices.copy()
            can = nl.canonical()
            np.testing.assert_array_equal(nl.indices, before)           # the list itself is left as it was
            np.testing.assert_array_equal(can.offsets, ref.offsets)
            np.testing.assert_array_equal(can.indices, ref.indices)
            assert all(np.all(np.diff(can.stored_row(p)) > 0) for p in range(0, len(x), 97))
    cross = arpy.cross_neighbor_list(x[:300] + 0.003, rc[:300], x, rc)            # cross lists: rows ascending
    can = cross.canonical()
    np.testing.assert_array_equal(can.offsets, cross.offsets)
    for p in range(300):
        np.testing.assert_array_equal(can.stored_row(p), np.sort(cross.stored_row(p)))


def test_pairs_increasing_is_lexsort_leaving_distinct_pairs_in_place():
    """pairs_increasing(i, j) against np.lexsort: True exactly when the sort is the identity and no
    pair repeats (ties, repeated pairs, one pair and none included)."""
    from arpy.lists.neighborlist import pairs_increasing

    rng = np.random.default_rng(2)
    for _ in range(300):
        n = int(rng.integers(0, 7))
        i, j = rng.integers(-1, 3, n), rng.integers(0, 4, n)
        if rng.random() < 0.5:                                   # (sorted, often distinct)
            order = np.lexsort((j, i))
            i, j = i[order], j[order]
        want = bool(np.array_equal(np.lexsort((j, i)), np.arange(n))
                    and len(set(zip(i.tolist(), j.tolist()))) == n)
        assert pairs_increasing(i, j) == want, (i, j)


def ckdtree_min_rule(x: np.ndarray, rc: np.ndarray, box: float | None):
    """cKDTree's sparse distance matrix (boxsize: the periodic cube of edge box) under the min rule,
    both orientations, no diagonal: an independent reference for to_sparse and distances."""
    from scipy.spatial import cKDTree

    tree = cKDTree(x, boxsize=box)
    ref = tree.sparse_distance_matrix(tree, rc.max(), output_type="coo_matrix").tocsr()
    ref = ref.multiply(ref <= np.minimum.outer(rc, rc)).tocsr()      # the min rule
    ref.setdiag(0.0)
    ref.eliminate_zeros()
    return ref


@pytest.mark.parametrize("full", [False, True])
def test_to_sparse_equals_ckdtree_sparse_distance_matrix(full):
    """A list remembers its positions and domain: to_sparse(), distances() and vectors() without
    arguments are cKDTree's sparse distance matrix with boxsize (minimum image) in a periodic box, and
    without one in free space; to_sparse is a csr_array with sorted rows (other formats on request),
    mode="connectivity" its pattern; a cross list's matrix holds its (query, reference) distances."""
    import scipy.sparse as sp

    rng = np.random.default_rng(8)
    for d in (2, 3):
        x = rng.random((600, d))
        rc = rng.uniform(0.02, 0.08, len(x)) * (1 if d == 2 else 2)
        for domain, box in ((None, None), (arpy.Domain([1.0] * d, periodic=True), 1.0)):
            ref = ckdtree_min_rule(x, rc, box)
            nl = arpy.neighbor_list(x, rc, full=full, domain=domain)
            got = nl.to_sparse()
            assert isinstance(got, sp.csr_array) and got.has_sorted_indices and got.nnz == ref.nnz
            np.testing.assert_array_equal(got.indptr, ref.indptr)
            np.testing.assert_array_equal(got.indices, ref.indices)
            np.testing.assert_allclose(got.data, ref.data, rtol=1e-13, atol=0)
            p, q = nl.rows(), nl.indices
            dist, vec, shift = nl.distances(), nl.vectors(), nl.shifts()
            np.testing.assert_allclose(dist, np.asarray(ref[p, q]).ravel(), rtol=1e-13, atol=0)
            # vectors by the minimum image: x_q - x_p + S * edge, no longer than half an edge per axis
            edge = 0.0 if box is None else box
            assert np.array_equal(vec, x[q] - x[p] + shift * edge) and np.all(np.abs(vec) <= 0.5)
            assert (box is None) == (not shift.any())
            np.testing.assert_allclose(np.linalg.norm(vec, axis=1), dist, rtol=1e-14)
            assert (nl.to_sparse(mode="connectivity") != (ref > 0)).nnz == 0
            coo = nl.to_sparse(format="coo")
            assert isinstance(coo, sp.coo_array) and (coo.tocsr() != got).nnz == 0
    y = rng.random((50, 3))
    cross = arpy.cross_neighbor_list(y, 0.1, x, rc)
    mat = cross.to_sparse()
    assert mat.shape == (50, len(x)) and mat.nnz == len(cross)
    i, j = cross.pairs()
    np.testing.assert_allclose(np.asarray(mat[i, j]).ravel(), np.linalg.norm(y[i] - x[j], axis=1), rtol=1e-15)
    with pytest.raises(ValueError, match="mode must be"):
        cross.to_sparse(mode="ones")


@pytest.mark.parametrize("full", [False, True])
def test_vectors_distances_and_shifts_against_explicit_images(full):
    """vectors/distances/shifts of every stored entry: in a box periodic along x only (walls along y),
    each vector is x_q - x_p + S * edge exactly, is the shortest of the images -1, 0, +1 (checked
    by NumPy over all three), and lies within the min rule; the same with the positions passed
    explicitly; in free space S = 0 and the vectors are the plain differences; a cross list's
    reference positions are its own unless given."""
    rng = np.random.default_rng(9)
    x = rng.random((500, 2)) * [2.0, 1.0]
    rc = rng.uniform(0.03, 0.1, len(x))
    box = arpy.Domain(([0.0, 0.0], [2.0, 1.0]), periodic=(True, False))
    nl = arpy.neighbor_list(x, rc, full=full, domain=box)
    p, q = nl.rows(), nl.indices
    v, d, s = nl.vectors(), nl.distances(), nl.shifts()
    assert v.shape == s.shape == (len(nl), 2) and s.dtype == np.int64 and np.all(s[:, 1] == 0)
    assert np.array_equal(v, x[q] - x[p] + s * [2.0, 0.0])
    images = np.stack([x[q] - x[p] + [k * 2.0, 0.0] for k in (-1, 0, 1)])
    np.testing.assert_allclose(d, np.linalg.norm(images, axis=2).min(axis=0), rtol=1e-15)
    assert np.all(d <= np.minimum(rc[p], rc[q])) and np.any(s[:, 0] != 0)
    assert np.array_equal(nl.vectors(x.tolist(), domain=box), v) and np.array_equal(nl.distances(x), d)
    free = arpy.neighbor_list(x, rc, full=full)
    assert np.array_equal(free.vectors(), x[free.indices] - x[free.rows()])
    assert not free.shifts().any()
    # another domain given explicitly overrides the list's: raw differences in free space
    assert np.array_equal(nl.vectors(domain=arpy.Domain()), x[q] - x[p])
    cross = arpy.cross_neighbor_list(x[:20], 0.1, x, rc)
    want = np.linalg.norm(x[cross.indices] - x[cross.rows()], axis=1)
    np.testing.assert_allclose(cross.distances(), want)
    np.testing.assert_allclose(cross.distances(x[:20] + 1.0, x + 1.0), want, rtol=1e-12)
    with pytest.raises(ValueError, match="x_ref is for cross lists"):
        nl.vectors(x, x)


@pytest.mark.parametrize("full", [False, True])
def test_quantities_ijdDS_against_ckdtree_on_a_shifted_box(full):
    """quantities("ijdDS") on a periodic box that does not start at 0: i and j are the stored
    entries; D = x_j - x_i + S edge exactly; d is |D| (the bits of distances()) and, as a multiset,
    cKDTree's minimum-image distances with boxsize (each pair once or twice); any subset and order
    of the letters gives the same arrays; bad specs and a list without positions are refused."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(21)
    lo, hi = np.array([-1.0, -0.5, 0.0]), np.array([1.0, 2.5, 1.5])
    x = lo + rng.random((3000, 3)) * (hi - lo)
    box = arpy.Domain((lo, hi), periodic=(True, False, True))
    nl = arpy.neighbor_list(x, 0.25, full=full, domain=box)
    i, j, d, D, S = nl.quantities("ijdDS")
    assert i.dtype == j.dtype == S.dtype == np.int64 and D.shape == S.shape == (len(nl), 3)
    assert np.array_equal(i, nl.rows()) and np.array_equal(j, nl.indices)
    assert np.array_equal(D, x[j] - x[i] + S * (hi - lo) * [1, 0, 1]) and not S[:, 1].any() and S.any()
    assert np.array_equal(d, nl.distances())
    np.testing.assert_allclose(d, np.linalg.norm(D, axis=1), rtol=1e-15)
    big = 1e6                                  # (walls along y: no wrap there)
    tree = cKDTree(np.c_[x[:, 0] - lo[0], x[:, 1] - lo[1], x[:, 2] - lo[2]],
                   boxsize=[hi[0] - lo[0], big, hi[2] - lo[2]])
    ref = tree.sparse_distance_matrix(tree, 0.25, output_type="ndarray")
    ref = ref[ref["i"] != ref["j"]] if full else ref[ref["i"] < ref["j"]]
    np.testing.assert_allclose(np.sort(d), np.sort(ref["v"]), rtol=1e-14)
    for spec in ("S", "dj", "Di"):
        for got, want in zip(nl.quantities(spec), [dict(zip("ijdDS", (i, j, d, D, S)))[c] for c in spec]):
            assert np.array_equal(got, want)
    for bad in ("", "ijx", "ii", 3):
        with pytest.raises(ValueError, match="distinct letters"):
            nl.quantities(bad)
    bare = arpy.NeighborList.from_pairs(3, [0], [1])
    assert [a.tolist() for a in bare.quantities("ij")] == [[0], [1]]
    with pytest.raises(ValueError, match="holds no positions"):
        bare.quantities("d")


def test_lists_without_positions_and_positions_moved_in_place():
    """A list from from_pairs holds no positions: distances() and the others say so and take them
    as arguments (the connectivity pattern needs none); a list holds its positions by reference:
    moved in place, its distances are those at the new positions, for the pairs of the build."""
    x = np.array([[0.0, 0.0], [0.1, 0.0], [0.5, 0.0], [0.55, 0.0]])
    nl = arpy.NeighborList.from_pairs(4, [0, 2], [1, 3])
    assert nl.x is None and nl.domain is None
    for what in ("distances", "vectors", "shifts", "to_sparse"):
        with pytest.raises(ValueError, match=rf"NeighborList.{what}: this list holds no positions .*pass x="):
            getattr(nl, what)()
    np.testing.assert_allclose(nl.distances(x), [0.1, 0.05])
    assert nl.to_sparse(mode="connectivity").nnz == 4
    built = arpy.neighbor_list(x, 0.2)
    assert built.x is x                                                  # a reference, not a copy
    x[1, 0] = 0.15
    np.testing.assert_allclose(built.distances(), [0.15, 0.05])
    assert built.canonical().x is x and built.ordered_by(np.arange(4)).x is x


@pytest.mark.parametrize("domain", [None, arpy.Domain([1.0, 1.0, 1.0], periodic=(True, True, False))])
def test_counts_and_neighbors_are_each_particles_neighbours_in_both_forms(domain):
    """counts() and neighbors(p) are every particle's neighbours by brute force (minimum image), for a
    half list and a full one alike; stored_counts() and stored_row(p) are the stored rows."""
    rng = np.random.default_rng(12)
    x = rng.random((700, 3))
    rc = rng.uniform(0.05, 0.15, len(x))
    period = None if domain is None else np.array([1.0, 1.0, 0.0])
    i, j = brute_force_pairs(x, rc, period=period)
    rows, cols = np.concatenate([i, j]), np.concatenate([j, i])
    want = np.bincount(rows, minlength=len(x))
    for full in (False, True):
        nl = arpy.neighbor_list(x, rc, full=full, domain=domain)
        np.testing.assert_array_equal(nl.counts(), want)
        np.testing.assert_array_equal(nl.stored_counts(), np.diff(nl.offsets))
        for p in range(0, len(x), 23):
            np.testing.assert_array_equal(np.sort(nl.neighbors(p)), np.sort(cols[rows == p]))
            np.testing.assert_array_equal(nl.stored_row(p), nl.indices[nl.offsets[p]:nl.offsets[p + 1]])
        assert full or not np.array_equal(nl.stored_counts(), want)
    empty = arpy.NeighborList.from_pairs(3, [], [])
    assert empty.counts().tolist() == [0, 0, 0] and empty.neighbors(2).size == 0


def test_symmetric_is_a_deprecated_alias_of_not_full():
    """symmetric= still works, with a DeprecationWarning naming full=, in every signature that had it
    (the same lists); the attribute too; full=True with symmetric=True contradict each other."""
    x = np.random.default_rng(13).random((200, 2))
    for symmetric in (True, False):
        want = arpy.neighbor_list(x, 0.1, full=not symmetric)
        calls = [lambda: arpy.neighbor_list(x, 0.1, symmetric=symmetric),
                 lambda: arpy.neighbor_list_in_cell_order(x, 0.1, symmetric=symmetric)[1],
                 lambda: arpy.ARCellList(x, 0.1).verlet_list(symmetric=symmetric),
                 lambda: arpy.NeighborList.from_pairs(len(x), *want.pairs(), symmetric=symmetric),
                 lambda: arpy.NeighborList(want.offsets, want.indices, symmetric=symmetric)]
        for call in calls:
            with pytest.warns(DeprecationWarning, match="symmetric= is deprecated, use full="):
                nl = call()
            assert nl.full == (not symmetric) and len(nl) == len(want)
        with pytest.warns(DeprecationWarning, match="NeighborList.full"):
            assert want.symmetric == symmetric
    with pytest.raises(ValueError, match="contradict"), pytest.warns(DeprecationWarning):
        arpy.neighbor_list(x, 0.1, full=True, symmetric=True)
    with pytest.raises(TypeError):
        arpy.NeighborList(want.offsets, want.indices, True)           # the form is keyword-only


def test_cell_order_in_a_periodic_box():
    """neighbor_list_in_cell_order in a periodic box: the pairs of x[order] by the minimum image,
    particles already in that order keep it (the identity) and their list is neighbor_list's."""
    rng = np.random.default_rng(14)
    x = rng.random((1500, 2))
    rc = rng.uniform(0.01, 0.04, len(x))
    torus = arpy.Domain([1.0, 1.0], periodic=True)
    for method in ("cell", "ar"):
        order, nl = arpy.neighbor_list_in_cell_order(x, rc, method=method, domain=torus)
        assert sorted(order.tolist()) == list(range(len(x))) and not np.array_equal(order, np.arange(len(x)))
        assert_same_pairs(nl.pairs(), brute_force_pairs(x[order], rc[order], period=np.ones(2)))
        assert np.array_equal(nl.x, x[order]) and nl.domain is torus
        again, same = arpy.neighbor_list_in_cell_order(x[order], rc[order], method=method, domain=torus)
        np.testing.assert_array_equal(again, np.arange(len(x)))
        assert_same_pairs(same.pairs(), nl.pairs())


# ---------------------------------------------------------------- cache order

def _reference_order(x, domain=None):
    """The reference Morton order on the grid cache_order documents (cube over the box or the
    bounding box, 2**30 / 2**20 cells per axis)."""
    import math
    from arpy.reference import morton_order
    d = x.shape[1]
    if domain is not None:
        lo, hi = np.asarray(domain.lo, float), np.asarray(domain.hi, float)
    else:
        lo, hi = x.min(axis=0), x.max(axis=0)
    bits = {2: 30, 3: 20}[d]
    return morton_order(x, lo, math.ldexp(1.0, bits) / float(np.max(hi - lo)), bits)


def test_reference_morton_order_is_the_z_curve():
    """The reference itself, on a 4 x 4 lattice of cell centres: the Z curve drawn by hand."""
    from arpy.reference import morton_order
    c = np.array([(i, j) for i in range(4) for j in range(4)], float) + 0.5
    order = morton_order(c, np.zeros(2), 1.0, 2)
    z = [(0, 0), (0, 1), (1, 0), (1, 1), (0, 2), (0, 3), (1, 2), (1, 3),
         (2, 0), (2, 1), (3, 0), (3, 1), (2, 2), (2, 3), (3, 2), (3, 3)]
    assert [tuple(p) for p in (c[order] - 0.5).astype(int)] == z


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("d", [2, 3])
def test_cache_order_is_the_reference_morton_order(seed, d):
    rng = np.random.default_rng(seed)
    x = rng.random((3000, d))
    x[:200] = x[200:400]                                         # ties: coincident points keep index order
    x[400:600] = np.round(x[400:600] * 8) / 8                    # points on cell faces of every level
    x[600:700] = rng.random((100, d)) * 1e-7 + 0.3               # a cluster far finer than the rest
    x[700:710] += 3.0                                            # outside the box below: the nearest cell
    perm = arpy.cache_order(x)
    assert perm.dtype == np.int64 and np.array_equal(np.sort(perm), np.arange(len(x)))
    assert np.array_equal(perm, _reference_order(x))
    box = arpy.Domain([[-1.0] * d, [2.0] * d], periodic=True)
    assert np.array_equal(arpy.cache_order(x, domain=box), _reference_order(x, box))


def test_cache_order_puts_neighbours_close_and_keeps_the_lists():
    x = np.random.default_rng(4).random((20_000, 2))
    perm = arpy.cache_order(x)
    nl = arpy.neighbor_list(x, 0.01, full=True)
    ordered = arpy.neighbor_list(x[perm], 0.01, full=True)
    # the same pairs, renumbered; a neighbour's index is near the particle's own in cache order
    i, j = ordered.pairs()
    pi, pj = perm[i], perm[j]
    a, b = np.minimum(pi, pj), np.maximum(pi, pj)
    o = np.lexsort((b, a))
    ref_i, ref_j = nl.pairs()
    assert np.array_equal(a[o], ref_i) and np.array_equal(b[o], ref_j)
    assert np.median(np.abs(i - j)) < 0.02 * np.median(np.abs(ref_i - ref_j))


def test_cache_order_edge_cases():
    assert arpy.cache_order(np.zeros((0, 2))).size == 0
    assert np.array_equal(arpy.cache_order(np.ones((5, 3))), np.arange(5))        # one point, five times
    huge = np.array([[-1e308, 0.0], [1e308, 1.0], [0.0, 0.0]])                  # extent beyond the double range
    assert np.array_equal(arpy.cache_order(huge), [0, 2, 1])
    tiny = np.array([[3e-320, 0.0], [0.0, 0.0], [1e-320, 0.0]])                 # subnormal extent
    assert np.array_equal(arpy.cache_order(tiny), [1, 2, 0])
    with pytest.raises(ValueError, match="particle 1 is not finite"):
        arpy.cache_order(np.array([[0.0, 0.0], [np.nan, 1.0]]))
    with pytest.raises(ValueError, match="shape"):
        arpy.cache_order(np.zeros(4))


def test_stored_counts_where_counts_each_rows_true_entries(monkeypatch):
    """NeighborList.stored_counts_where: per row, the stored entries where the mask is True, as a Python
    count over each row's slice, at every block size (empty rows and rows longer than a block included);
    a mask of the wrong shape or type is refused."""
    from arpy.lists import neighborlist

    g = np.random.default_rng(8)
    lens = g.integers(0, 25, 300) * (g.random(300) < 0.8)
    lens[:2], lens[-3:], lens[100] = 0, 0, 200
    offsets = np.concatenate([[0], np.cumsum(lens)]).astype(np.int64)
    nl = arpy.NeighborList(offsets, g.integers(0, 300, offsets[-1]).astype(np.int32), full=True)
    mask = g.random(offsets[-1]) < 0.6
    want = [int(mask[a:b].sum()) for a, b in zip(offsets[:-1], offsets[1:])]
    for block in (1, 5, 64, neighborlist.COUNT_BLOCK):
        monkeypatch.setattr(neighborlist, "COUNT_BLOCK", block)
        got = nl.stored_counts_where(mask)
        assert got.dtype == np.int64 and got.tolist() == want, block
    for bad in (mask[:-1], mask.astype(np.int8)):
        with pytest.raises(ValueError, match="stored_counts_where"):
            nl.stored_counts_where(bad)
