"""Hostile but fair input: no hang, no crash, no silent wrong answer.

Each case is an input at the edge of what the core handles (extreme extents and
scales, copied or freed trees, re-entrant calls, allocation failures).  Cases
that could hang or kill the interpreter run in a subprocess with a timeout.
"""

from __future__ import annotations

import copy
import math
import pickle
import re
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial import cKDTree

import arpy
from arpy.reference import brute_force_pairs

METHODS = ["brute", "cell", "ar", "auto"]


def run_isolated(code: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter; a hang fails the test instead of blocking it."""
    try:
        return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                              timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"did not finish within {timeout} s:\n{code}")


def periodic(kw: dict, k: int) -> dict:
    """The keyword arguments of neighbor_list with lengths times 2**k, ``box`` as a periodic Domain."""
    out = {key: math.ldexp(v, k) for key, v in kw.items() if key != "box"}
    if "box" in kw:
        out["domain"] = arpy.Domain(np.ldexp(kw["box"], k), periodic=True)
    return out


def pairs_of(found) -> set[tuple[int, int]]:
    """The pairs of a NeighborList, or an (i, j) pair of index arrays, as a set."""
    i, j = found.pairs() if hasattr(found, "pairs") else found
    return set(zip(i.tolist(), j.tolist()))


# ---------------------------------------------------------------- 1. hangs at huge extents
def test_huge_extent_is_refused_promptly_by_every_entry_point():
    r = run_isolated("""
        import numpy as np, arpy
        x = np.array([[-1e308, 0.0], [1e308, 0.0]])
        for call in (lambda: arpy.neighbor_list(x, 1.0),
                     lambda: arpy.neighbor_list(x, 1.0, method="auto"),
                     lambda: arpy.neighbor_list(x, 1.0, method="ar"),
                     lambda: arpy.neighbor_list(x, 1.0, method="brute"),
                     lambda: arpy.ARCellList(x, 1.0),
                     lambda: arpy.DCPSE(x, 1.0)):
            try:
                call()
            except ValueError as err:
                assert "range" in str(err), err
            else:
                raise AssertionError("accepted")
        print("ok")
        """, timeout=60)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr


# ---------------------------------------------------------------- 2. overflow / underflow
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("scale", [1e300, 1e-300])
def test_squared_distances_do_not_overflow_or_underflow(method, scale):
    x = np.array([[0.0, 0.0], [3.0, 0.0], [4.5, 0.0]]) * scale
    rc = np.array([2.0, 2.0, 2.0]) * scale
    # 0-1 at distance 3 > 2 and 0-2 at 4.5: no pair; 1-2 at 1.5: a pair
    assert pairs_of(arpy.neighbor_list(x, rc, method=method)) == {(1, 2)}


def test_an_ar_tree_whose_root_cell_passes_the_largest_double_is_refused_with_its_reason():
    """An AR tree's root cell is the smallest cutoff times a power of two, up to twice the extent: with
    a coordinate just above 2**1023 it is 2**1024, beyond the largest double.  ARCellList refuses that
    with a ValueError naming the root cell (it raised OverflowError from its edge); lengths below
    2**1021 build, and the list is the brute-force one; neighbor_list(method="ar") keeps its answer."""
    x = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, np.nextafter(2.0 ** 1023, np.inf)]])
    rc = np.full(3, np.nextafter(2.0 ** 994, 0.0))
    with pytest.raises(ValueError, match="root cell"):
        arpy.ARCellList(x, rc)
    # (the reference on the lengths scaled by 2**-1000, exact: its squares would overflow at full size)
    scaled = lambda *v: [np.ldexp(a, -1000) for a in v]                     # noqa: E731
    assert pairs_of(arpy.neighbor_list(x, rc, method="ar")) == pairs_of(brute_force_pairs(*scaled(x, rc))) == {(0, 1)}
    for top in (np.nextafter(2.0 ** 1021, 0.0), 2.0 ** 1020):
        y, ry = np.array([[0.0, 0.0], [0.0, 0.0], [-top, top], [top, top]]), np.full(4, top)
        tree = arpy.ARCellList(y, ry)
        assert np.isfinite(tree.edge) and tree.edge >= 2 * top
        assert pairs_of(tree.verlet_list()) == pairs_of(brute_force_pairs(*scaled(y, ry))) == {(0, 1)}


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("d", [2, 3])
def test_lists_are_exact_over_the_whole_exponent_range(method, d, rng):
    """Scaling by a power of two is exact: the list must not change from 2**-1000 to 2**1000."""
    x = rng.random((200, d))
    rc = rng.uniform(0.02, 0.2, 200)
    want = pairs_of(arpy.neighbor_list(x, rc, method="brute"))
    assert want == pairs_of(brute_force_pairs(x, rc))
    for k in range(-1000, 1001, 125):
        xs, rcs = np.ldexp(x, k), np.ldexp(rc, k)
        assert pairs_of(arpy.neighbor_list(xs, rcs, method=method)) == want, k
        assert pairs_of(arpy.neighbor_list(xs, rcs, method=method, full=True)) == want, k


def test_source_rows_are_exact_over_the_exponent_range(rng):
    """The particles' own rows (the simulation's stencil rows) scale as the lists do, also where the
    core first reports the lengths out of its range and the search runs again on scaled copies."""
    from arpy.lists.search import source_rows
    x = rng.random((180, 2))
    rc = np.where(x[:, 0] < 0.5, 0.03, 0.12)
    want = source_rows(x, rc, 150)
    for k in (-1040, -600, -300, 300, 600, 1000):
        got = source_rows(np.ldexp(x, k), np.ldexp(rc, k), 150)
        assert np.array_equal(got.offsets, want.offsets) and np.array_equal(got.indices, want.indices), k
    with pytest.raises(ValueError, match="range"):
        source_rows(np.array([[0.0, 0.0], [1e300, 0.0]]), np.array([1e-300, 1e-300]), 2)


def test_lists_with_skin_and_periodic_box_at_extreme_scales(rng):
    x = rng.random((150, 2))
    rc = rng.uniform(0.02, 0.1, 150)
    box = np.array([1.0, 1.0])
    for kw in (dict(skin=0.01), dict(box=box), dict(box=box, skin=0.01)):
        want = pairs_of(arpy.neighbor_list(x, rc, method="brute", **periodic(kw, 0)))
        for k in (-1040, -600, 600, 1000):
            got = arpy.neighbor_list(np.ldexp(x, k), np.ldexp(rc, k), method="cell", **periodic(kw, k))
            assert pairs_of(got) == want, (kw, k)


def test_ar_tree_and_cross_lists_at_extreme_scales(rng):
    x, rc = rng.random((120, 3)), rng.uniform(0.05, 0.2, 120)
    q, rq = rng.random((40, 3)) * 1.2 - 0.1, rng.uniform(0.05, 0.2, 40)
    tree = arpy.ARCellList(x, rc)
    want_v, want_c = pairs_of(tree.verlet_list()), pairs_of(tree.cross_list(q, rq))
    for k in (-1000, -700, 700, 1000):
        t = arpy.ARCellList(np.ldexp(x, k), np.ldexp(rc, k))
        assert t.edge == math.ldexp(tree.edge, k) and np.array_equal(t.lo, np.ldexp(tree.lo, k))
        assert np.array_equal(t.level, tree.level)
        assert pairs_of(t.verlet_list()) == want_v
        assert pairs_of(t.cross_list(np.ldexp(q, k), np.ldexp(rq, k))) == want_c
        assert t.find_cell(np.ldexp(x[0], k), 3) == tree.find_cell(x[0], 3)


def test_lengths_spanning_more_than_double_precision_are_refused():
    x = np.array([[0.0, 0.0], [1e200, 0.0]])
    with pytest.raises(ValueError, match="range"):
        arpy.neighbor_list(x, np.array([1e-120, 1.0]))
    # a span of 2**900 is still computed, exactly
    got = arpy.neighbor_list(np.array([[0.0, 0.0], [2.0 ** 450, 0.0], [2.0 ** 450, 2.0 ** -449]]),
                             np.array([2.0 ** 451, 2.0 ** -449, 2.0 ** -449]))
    assert pairs_of(got) == {(1, 2)}


def test_non_finite_queries_are_named(rng):
    tree = arpy.ARCellList(rng.random((60, 2)), 0.2)
    for bad in (np.nan, np.inf):
        q = np.array([[0.5, 0.5], [0.1, bad]])
        with pytest.raises(ValueError, match="cross_list: position of particle 1 is not finite"):
            tree.cross_list(q, 0.2)


def test_far_queries_have_empty_rows_not_errors(rng):
    x, rc = rng.random((60, 2)), np.full(60, 0.2)
    q = np.array([[0.5, 0.5], [1e300, 0.5], [-1e308, 1e308], [0.1, 0.9]])
    nl = arpy.cross_neighbor_list(q, 0.2, x, rc)
    want = cKDTree(x).query_ball_point(q[[0, 3]], 0.2)
    assert [sorted(nl.neighbors(p).tolist()) for p in range(4)] == [sorted(want[0]), [], [], sorted(want[1])]


# ---------------------------------------------------------------- 3. copies of a tree
@pytest.mark.parametrize("clone", [copy.copy, copy.deepcopy, lambda t: pickle.loads(pickle.dumps(t))])
def test_copied_tree_is_independent(clone, rng):
    x = rng.random((100, 2))
    t = arpy.ARCellList(x, 0.1)
    want = pairs_of(t.verlet_list())
    t2 = clone(t)
    del t
    t3 = arpy.ARCellList(rng.random((50, 2)), 0.03)      # may take the freed handle
    assert pairs_of(t2.verlet_list()) == want
    assert pairs_of(t3.verlet_list()) == pairs_of(brute_force_pairs(t3._x, t3._rc))
    assert t2.cells and t2.n == 100


def test_tree_keeps_its_particles_when_the_caller_changes_them(rng):
    x = rng.random((80, 2))
    t = arpy.ARCellList(x, 0.1)
    want = pairs_of(t.verlet_list(skin=0.05))
    x[:] = 0.0
    assert pairs_of(t.verlet_list(skin=0.05)) == want


# ---------------------------------------------------------------- 4. DC-PSE order, allocation
def test_absurd_dcpse_order_is_refused_up_front(rng):
    src = rng.random((300, 2))
    for order in (200, 1000, 13, 1, 2.5, True):
        with pytest.raises(ValueError, match="order"):
            arpy.DCPSE(src, np.full(300, 0.2), order=order, strict=False)
    op = arpy.DCPSE(src, np.full(300, 0.35), order=arpy.dcpse.kernel.MAX_ORDER, strict=False)
    assert op.n_neighbors.max() > 78


def test_core_allocation_failure_is_a_memory_error():
    r = run_isolated("""
        import resource, numpy as np, arpy
        x = np.random.default_rng(0).random((30000, 2))
        arpy.neighbor_list(x[:10], 0.1)                   # core loaded before the cap
        resource.setrlimit(resource.RLIMIT_AS, (1500 * 2**20, resource.RLIM_INFINITY))
        try:
            arpy.neighbor_list(x, 2.0)                    # 4.5e8 pairs: 1.8 GB of indices
        except MemoryError as err:
            print("MemoryError:", err)
        """, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "MemoryError: neighbor_list: the arpy core could not allocate memory" in r.stdout


# ---------------------------------------------------------------- 5. re-entrant calls
def test_a_signal_handler_may_call_arpy_between_build_and_collection():
    r = run_isolated("""
        import os, signal, numpy as np, arpy, arpy.lists.search as nb
        from arpy.reference import brute_force_pairs
        rng = np.random.default_rng(5)
        xa, xb = rng.random((300, 2)), rng.random((200, 3))
        got = {}
        def handler(signum, frame):
            got["b"] = arpy.neighbor_list(xb, 0.15).pairs()
            got["tree"] = arpy.ARCellList(xb, 0.15).verlet_list().pairs()
        signal.signal(signal.SIGUSR1, handler)
        real = nb.raise_for_info
        sent = []
        def raise_then_signal(*args, **kwargs):       # runs after the core published its list
            real(*args, **kwargs)
            if not sent:
                sent.append(1)
                os.kill(os.getpid(), signal.SIGUSR1)
        nb.raise_for_info = raise_then_signal
        a = arpy.neighbor_list(xa, 0.1).pairs()
        nb.raise_for_info = real
        as_set = lambda p: set(zip(p[0].tolist(), p[1].tolist()))
        assert "b" in got
        assert as_set(a) == as_set(brute_force_pairs(xa, 0.1))
        assert as_set(got["b"]) == as_set(got["tree"]) == as_set(brute_force_pairs(xb, 0.15))
        print("ok")
        """, timeout=60)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr


def test_an_uncollected_list_does_not_block_later_calls(rng):
    x = rng.random((50, 2))
    handle, nnz, info, bad = arpy._core.arpy_neighbors(x.T, np.full(50, 0.2), 0.0, 1, 0, 1, 0, np.empty(0, np.int64))
    assert info == 0 and handle > 0
    assert pairs_of(arpy.neighbor_list(x, 0.2)) == pairs_of(brute_force_pairs(x, 0.2))
    offsets, indices = np.empty(51, np.int64), np.empty(nnz, np.int32)
    info = arpy._core.arpy_result_take(handle, offsets, indices)
    assert info == 0 and offsets[-1] == nnz
    info = arpy._core.arpy_result_take(handle, offsets, indices)          # taken: gone
    with pytest.raises(arpy.ArpyError, match="no result"):
        arpy._errors.raise_for_info(info)


# ---------------------------------------------------------------- 6. self-organization without a gradient
@pytest.mark.parametrize("case", ["one particle, periodic", "two far apart", "resolution above the box"])
def test_self_organize_without_any_gradient(case):
    if case == "one particle, periodic":
        ps = arpy.self_organize(np.array([[0.5, 0.5]]), lambda p: np.full(len(p), 0.1), domain=arpy.Domain([1, 1], periodic=True), adapt_number=False)
    elif case == "two far apart":
        ps = arpy.self_organize(np.array([[0.1, 0.1], [0.9, 0.9]]), lambda p: np.full(len(p), 0.01),
                                adapt_number=False)
    else:
        ps = arpy.self_organize(np.random.default_rng(1).random((50, 2)), lambda p: np.full(len(p), 1e6),
                                domain=arpy.Domain([1, 1]))
    assert ps.x.shape[1] == 2 and np.all(np.isfinite(ps.x))
    assert all(np.isnan(e["gamma"]) or e["gamma"] > 0 for e in ps.log)


def test_self_organize_refuses_a_resolution_positions_cannot_resolve(rng):
    with pytest.raises(ValueError, match="cannot resolve"):
        arpy.self_organize(rng.random((50, 2)), grad_f=lambda p: np.zeros_like(p), D0=1e-300, domain=arpy.Domain([1, 1]))


def test_self_organize_bad_parameters(rng):
    x = rng.random((30, 2))
    res = lambda p: np.full(len(p), 0.1)          # noqa: E731
    for kw in (dict(max_particles=np.nan), dict(max_particles=0), dict(max_iter=2.5), dict(tol=np.nan),
               dict(n_star=-1)):
        with pytest.raises(ValueError, match=next(iter(kw))):
            arpy.self_organize(x, res, domain=arpy.Domain([1, 1]), **kw)
    bad = x.copy()
    bad[7, 1] = np.nan
    with pytest.raises(ValueError, match="particle 7 is not finite"):
        arpy.self_organize(bad, res, domain=arpy.Domain([1, 1]))


# ---------------------------------------------------------------- lesser ones
def test_dcpse_edge_cases(rng):
    src = rng.random((120, 2))
    eps = np.full(120, 0.25)
    empty = arpy.DCPSE(src, eps, col_x=np.zeros((0, 2)), col_eps=np.zeros(0))
    assert empty.interpolation().shape == (0, 120) and empty.laplacian().shape == (0, 120)
    assert empty.gradient()[0].shape == (0, 120)
    # a collocation point far away has no stencil; the others are those of a set without it
    col = np.array([[0.5, 0.5], [1e300, 0.5], [0.3, 0.6]])
    with pytest.raises(arpy.DegenerateStencilError) as err:
        arpy.DCPSE(src, eps, col_x=col, col_eps=0.25)
    assert err.value.points.tolist() == [1] and err.value.n_neighbors.tolist() == [0]
    loose = arpy.DCPSE(src, eps, col_x=col, col_eps=0.25, strict=False)
    near = arpy.DCPSE(src, eps, col_x=col[[0, 2]], col_eps=0.25)
    assert loose.failed.tolist() == [1]
    lap = loose.laplacian().toarray()
    assert np.array_equal(lap[[0, 2]], near.laplacian().toarray()) and not lap[1].any()
    for kw, word in ((dict(c=0.0), "c must"), (dict(c=np.inf), "c must"), (dict(max_cond=0.5), "max_cond"),
                     (dict(max_cond=np.nan), "max_cond")):
        with pytest.raises(ValueError, match=word):
            arpy.DCPSE(src, eps, **kw)
    with pytest.raises(ValueError, match="collocation point 1 is not finite"):
        arpy.DCPSE(src, eps, col_x=np.array([[0.5, 0.5], [np.nan, 0.1]]))


def test_dcpse_with_a_huge_core_size_reports_its_neighbours(rng):
    src = rng.random((50, 2))
    op = arpy.DCPSE(src, 1e300, strict=False)
    assert np.all(op.n_neighbors == 49) and op.failed.size == 50      # singular (offsets ~1e-301 eps)
    with pytest.raises(arpy.DegenerateStencilError, match="singular"):
        arpy.DCPSE(src, 1e300)


@pytest.mark.parametrize("k", [-700, 700])
def test_dcpse_weights_scale_exactly(k, rng):
    """Operators of a set scaled by 2**k are those of the set times 2**(-k |alpha|), bitwise
    (the Laplacian's weights, times 2**(-2k), would leave the double range here)."""
    x = rng.random((150, 2))
    eps = np.full(150, 0.22)
    q = rng.random((20, 2)) * 0.8 + 0.1
    for col in (None, q):
        op = arpy.DCPSE(x, eps, col, None if col is None else 0.22, strict=False)
        big = arpy.DCPSE(np.ldexp(x, k), np.ldexp(eps, k), None if col is None else np.ldexp(col, k),
                         None if col is None else math.ldexp(0.22, k), strict=False)
        assert np.array_equal(op.failed, big.failed)
        for a, b in zip(op.gradient(), big.gradient()):
            assert (a - sp.csr_matrix(np.ldexp(b.toarray(), k))).count_nonzero() == 0
        if col is not None:
            assert (op.interpolation() - big.interpolation()).count_nonzero() == 0
        if k < 0:
            with pytest.raises(ValueError, match="overflow"):
                big.laplacian()


def test_auto_and_dcpse_fall_back_to_the_uniform_list_beyond_the_tree_depth(rng):
    grid = rng.random((150, 2))
    x = np.concatenate([grid, grid + 1e12])                # extent / cutoff = 3e12 > 2**30
    eps = np.full(len(x), 0.3)
    with pytest.raises(arpy._errors.TreeDepthError):
        arpy.neighbor_list(x, eps * np.r_[np.ones(len(x) - 1), 0.5], method="ar")
    rc = eps * np.r_[np.ones(len(x) - 1), 0.2]             # span 5: auto picks ar, which is too deep
    assert pairs_of(arpy.neighbor_list(x, rc, method="auto")) == pairs_of(brute_force_pairs(x, rc))
    box = [1e12 + 2.0, 1e12 + 2.0]                         # the same in a periodic box
    assert pairs_of(arpy.neighbor_list(x, rc, method="auto", domain=arpy.Domain(box, periodic=True))) == \
        pairs_of(arpy.neighbor_list(x, rc, method="cell", domain=arpy.Domain(box, periodic=True)))
    full = arpy.NeighborList.from_pairs(len(x), *arpy.neighbor_list(x, eps, method="brute").pairs(), full=True)
    op = arpy.DCPSE(x, eps, strict=False)
    assert (op.laplacian() - arpy.DCPSE(x, eps, neighbors=full, strict=False).laplacian()).count_nonzero() == 0
    q = np.concatenate([grid[:30] + 0.05, grid[:30] + 1e12 + 0.05])
    tree_free = arpy.cross_neighbor_list(q, 0.3, x, eps)
    want = cKDTree(x).query_ball_point(q, 0.3)
    assert [sorted(tree_free.neighbors(p).tolist()) for p in range(len(q))] == [sorted(w) for w in want]


def test_ar_cell_operations_validate_their_input(rng):
    t = arpy.ARCellList(rng.random((100, 2)), 0.1)
    for point in ([np.nan, 0.5], [np.inf, 0.5]):
        with pytest.raises(ValueError, match="finite"):
            t.find_cell(point, 3)
    assert t.find_cell([5.0, 0.5], 3) is None
    last = arpy.lists.ar._last_key(2)
    for op in (t.parent, t.neighbor_cells, t.particles_in_cell, t.children, t.cell_level):
        for bad in (0, -5, 2 ** 63 - 1, last + 1):
            with pytest.raises(ValueError, match="cell index"):
                op(bad)
        with pytest.raises(TypeError):
            op(1.5)
    assert t.cell_level(last) == arpy.lists.ar.MAX_LEVEL[2]
    assert t.parent(last) is not None


def test_periodic_ghosts_refuse_a_negative_skin():
    with pytest.raises(ValueError, match="skin"):
        arpy.periodic_ghosts(np.array([[0.1, 0.1]]), 0.1, arpy.Domain([1, 1], periodic=True), -0.5)


def test_simulation_refuses_steps_that_do_not_advance():
    x = np.stack(np.meshgrid(np.linspace(0.05, 0.95, 10), np.linspace(0.05, 0.95, 10)), -1).reshape(-1, 2)
    ps = arpy.self_organize(x, lambda p: np.full(len(p), 0.1), domain=arpy.Domain([1, 1], periodic=True), adapt_number=False,
                            max_iter=1)
    sim = arpy.Simulation(ps, np.sin(2 * np.pi * x[:, 0]), nu=0.01, D0=0.1, reorganize_every=0)
    for dt in (-1.0, 0.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="dt"):
            sim.step(dt)
    assert sim.t == 0.0 and sim.steps == 0
    for kw in (dict(cfl=0.0), dict(cfl=np.nan), dict(max_iter=0)):
        with pytest.raises(ValueError, match=next(iter(kw))):
            arpy.Simulation(ps, np.zeros(len(x)), nu=0.01, D0=0.1, **kw)


def test_the_range_of_the_core_is_the_one_python_scales_into():
    """RANGE_EXP of fortran/core/arpy_kinds.f90 is arpy._codes.RANGE_EXP, and the core refuses
    lengths just outside it (code 13) while Python's scaling keeps them inside."""
    from pathlib import Path
    import re

    src = (Path(__file__).resolve().parents[1] / "fortran" / "core" / "arpy_kinds.f90").read_text()
    assert int(re.search(r"RANGE_EXP\s*=\s*(\d+)", src).group(1)) == arpy._codes.RANGE_EXP
    e = arpy._codes.RANGE_EXP
    x = np.array([[0.0, 0.0], [1.0, 0.0]])
    for rc, xs in ((math.ldexp(1.0, -e - 1), x), (1.0, x * math.ldexp(1.0, e + 1))):
        out = arpy._core.arpy_neighbors(xs.T, np.full(2, rc), 0.0, 0, 0, 1, 0, np.empty(0, np.int64))
        assert out[2] == 13
        with pytest.raises(ValueError, match="range"):
            arpy._errors.raise_for_info(out[2])
    assert arpy._bridge.core_exponent(math.ldexp(1.0, e + 1), 1.0) != 0
    assert arpy._bridge.core_exponent(math.ldexp(1.0, e), math.ldexp(1.0, -e)) == 0


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("bad, word", [
    (("x", 0, np.nan), "not finite"), (("x", 1, np.inf), "not finite"), (("x", 0, -np.inf), "not finite"),
    (("rc", None, np.nan), "cutoff"), (("rc", None, 0.0), "cutoff"), (("rc", None, -1e-3), "cutoff"),
    (("rc", None, np.inf), "cutoff"), (("x", 1, 1e300), "range"), (("rc", None, 1e-305), "range")])
def test_a_bad_particle_among_many_is_named(d, bad, word):
    """The core checks large sets in parallel (one pass that tests finiteness and range by the
    same comparisons); the particle at fault, deep in the second thread's half, is still named (a
    length out of range is reported as the span of all lengths)."""
    what, axis, value = bad
    n = 30_000
    x = np.random.default_rng(8).random((n, d))
    rc = np.full(n, 0.01)
    p = 23_456
    if what == "x":
        x[p, axis if axis < d else 0] = value
    else:
        rc[p] = value
    for method in ("cell", "ar"):
        with pytest.raises(ValueError, match=word) as err:
            arpy.neighbor_list(x, rc, method=method)
        assert word == "range" or str(p) in str(err.value), (method, str(err.value))


@pytest.mark.parametrize("n", [1, 3, 7, 19_999, 20_001, 100_003])
@pytest.mark.parametrize("d", [1, 2, 3])
def test_column_extremes_are_numpys(n, d):
    """The core's per-column extremes (parallel blocks, four running minima per column) equal
    NumPy's; a NaN anywhere in a column, the last entry included, shows in that column only."""
    from arpy._validate import column_extremes
    rng = np.random.default_rng(n + d)
    x = rng.normal(size=(n, d)) * 1e3
    x[rng.integers(n), 0] = np.inf
    x[rng.integers(n), d - 1] = -np.inf
    lo, hi = column_extremes(x)
    assert np.array_equal(lo, x.min(axis=0)) and np.array_equal(hi, x.max(axis=0))
    for p in {0, n // 2, n - 1}:
        y = x.copy()
        y[p, d - 1] = np.nan
        lo, hi = column_extremes(y)
        assert np.isnan(lo[d - 1]) and np.isnan(hi[d - 1])
        assert np.array_equal(lo[:d - 1], x.min(axis=0)[:d - 1]) and np.array_equal(hi[:d - 1], x.max(axis=0)[:d - 1])


# ---------------------------------------------------------------- plain mistakes, each named
def _domain_calls() -> dict:
    """Every public function that takes ``domain=``, called with ``domain = bad``."""
    from arpy.adapt.forces import energy
    from arpy.adapt.resolution import SampledResolution
    from arpy.dcpse.displace import displace_until_valid
    from arpy.distributed import bisect, halo
    from arpy.domain import h_min, nearest
    from arpy.lists.reuse import ReusedLists

    x = np.random.default_rng(3).random((40, 2))
    D = np.full(40, 0.3)
    nl = arpy.neighbor_list(x, 0.3)
    dec, owner = bisect(x, 2)
    return {
        "neighbor_list": lambda bad: arpy.neighbor_list(x, 0.3, domain=bad),
        "neighbor_list, no particles": lambda bad: arpy.neighbor_list(np.zeros((0, 2)), 0.3, domain=bad),
        "cache_order": lambda bad: arpy.cache_order(x, domain=bad),
        "cache_order, one particle": lambda bad: arpy.cache_order(x[:1], domain=bad),
        "ARCellList": lambda bad: arpy.ARCellList(x, 0.3, domain=bad),
        "periodic_ghosts": lambda bad: arpy.periodic_ghosts(x, 0.3, bad),
        "nearest": lambda bad: nearest(x, y=x[:3], domain=bad),
        "h_min": lambda bad: h_min(x, domain=bad),
        "DomainDCPSE": lambda bad: arpy.DomainDCPSE(x, D, domain=bad),
        "self_organize": lambda bad: arpy.self_organize(x, lambda p: np.full(len(p), 0.3), domain=bad),
        "SampledResolution": lambda bad: SampledResolution(x, D, 2.0, bad),
        "field_resolution": lambda bad: arpy.field_resolution(x, x[:, 0], D, D0=0.3, domain=bad),
        "displace_until_valid": lambda bad: displace_until_valid(x, D, 2.0, domain=bad),
        "energy": lambda bad: energy(x, D, nl, domain=bad),
        "bisect": lambda bad: bisect(x, 2, domain=bad),
        "halo": lambda bad: halo(x, 0.3, dec, owner, domain=bad),
        "ReusedLists": lambda bad: ReusedLists(bad, 0.1),
        "NeighborList.vectors": lambda bad: nl.vectors(x, domain=bad),
        "NeighborList.shifts": lambda bad: nl.shifts(x, domain=bad),
        "NeighborList.to_sparse": lambda bad: nl.to_sparse(x, domain=bad),
        "Particles": lambda bad: arpy.Particles(x, D, 2.0, 6, domain=bad),
    }


@pytest.mark.parametrize("bad", [[1, 1], [], (1.0, 1.0), np.ones(2), "unit square"], ids=repr)
def test_a_domain_that_is_not_a_domain_is_named(bad):
    """``domain=[1, 1]`` gave ``AttributeError: 'list' object has no attribute 'for_dim'`` (an empty
    list was taken as free space): every entry point names the argument and what it takes."""
    for name, call in _domain_calls().items():
        with pytest.raises(TypeError, match=r"domain must be an arpy\.Domain \(e\.g\. arpy\.Domain\(\[1, 1\]\)\)"
                                            rf".*, got {type(bad).__name__}$") as err:
            call(bad)
        assert ("or None" in str(err.value)) == (name != "periodic_ghosts"), name
    with pytest.raises(TypeError, match="got NoneType"):
        arpy.periodic_ghosts(np.zeros((2, 2)), 0.3, None)


@pytest.mark.parametrize("i, j, words", [
    ([0, 1], [1, 5], r"pair 1 is \(1, 5\): an index outside \[0, 4\) \(4 particles\)"),
    ([0, -1], [1, 2], r"pair 1 is \(-1, 2\): an index outside \[0, 4\)"),
    ([0, 2], [1, 2], r"pair 1 is \(2, 2\): a particle paired with itself"),
    ([0, 2, 1], [1, 3, 0], r"the pair \(0, 1\) is given twice"),
    ([0, 2, 0], [1, 3, 1], r"the pair \(0, 1\) is given twice"),
    ([0, 1], [2], r"i and j must be arrays \(m,\) of one length m, got shapes \(2,\) and \(1,\)"),
    ([0.0], [1.5], r"i must hold integer particle indices, got dtype float64"),
])
@pytest.mark.parametrize("full", [False, True])
def test_from_pairs_refuses_what_is_not_a_pair(i, j, words, full):
    """Out-of-range, self and repeated pairs were taken (a list with wrong rows and counts)."""
    with pytest.raises((ValueError, TypeError), match="from_pairs: " + words):
        arpy.NeighborList.from_pairs(4, i, j, full=full)
    with pytest.raises(ValueError, match="n .* must be an integer >= 0, got -1"):
        arpy.NeighborList.from_pairs(-1, [], [])
    good = arpy.NeighborList.from_pairs(np.int64(4), np.array([2, 0], np.int32), [1, 3], full=full)
    assert good.pairs()[0].tolist() == [0, 1] and good.pairs()[1].tolist() == [3, 2]


def test_a_row_outside_the_list_is_an_index_error():
    """``nl.neighbors(-1)`` gave [] and ``nl.neighbors(-2)`` the row n - 2: an index outside [0, n) is
    refused, a negative one too (not counted from the end); so is a rank's box outside [0, P)."""
    from arpy.distributed import bisect

    nl = arpy.NeighborList.from_pairs(3, [0, 1], [1, 2])
    for p in (-1, -2, 3, np.int64(-1)):
        with pytest.raises(IndexError, match=rf"p = {p} is out of range: 3 particles, indices 0 <= p < 3"):
            nl.neighbors(p)
        with pytest.raises(IndexError, match=rf"p = {p} is out of range: 3 particles, indices 0 <= p < 3"):
            nl.stored_row(p)
    for p in (1.0, True):
        with pytest.raises(TypeError, match="p must be an integer index"):
            nl.neighbors(p)
        with pytest.raises(TypeError, match="p must be an integer index"):
            nl.stored_row(p)
    assert nl.stored_row(np.int32(1)).tolist() == [2] and nl.stored_row(2).tolist() == []
    assert sorted(nl.neighbors(np.int32(1)).tolist()) == [0, 2] and nl.neighbors(2).tolist() == [1]
    dec, _ = bisect(np.random.default_rng(6).random((20, 2)), 3)
    with pytest.raises(IndexError, match="r = -1 is out of range: 3 ranks"):
        dec.box(-1)
    assert np.array_equal(dec.box(np.int64(2))[0], dec.box(2)[0])


def test_bisect_refuses_positions_that_are_not_finite():
    """A NaN position gave degenerate boxes; on ranks, every rank refuses, also those without one."""
    from arpy.distributed import bisect, run_threads

    x = np.random.default_rng(5).random((60, 2))
    x[[7, 31], [1, 0]] = [np.nan, np.inf]
    with pytest.raises(ValueError, match=r"bisect: 2 positions not finite \(NaN or Inf\), the first of particle 7; "):
        bisect(x, 2)

    def rank(comm):
        try:
            bisect(x[comm.rank::2], 2, comm=comm)              # rank 1 holds both (its particles 3 and 15)
        except ValueError as exc:
            return str(exc)
        return "accepted"

    assert run_threads(2, rank, timeout=10) == [
        "bisect: 2 positions not finite (NaN or Inf) (on other ranks); the boxes are cut at finite positions only",
        "bisect: 2 positions not finite (NaN or Inf), 2 on this rank (the first of its particle 3); the boxes are cut "
        "at finite positions only"]
    x[[7, 31]] = 0.5
    assert run_threads(2, rank, timeout=10) == ["accepted", "accepted"]


def test_a_wall_condition_on_a_box_without_walls_is_refused():
    """``Dirichlet(1.0)`` on a fully periodic box was silently ignored."""
    from arpy.dcpse.boundary import Dirichlet, Neumann, conditions

    torus = arpy.Domain([1.0, 1.0], periodic=True)
    for bc in (Dirichlet(1.0), Neumann(0.5), Dirichlet(lambda w, t: w[:, 0])):
        with pytest.raises(ValueError, match=r"boundary condition .*: the box is periodic along every axis .* walls"):
            conditions(bc, torus)
    x = np.random.default_rng(4).random((50, 2))
    ps = arpy.Particles(x, np.full(50, 0.3), 2.0, 6, domain=torus)
    with pytest.raises(ValueError, match=r"Dirichlet\(value=1\.0\): the box is periodic along every axis"):
        arpy.Simulation(ps, x[:, 0], nu=0.01, D0=0.3, boundary=Dirichlet(1.0))
    with pytest.raises(ValueError, match=r"Dirichlet\(value=1\.0\): the box is periodic"):
        arpy.Simulation(ps, {"u": x[:, 0], "v": x[:, 1]}, nu=0.01, D0=0.3, boundary={"v": Dirichlet(1.0)})
    assert not conditions(Dirichlet(1.0), arpy.Domain([1.0, 1.0], periodic=(True, False))).dirichlet_faces[0].any()
    for value in ("one", None, [1.0, 2.0]):
        with pytest.raises(ValueError, match="the Dirichlet value must be a finite number .*, got "
                                             + re.escape(repr(value))):
            Dirichlet(value)



def test_a_sampled_resolution_names_a_bad_rstar():
    """rstar = -1 was blamed on the cutoff radii of an ARCellList the caller never made."""
    from arpy.adapt.resolution import SampledResolution

    x = np.random.default_rng(7).random((30, 2))
    for bad in (-1.0, 0.0, np.nan, np.inf):
        with pytest.raises(ValueError, match=rf"rstar must be a finite number > 0 .*, got {bad!r}"):
            SampledResolution(x, np.full(30, 0.2), bad)
