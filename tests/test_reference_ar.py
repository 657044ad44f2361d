"""Checks of the pure-NumPy AR cell list reference against brute force.

The reference (arpy.reference.ar) is itself the yardstick for the Fortran
core, so it is tested here against an all-pairs search and against the rules
of Awile et al. (CPC 2012) directly: level rule, J index / Op1-Op5 consistency,
Verlet lists (half and full, with and without skin), cross lists.
"""
from itertools import product

import numpy as np
import pytest

from arpy.reference import brute_force_cross_pairs, brute_force_pairs
from arpy.reference.ar import ARCellListRef
from arpy.reference.ar_keys import MAX_LEVEL, level_first_index
from conftest import fitted_root


# ----------------------------------------------------------------- brute force
def brute_pairs(x, rc, skin=0.0):
    """All unordered pairs (p < q) obeying the min rule, as sorted codes p*n + q."""
    p, q = brute_force_pairs(x, rc, skin)
    return p * len(x) + q


def brute_cross(xq, rq, x, rc, skin=0.0):
    """Sorted codes i*n + q of query i and reference q obeying the min rule."""
    i, q = brute_force_cross_pairs(xq, rq, x, rc, skin)
    return i * len(x) + q


def csr_codes(off, ind, ncols):
    """CSR -> (row codes r*ncols + c) in storage order; checks CSR shape invariants."""
    off = np.asarray(off)
    ind = np.asarray(ind)
    assert off.dtype == np.int64 and ind.dtype == np.int64
    assert off[0] == 0 and off[-1] == ind.size and np.all(np.diff(off) >= 0)
    rows = np.repeat(np.arange(off.size - 1), np.diff(off))
    return rows * ncols + ind, rows


def check_symmetric(off, ind, n, expected):
    codes, rows = csr_codes(off, ind, n)
    assert np.all(rows != ind), "self pair in list"
    lo, hi = np.minimum(rows, ind), np.maximum(rows, ind)
    und = np.sort(lo * n + hi)
    assert und.size == np.unique(und).size, "pair stored twice in a symmetric list"
    np.testing.assert_array_equal(und, expected)
    # rows sorted ascending
    assert np.all(np.diff(codes) > 0)


def check_full(off, ind, n, expected):
    codes, rows = csr_codes(off, ind, n)
    p, q = expected // n, expected % n
    full = np.sort(np.concatenate((p * n + q, q * n + p)))
    np.testing.assert_array_equal(codes, full)   # also checks per-row ascending order


def loguniform_cutoffs(rng, n, rmin, span=1000.0):
    return rmin * span ** rng.random(n)


# ------------------------------------------------------------------- fixtures
def two_resolution(d, lam, n_small):
    """§3.1 layout: 10^d coarse particles (h_b = 0.1, rc_b = 1.5 h_b) and a block
    of n_small fine ones (rc_s = rc_b/lam, h_s = 2 rc_s/3) next to the coarse mesh,
    starting one fine spacing from the last coarse column so cross-level pairs exist."""
    hb = 0.1
    rcb = 1.5 * hb
    g = (np.arange(10) + 0.5) * hb
    coarse = np.array(list(product(g, repeat=d)))
    rcs = rcb / lam
    hs = 2.0 * rcs / 3.0
    m = int(np.ceil(n_small ** (1.0 / d)))
    idx = np.array(list(product(range(m), repeat=d)))[:n_small]
    fine = np.empty((n_small, d))
    fine[:, 0] = 0.95 + hs * (1 + idx[:, 0])
    fine[:, 1:] = 0.05 + hs * (idx[:, 1:] - m // 2)
    x = np.vstack((coarse, fine))
    rc = np.concatenate((np.full(len(coarse), rcb), np.full(n_small, rcs)))
    return x, rc


# --------------------------------------------------------------------- levels
@pytest.mark.parametrize("d", [2, 3])
def test_level_rule_and_sort_order(d):
    rng = np.random.default_rng(1 + d)
    n = 3000
    x = rng.random((n, d))
    rc = loguniform_cutoffs(rng, n, 1e-4)
    # the root fitted to the smallest cutoff; then exact boundary values of its levels, values
    # just below them, cutoffs >= D_m (none below the smallest, which sets the root)
    D = fitted_root(1.0, rc[30:], MAX_LEVEL[d])
    m = np.arange(1, 12)
    special = np.concatenate((D / 2.0 ** m, np.nextafter(D / 2.0 ** m, 0), [D / 2, D, 3 * D, 1e6]))
    assert special.min() > rc[30:].min()
    rc[: special.size] = special
    cl = ARCellListRef(x, rc, domain=(np.zeros(d), np.ones(d)))
    assert cl.edge == D > 1.0
    k = cl.level
    upper = D / 2.0 ** k            # exact powers of two
    lower = D / 2.0 ** (k + 1)
    ok = (rc >= lower) & ((rc < upper) | (k == 0))
    assert np.all(ok)
    assert np.all(k[rc >= D / 2] == 0)
    np.testing.assert_array_equal(k[: m.size], m - 1)       # rc = D/2^m -> level m-1
    np.testing.assert_array_equal(k[m.size: 2 * m.size], m)  # just below -> level m
    assert cl.maxlevel == k.max()
    np.testing.assert_array_equal(cl.level_of_cutoff(rc), k)
    # Algorithm 1 step 1 + Algorithm 2: levels ascending (cutoffs descending
    # across levels), then J ascending; inside a cell cutoffs still descend
    rs, ks = rc[cl.order], k[cl.order]
    assert np.all(np.diff(ks) >= 0)
    for lev in range(cl.maxlevel):
        a, b = cl.level_start[lev], cl.level_start[lev + 1]
        c = cl.level_start[lev + 2]
        if a < b < c:
            assert rs[a:b].min() > rs[b:c].max()
    for first, last in cl.cells.values():
        assert np.all(np.diff(rs[first:last]) <= 0)
    assert np.all(np.diff(cl.cell_of[cl.order]) >= 0)
    np.testing.assert_array_equal(np.sort(cl.order), np.arange(n))
    for lev in range(cl.maxlevel + 2):
        assert cl.level_start[lev] == np.count_nonzero(k < lev)


# -------------------------------------------------------------- Verlet lists
@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("skin", [0.0, 0.004])
def test_verlet_uniform_random_vs_brute(d, skin):
    rng = np.random.default_rng(10 * d + int(skin > 0))
    n = 1500
    x = rng.random((n, d))
    rc = loguniform_cutoffs(rng, n, 5e-4 if d == 2 else 2e-3)   # spans a factor 1000
    cl = ARCellListRef(x, rc)
    assert cl.maxlevel >= 8
    expected = brute_pairs(x, rc, skin)
    assert expected.size > 1000
    check_symmetric(*cl.verlet_list(skin=skin, full=False), n, expected)
    check_full(*cl.verlet_list(skin=skin, full=True), n, expected)


@pytest.mark.parametrize("d,lam,n_small", [(2, 1, 400), (2, 10, 2000), (2, 1000, 2000),
                                           (3, 10, 1500), (3, 1000, 1500)])
def test_verlet_two_resolution_vs_brute(d, lam, n_small):
    x, rc = two_resolution(d, lam, n_small)
    n = len(x)
    cl = ARCellListRef(x, rc)
    expected = brute_pairs(x, rc)
    p, q = expected // n, expected % n
    if lam > 1:
        assert np.any(rc[p] != rc[q]), "fixture should produce cross-resolution pairs"
    check_symmetric(*cl.verlet_list(), n, expected)
    check_full(*cl.verlet_list(full=True), n, expected)
    expected_s = brute_pairs(x, rc, 0.1 * rc.min())
    check_full(*cl.verlet_list(skin=0.1 * rc.min(), full=True), n, expected_s)


def _degenerate_set(d, rng):
    """Random points plus exact duplicates, points on faces and corners of [0,1]^d."""
    x = rng.random((300, d))
    dup = x[rng.integers(0, 300, 40)]
    trip = np.repeat(x[:3], 3, axis=0)
    faces = rng.random((80, d))
    axis = rng.integers(0, d, 80)
    faces[np.arange(80), axis] = rng.integers(0, 2, 80).astype(float)
    corners = np.array(list(product([0.0, 1.0], repeat=d)))
    # points on interior cell faces: dyadic coordinates j / 2^m (exact in u-space)
    m = rng.integers(1, 8, (60, d))
    grid = rng.integers(0, 2 ** m + 1) / 2.0 ** m
    x = np.vstack((x, dup, trip, faces, grid, corners, corners))
    rc = loguniform_cutoffs(rng, len(x), 1e-3)
    rc[-len(corners):] = 0.7        # corner copies see each other, and faces nearby
    return x, rc


@pytest.mark.parametrize("d", [2, 3])
def test_verlet_coincident_and_face_points(d):
    rng = np.random.default_rng(30 + d)
    x, rc = _degenerate_set(d, rng)
    n = len(x)
    expected = brute_pairs(x, rc)
    for domain in (None, (np.zeros(d), np.ones(d))):
        cl = ARCellListRef(x, rc, domain=domain)
        for method in ("vectorized", "loop"):
            check_symmetric(*cl.verlet_list(method=method), n, expected)
            check_full(*cl.verlet_list(full=True, method=method), n, expected)
    # non-cubic domain, upper faces of the box below the cube's faces
    lo = np.full(d, -0.25)
    hi = np.ones(d)
    hi[0] = 2.0
    cl = ARCellListRef(x, rc, domain=(lo, hi))
    assert cl.edge == fitted_root(2.25, rc, MAX_LEVEL[d]) >= 2.25 and np.all(cl.hi == lo + cl.edge)
    check_symmetric(*cl.verlet_list(), n, expected)
    expected_s = brute_pairs(x, rc, 0.01)
    check_symmetric(*cl.verlet_list(skin=0.01), n, expected_s)


@pytest.mark.parametrize("d", [2, 3])
def test_all_points_coincident(d):
    x = np.full((7, d), 0.3)
    rc = np.array([1.0, 0.5, 0.1, 1e-3, 1e-3, 2.0, 0.2])
    cl = ARCellListRef(x, rc)
    assert cl.edge == np.nextafter(rc.min(), np.inf)             # a root of one cell, every particle on it
    assert np.all(cl.level == 0)
    n = len(x)
    expected = brute_pairs(x, rc)
    assert expected.size == n * (n - 1) // 2
    check_symmetric(*cl.verlet_list(), n, expected)
    check_full(*cl.verlet_list(full=True, method="loop"), n, expected)


@pytest.mark.parametrize("d", [2, 3])
def test_loop_equals_vectorized_and_recursive_equals_sort(d):
    """Algorithm 3 literal (Op1-Op5 per particle) vs the vectorised sweep, and
    Algorithm 2 literal (recursive partition) vs one sort by J: identical results."""
    rng = np.random.default_rng(40 + d)
    n = 500
    x = rng.random((n, d)) ** 2          # denser near the origin
    rc = loguniform_cutoffs(rng, n, 1e-3)
    a = ARCellListRef(x, rc, method="sort")
    b = ARCellListRef(x, rc, method="recursive")
    np.testing.assert_array_equal(a.order, b.order)
    assert a.cells == b.cells
    assert a.finer == b.finer
    for skin in (0.0, 0.003):
        for full in (False, True):
            v = a.verlet_list(skin=skin, full=full)
            lp = b.verlet_list(skin=skin, full=full, method="loop")
            np.testing.assert_array_equal(v[0], lp[0])
            np.testing.assert_array_equal(v[1], lp[1])


def test_symmetric_row_is_finder():
    """Half list: a pair sits in the row of the coarser particle (Algorithm 3)."""
    rng = np.random.default_rng(5)
    x = rng.random((800, 2))
    rc = loguniform_cutoffs(rng, 800, 1e-3)
    cl = ARCellListRef(x, rc)
    off, ind = cl.verlet_list()
    rows = np.repeat(np.arange(800), np.diff(off))
    assert np.all(cl.level[rows] <= cl.level[ind])
    same = cl.level[rows] == cl.level[ind]
    # on equal levels: same cell -> earlier sorted position; else smaller J
    sc = same & (cl.cell_of[rows] == cl.cell_of[ind])
    assert np.all(cl.rank[rows[sc]] < cl.rank[ind[sc]])
    assert np.all(cl.cell_of[rows[same & ~sc]] < cl.cell_of[ind[same & ~sc]])


# ---------------------------------------------------------------- cross list
@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("skin", [0.0, 0.01])
def test_cross_list_vs_brute(d, skin):
    rng = np.random.default_rng(50 + d + int(skin > 0))
    n, m = 1200, 700
    x = rng.random((n, d))
    rc = loguniform_cutoffs(rng, n, 1e-3 if d == 2 else 3e-3)
    rc[:3] = [1.5, 4.0, 300.0]                      # level 0 with rc > D_m
    xq = rng.random((m, d)) * 2.0 - 0.5             # partly outside the domain
    xq[:50] = x[rng.integers(0, n, 50)]             # on reference points
    xq[50:80, 0] = 1.0                              # on the upper x face
    xq[80:90] = x.max(axis=0)                       # corner of the bounding box
    xq[90] = 100.0                                  # far away
    xq[91] = -50.0
    rq = loguniform_cutoffs(rng, m, 1e-3)
    rq[90:92] = 1e4
    cl = ARCellListRef(x, rc)
    off, ind = cl.cross_list(xq, rq, skin=skin)
    assert off.shape == (m + 1,)
    codes, _ = csr_codes(off, ind, n)
    assert np.all(np.diff(codes) > 0)
    expected = brute_cross(xq, rq, x, rc, skin)
    np.testing.assert_array_equal(codes, expected)
    assert ind[off[90]:off[91]].tolist() == [2]     # only rc = 300 reaches x = 100


def test_cross_list_against_itself_is_full_list_plus_self():
    rng = np.random.default_rng(7)
    x = rng.random((600, 3))
    rc = loguniform_cutoffs(rng, 600, 5e-3)
    cl = ARCellListRef(x, rc)
    off, ind = cl.cross_list(x, rc)
    codes, rows = csr_codes(off, ind, 600)
    assert np.count_nonzero(rows == ind) == 600
    keep = rows != ind
    f_off, f_ind = cl.verlet_list(full=True)
    np.testing.assert_array_equal(codes[keep], csr_codes(f_off, f_ind, 600)[0])


# ----------------------------------------------------- J index and Op1 - Op5
def test_level_order_index_small_cases():
    x = np.array([[0.0, 0.0], [1.0, 1.0]])
    cl = ARCellListRef(x, np.array([1.0, 1.0]))
    # Op1: child numbers follow Algorithm 2's split order, axis 0 first
    assert cl.find_cell([0.5, 0.5], 0) == 1
    assert cl.find_cell([0.25, 0.25], 1) == 2
    assert cl.find_cell([0.25, 0.75], 1) == 3
    assert cl.find_cell([0.75, 0.25], 1) == 4
    assert cl.find_cell([0.75, 0.75], 1) == 5
    assert cl.find_cell([1.0, 1.0], 1) == 5          # upper face -> last cell
    assert cl.find_cell([0.1, 0.1], 2) == 6
    assert cl.find_cell([1.0, 1.0], 2) == 21
    assert cl.find_cell([1.5, 0.5], 1) is None       # outside
    assert [level_first_index(k, 2) for k in range(4)] == [1, 2, 6, 22]
    assert [level_first_index(k, 3) for k in range(4)] == [1, 2, 10, 74]
    assert cl.children(1) == [2, 3, 4, 5]
    assert cl.children(3) == [10, 11, 12, 13]
    assert cl.parent(1) is None
    assert [cl.parent(j) for j in (2, 5, 6, 9, 10, 21)] == [1, 1, 2, 2, 3, 5]
    assert cl.cell_coords(13) == (2, (1, 3))
    assert sorted(cl.neighbor_cells(2)) == [3, 4, 5]


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("method", ["sort", "recursive"])
def test_cells_table_and_operations(d, method):
    rng = np.random.default_rng(60 + d)
    n = 700
    x = rng.random((n, d))
    x[:20] = x[20:40]                                      # duplicates
    x[40:60, 1] = 1.0                                      # upper face
    m = rng.integers(1, 9, (80, d))
    x[60:140] = rng.integers(0, 2 ** m + 1) / 2.0 ** m     # interior cell faces
    rc = loguniform_cutoffs(rng, n, 1e-3)
    cl = ARCellListRef(x, rc, domain=(np.zeros(d), np.ones(d)), method=method)
    nc = 2 ** d
    tol = 1e-12 * cl.edge

    # cells: half-open ranges tile [0, n) in increasing J
    keys = sorted(cl.cells)
    bounds = [cl.cells[j] for j in keys]
    assert bounds[0][0] == 0 and bounds[-1][1] == n
    assert all(b[0] < b[1] for b in bounds)
    assert all(b0[1] == b1[0] for b0, b1 in zip(bounds, bounds[1:]))

    for J in keys:
        k, c = cl.cell_coords(J)
        assert cl.cell_from_coords(k, c) == J
        members = cl.particles_in_cell(J)                   # Op2
        np.testing.assert_array_equal(np.sort(members), np.flatnonzero(cl.cell_of == J))
        assert np.all(cl.level[members] == k)
        lo, hi = cl.cell_region(J)
        assert np.all(x[members] >= lo - tol) and np.all(x[members] <= hi + tol)
    for p in range(n):                                      # Op1 agrees with the build
        assert cl.find_cell(x[p], cl.level[p]) == cl.cell_of[p]
        assert cl.find_cell_for_cutoff(x[p], rc[p]) == cl.cell_of[p]

    # finer == all strict ancestors (via Op4) of the non-empty cells
    anc = set()
    for J in keys:
        P = cl.parent(J)
        while P is not None:
            anc.add(P)
            P = cl.parent(P)
    assert anc == set(cl.finer)

    # Op3 / Op4 consistency and tiling of child regions
    for J in set(keys) | set(cl.finer):
        ch = cl.children(J)
        assert len(ch) == nc and ch == list(range(ch[0], ch[0] + nc))
        assert all(cl.parent(c) == J for c in ch)
        plo, phi = cl.cell_region(J)
        h = (phi - plo) / 2
        corners = {tuple(np.round((cl.cell_region(c)[0] - plo) / h).astype(int)) for c in ch}
        assert corners == set(product((0, 1), repeat=d))
        if J in cl.finer:
            assert any(cl.cell_exists(c) for c in ch)

    # Op5 against its literal definition: centre +- edge, then Op1
    for J in list(keys)[::7] + list(cl.finer)[::7]:
        k, _ = cl.cell_coords(J)
        lo, hi = cl.cell_region(J)
        centre = 0.5 * (lo + hi)
        h = hi - lo
        lit = set()
        for off in product((-1, 0, 1), repeat=d):
            if any(off):
                Jn = cl.find_cell(centre + np.array(off) * h, k)
                if Jn is not None:
                    lit.add(Jn)
        assert set(cl.neighbor_cells(J)) == lit
        assert set(cl.neighbor_cells(J, existing_only=True)) == {
            j for j in lit if j in cl.cells or j in cl.finer}


# ----------------------------------------------------------- depth limits
@pytest.mark.parametrize("d", [2, 3])
def test_depth_limit(d):
    L = MAX_LEVEL[d]
    assert L == {2: 30, 3: 20}[d]
    base = np.array(list(product([0.0, 1.0], repeat=d)))
    # a cluster of deepest-level particles
    cl_pts = 0.3 + np.arange(12)[:, None] * np.array([3e-10 * 2 ** (30 - L)] + [1e-10] * (d - 1))
    x = np.vstack((base, cl_pts))
    rc = np.full(len(x), 0.9)
    rc[len(base):] = 2.0 ** -(L + 1)                       # exactly level L
    cl = ARCellListRef(x, rc, domain=(np.zeros(d), np.ones(d)))
    assert cl.maxlevel == L
    expected = brute_pairs(x, rc)
    assert np.any(expected // len(x) >= len(base))        # deep pairs exist
    check_symmetric(*cl.verlet_list(), len(x), expected)
    check_symmetric(*cl.verlet_list(method="loop"), len(x), expected)
    assert max(cl.cells) < 2 ** 63
    rc[-1] = np.nextafter(rc[-1], 0.0)                     # now level L + 1
    with pytest.raises(ValueError, match="level"):
        ARCellListRef(x, rc, domain=(np.zeros(d), np.ones(d)))


# ---------------------------------------------------- halo ghost-ghost rule
def test_halo_bits_filter():
    rng = np.random.default_rng(9)
    n = 900
    x = rng.random((n, 2))
    rc = loguniform_cutoffs(rng, n, 2e-3)
    bits = np.zeros(n, np.int64)
    bits[x[:, 0] > 0.8] |= 1
    bits[x[:, 1] > 0.8] |= 2
    cl = ARCellListRef(x, rc)
    expected = brute_pairs(x, rc)
    p, q = expected // n, expected % n
    keep = (bits[p] == 0) | (bits[q] == 0) | ((bits[p] & bits[q]) == 0)
    assert not np.all(keep) and np.any(keep & (bits[p] > 0) & (bits[q] > 0))
    check_symmetric(*cl.verlet_list(halo_bits=bits), n, expected[keep])


# ------------------------------------------------------------------ bad input
def test_bad_input():
    x = np.random.default_rng(0).random((10, 2))
    rc = np.full(10, 0.1)
    with pytest.raises(ValueError):
        ARCellListRef(x[:, :1], rc)
    with pytest.raises(ValueError):
        ARCellListRef(x, rc[:5])
    with pytest.raises(ValueError):
        ARCellListRef(np.empty((0, 2)), np.empty(0))
    bad = x.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ARCellListRef(bad, rc)
    for r in (0.0, -1.0, np.inf, np.nan):
        rr = rc.copy()
        rr[2] = r
        with pytest.raises(ValueError):
            ARCellListRef(x, rr)
    with pytest.raises(ValueError, match="outside"):
        ARCellListRef(x, rc, domain=(np.zeros(2), np.full(2, 0.5)))
    cl = ARCellListRef(x, rc)
    with pytest.raises(ValueError):
        cl.verlet_list(skin=-1.0)
    with pytest.raises(ValueError):
        cl.cross_list(x[:, :1], rc)
