"""Threads: the core's parallel loops give bitwise the same results at 1 and 2 threads, and Python
threads calling arpy at the same time (the GIL is released) get the results of serial calls.

The core runs a loop on one thread below 20,000 rows (2,000 points for loops of heavier rows); the
tests of a few thousand particles lower these sizes for their runs at two threads
(:func:`parallel_from`), so that those runs take the parallel branches, and compare them with runs
at one thread and the default sizes."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
from typing import Iterator

import numpy as np
import pytest

import arpy
from arpy import _bridge
from arpy.reference import brute_force_pairs
from arpy.lists.search import source_rows
from arpy.lists.reuse import ReusedLists


@contextlib.contextmanager
def parallel_from(rows: int = 500, points: int = 50) -> Iterator[None]:
    """A ``with`` block in which the core's loops run in parallel from ``rows`` rows (loops over
    points: ``points``) on, instead of 20,000 (2,000); process-wide."""
    before = _bridge.set_parallel_thresholds(rows, points)
    try:
        yield
    finally:
        _bridge.set_parallel_thresholds(*before)


def threads_and_sizes(threads: int) -> contextlib.AbstractContextManager:
    """``threads`` core threads; at more than one, the parallel branches from small sizes on."""
    stack = contextlib.ExitStack()
    stack.enter_context(arpy.num_threads(threads))
    if threads > 1:
        stack.enter_context(parallel_from())
    return stack


def dcpse_outputs(op: arpy.DCPSE, ops) -> list[np.ndarray]:
    """Every array a DCPSE exposes: weights of each operator, neighbour counts, condition numbers."""
    mats = [op.interpolation() if o == "interpolation" else op.laplacian() if o == "laplacian" else op.derivative(o)
            for o in ops]
    return [m.data for m in mats] + [m.indices for m in mats] + [op.n_neighbors, op.cond, op.failed]


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="counts the process's threads in /proc")
def test_lowered_sizes_put_a_list_of_1500_particles_on_two_threads():
    """The tests' knob works: at two threads, a cell list of 1,500 particles starts no thread with the
    default sizes (its loops stay serial: its rows from 2,000 on) and starts one with the sizes
    lowered (a team of two).  In a Python thread of its own, whose OpenMP thread pool is new."""
    x = np.random.default_rng(0).random((1500, 2))
    seen: dict[str, set[str]] = {}
    lists: list[arpy.NeighborList] = []

    def tasks() -> set[str]:
        return set(os.listdir("/proc/self/task"))

    def run() -> None:
        seen["start"] = tasks()
        with arpy.num_threads(2):
            lists.append(arpy.neighbor_list(x, 0.03, method="cell"))
            seen["default"] = tasks()
            with parallel_from():
                lists.append(arpy.neighbor_list(x, 0.03, method="cell"))
            seen["lowered"] = tasks()

    t = threading.Thread(target=run)
    t.start()
    t.join(timeout=60)
    assert not t.is_alive() and len(lists) == 2
    assert all(a.tobytes() == b.tobytes() for a, b in zip((lists[0].offsets, lists[0].indices),
                                                          (lists[1].offsets, lists[1].indices)))
    assert not seen["default"] - seen["start"], "the default sizes started threads for 1,500 particles"
    assert seen["lowered"] - seen["default"], "the lowered sizes started no thread"


@pytest.mark.parametrize("d, order", [(2, 4), (2, 6), (3, 4)])
def test_dcpse_is_bitwise_the_same_at_one_and_two_threads(d, order):
    rng = np.random.default_rng(d + order)
    n = 3000 if d == 2 else 4000
    x = rng.random((n, d))
    eps = np.full(n, 0.07 if d == 2 else 0.2) * (1.3 if order == 6 else 1.0)
    y = rng.random((1500, d))
    grad = [tuple(int(i == j) for j in range(d)) for i in range(d)]
    results = []
    for threads in (1, 2):
        with threads_and_sizes(threads):
            assert arpy.get_num_threads() == threads
            at = arpy.DCPSE(x, eps, order=order, strict=False)
            off = arpy.DCPSE(x, eps, y, np.full(len(y), eps[0]), order=order, strict=False)
            results.append(dcpse_outputs(at, grad + ["laplacian"]) + dcpse_outputs(off, grad + ["interpolation"]))
    assert len(results[0]) == len(results[1])
    for a, b in zip(*results):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("d", [2, 3])
def test_neighbour_lists_are_bitwise_the_same_at_one_and_two_threads(d):
    """Large enough for the parallel row loops (above MIN_PARALLEL_ROWS); every method, both forms,
    a periodic box, the AR tree's own lists (its dense levels use the same loop) and cross lists."""
    rng = np.random.default_rng(d)
    n = 25000
    x = rng.random((n, d))
    rc = rng.uniform(0.004, 0.012, n) if d == 2 else rng.uniform(0.02, 0.05, n)
    # a second resolution for the AR tree (three levels up; two in 3D, where eight would give the wide
    # particles about 200 neighbours each)
    wide = rc * np.where(rng.random(n) < 0.1, 8.0 if d == 2 else 4.0, 1.0)
    torus = arpy.Domain(np.ones(d), periodic=True)
    results = []
    for threads in (1, 2):
        with arpy.num_threads(threads):
            out = []
            for method in ("cell", "ar"):
                for full in (False, True):
                    nl = arpy.neighbor_list(x, wide, method=method, full=full)
                    out += [nl.offsets, nl.indices]
                for full in (False, True):
                    nl = arpy.neighbor_list(x, rc, method=method, domain=torus, full=full)
                    out += [nl.offsets, nl.indices]
                order, nl = arpy.neighbor_list_in_cell_order(x, wide, method=method)
                out += [order, nl.offsets, nl.indices]
                # the particles in that order: a fixed point, whose list (the search keeps them where
                # they are) is the one found from the random order, and neighbor_list's of them
                again, same = arpy.neighbor_list_in_cell_order(x[order], wide[order], method=method)
                plain = arpy.neighbor_list(x[order], wide[order], method=method)
                assert np.array_equal(again, np.arange(n))
                for other in (nl, plain):
                    assert same.offsets.tobytes() == other.offsets.tobytes()
                    assert same.indices.tobytes() == other.indices.tobytes()
            # cross lists (queries in parallel from MIN_PARALLEL_POINTS on), near and outside the set
            y = rng.random((5000, d)) * 1.2 - 0.1 if threads == 1 else y
            nl = arpy.cross_neighbor_list(y, 2 * rc[:5000], x, wide)
            out += [nl.offsets, nl.indices]
            # the rows of the first sources (source_rows: sorted in parallel from MIN_PARALLEL_ROWS entries)
            nl = source_rows(x, wide, 20000)
            out += [nl.offsets, nl.indices]
            # Verlet lists reused after a drift (the filter of the stored rows runs in parallel)
            lists = ReusedLists(torus, 0.5)
            lists(x, 2 * rc)
            src, sx, se, nl = lists(torus.wrap(x + 0.1 * rc.min()), 2 * rc)
            assert lists.builds == 1
            out += [sx, nl.offsets, nl.indices]
            results.append(out)
    for a, b in zip(*results):
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
    i, j = brute_force_pairs(x[:3000], wide[:3000])                       # and the lists are right
    got = arpy.neighbor_list(x[:3000], wide[:3000], method="cell").pairs()
    assert np.array_equal(got[0], i) and np.array_equal(got[1], j)
    # the periodic fold in parallel blocks, against scipy's periodic search (one cutoff)
    from scipy.spatial import cKDTree
    r = float(rc.max())
    want = cKDTree(x, boxsize=1.0).query_pairs(r, output_type="ndarray")
    with arpy.num_threads(2):
        got = arpy.neighbor_list(x, np.full(n, r), method="ar", domain=torus).pairs()
    want = want[np.lexsort((want[:, 1], want[:, 0]))]
    assert np.array_equal(got[0], want[:, 0]) and np.array_equal(got[1], want[:, 1])


@pytest.mark.parametrize("d", [2, 3])
def test_ar_lists_over_many_levels_at_two_threads_equal_brute_force(d):
    """Cutoffs over two and a half decades (hashed and dense levels, leaves of every level in parallel blocks
    of the symmetric list, blocks of rows of the full list): at 2 threads (every loop in parallel) the
    lists are brute force's, and the same as at 1 thread; and source_rows gives the cross list's rows."""
    g = np.random.default_rng(10 + d)
    n = 6000
    x = g.random((n, d)) ** 2                                      # graded: dense where the cutoffs are small
    rc = 0.0005 * np.exp(g.uniform(0.0, np.log(300.0), n)) * (1.0 if d == 2 else 4.0)
    i, j = brute_force_pairs(x, rc)
    lists = {}
    for threads in (1, 2):
        with threads_and_sizes(threads):
            half = arpy.neighbor_list(x, rc, method="ar")
            full = arpy.ARCellList(x, rc).verlet_list(full=True, direct=True)
            rows = source_rows(x, rc, 4000)
            lists[threads] = [half.offsets, half.indices, full.offsets, full.indices, rows.offsets, rows.indices]
            got = half.pairs()
            assert np.array_equal(got[0], i) and np.array_equal(got[1], j)
            got = full.pairs()
            assert np.array_equal(got[0], i) and np.array_equal(got[1], j) and len(full) == 2 * i.size
            want = arpy.cross_neighbor_list(x[:4000], rc[:4000], x, rc).canonical()
            assert np.array_equal(rows.offsets, want.offsets) and np.array_equal(rows.indices, want.indices)
    for a, b in zip(lists[1], lists[2]):
        assert a.tobytes() == b.tobytes()


def test_self_organization_and_ten_simulation_steps_are_bitwise_the_same_at_one_and_two_threads():
    """A seeded self-organization (periodic box) and ten RK4 steps of an advection-diffusion run with a
    re-organization: particles, D and f identical at 1 and 2 threads (at 2, every loop in parallel)."""
    from arpy.cases.reversing_vortex import blob, blob_monitor, vortex

    torus = arpy.Domain([1.0, 1.0], periodic=True)
    results = []
    for threads in (1, 2):
        with threads_and_sizes(threads):
            x = np.random.default_rng(1).random((800, 2))
            ps = arpy.self_organize(x, resolution=lambda p: blob_monitor(p, 0.12), domain=torus, seed=1)
            sim = arpy.Simulation(ps, blob, velocity=vortex(2.5), nu=1e-3, D0=0.12, integrator="rk4", dt=0.0025,
                                  reorganize_every=5, seed=1)
            for _ in range(10):
                sim.step()
            results.append([ps.x, ps.D, sim.x, sim.D, sim.f])
    assert results[0][2].shape[0] > 2000
    for a, b in zip(*results):
        assert a.shape == b.shape and a.tobytes() == b.tobytes()


def test_threadpoolctl_limits_the_core_threads():
    """threadpoolctl sees the core's OpenMP runtime, and its limit is the core's default team
    (threadpoolctl is in the test extra: missing, the test fails)."""
    import threadpoolctl
    arpy.set_num_threads(0)
    arpy.neighbor_list(np.random.default_rng(0).random((100, 2)), 0.1)       # the core is loaded
    apis = {info["user_api"] for info in threadpoolctl.threadpool_info()}
    assert "openmp" in apis
    with threadpoolctl.threadpool_limits(limits=1, user_api="openmp"):
        assert arpy.get_num_threads() == 1
    with threadpoolctl.threadpool_limits(limits=2, user_api="openmp"):
        assert arpy.get_num_threads() == 2
        with arpy.num_threads(1):                        # arpy's own setting overrides it
            assert arpy.get_num_threads() == 1


def serial_and_concurrent(work, n_threads: int = 8) -> tuple[list, list]:
    """``work(k)`` for k = 0 .. n_threads - 1, one after the other on one core thread, and in n_threads
    Python threads at once, each core call with a team of two (every loop in parallel)."""
    with arpy.num_threads(1):
        serial = [work(k) for k in range(n_threads)]
    arpy.set_num_threads(2)
    sizes = _bridge.set_parallel_thresholds(64, 16)
    concurrent: list = [None] * n_threads
    errors: list = []
    start = threading.Barrier(n_threads)

    def run(k: int) -> None:
        try:
            start.wait()
            for _ in range(3):
                concurrent[k] = work(k)
        except Exception as exc:                   # reported below, in the test's thread
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(k,)) for k in range(n_threads)]
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=120)
    finally:
        arpy.set_num_threads(0)
        _bridge.set_parallel_thresholds(*sizes)
    assert not any(t.is_alive() for t in threads), "a thread did not finish"
    assert not errors, errors
    return serial, concurrent


def test_python_threads_calling_arpy_at_once_get_the_serial_results():
    rng = np.random.default_rng(7)
    sets = [(rng.random((4000, 2)), rng.uniform(0.005, 0.05, 4000)) for _ in range(8)]
    torus = arpy.Domain([1.0, 1.0], periodic=True)

    def work(k: int):
        x, rc = sets[k]
        out = []
        for method in ("cell", "ar", "brute" if k % 4 == 0 else "auto"):
            out += list(arpy.neighbor_list(x, rc, method=method, full=k % 2 == 1).pairs())
        out += list(arpy.neighbor_list(x, 0.02, domain=torus).pairs())
        tree = arpy.ARCellList(x, rc)
        out += [tree.order, tree.level] + list(tree.verlet_list().pairs())
        out += list(tree.cross_list(x[:500] + 0.001, 0.03).pairs())
        op = arpy.DCPSE(x, np.full(len(x), 0.05), strict=False)
        out += [op.laplacian().data, op.laplacian().indices, op.n_neighbors]
        return out

    serial, concurrent = serial_and_concurrent(work)
    for s, c in zip(serial, concurrent):
        assert len(s) == len(c)
        for a, b in zip(s, c):
            assert np.asarray(a).tobytes() == np.asarray(b).tobytes()


FORK_SCRIPT = """
import multiprocessing as mp, warnings, numpy as np, arpy
def work(seed):
    rng = np.random.default_rng(seed)
    x = rng.random((25000, 2))
    nl = arpy.neighbor_list(x, 0.01)
    op = arpy.DCPSE(x, np.full(len(x), 0.02), strict=False)
    return [len(nl), float(op.laplacian().data.sum()), arpy.get_num_threads()]
def child_asks_for_two(seed):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        arpy.set_num_threads(2)
    return [arpy.get_num_threads(), len(caught)]
if __name__ == "__main__":
    arpy.set_num_threads(2)
    parent = [work(s)[:2] for s in (1, 2)]
    with mp.get_context("fork").Pool(2) as pool:
        children = pool.map(work, [1, 2])
        asked = pool.map(child_asks_for_two, [0])
    assert [c[:2] for c in children] == parent, (children, parent)
    assert all(c[2] == 1 for c in children) and asked == [[1, 1]], (children, asked)
    print("ok")
"""


def test_a_forked_child_runs_on_one_thread_instead_of_hanging(tmp_path):
    """GNU OpenMP's thread pool does not survive fork(): a child forked after the parent ran parallel
    loops would wait forever in its first one.  arpy's children run on one thread (with the same
    results) and say so if asked for more."""
    script = tmp_path / "fork.py"
    script.write_text(FORK_SCRIPT)
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr


def test_thread_control():
    with arpy.num_threads(2):
        assert arpy.get_num_threads() == 2
        with arpy.num_threads(1):
            assert arpy.get_num_threads() == 1
        assert arpy.get_num_threads() == 2
    for bad in (-1, 1.5, "2", True):
        with pytest.raises(ValueError, match="threads"):
            arpy.set_num_threads(bad)



def test_thread_counts_above_the_bound_are_refused_and_never_stored():
    """A count above 4 per core is refused with the bound named (10**6 used to be accepted and kill
    the interpreter at the next large list; 2**40 raised f2py's OverflowError but stayed stored, so
    that the next ``with num_threads(1)`` raised on exit); a refused count changes nothing."""
    top = 4 * (os.cpu_count() or 1)
    try:
        arpy.set_num_threads(1)
        for bad in (top + 1, 10 ** 6, 2 ** 40, np.int64(top + 1)):
            with pytest.raises(ValueError, match=f"at most {top} .*got {int(bad)}$"):
                arpy.set_num_threads(bad)
            with pytest.raises(ValueError, match=f"at most {top}"):
                with arpy.num_threads(bad):
                    raise AssertionError("the block ran with a refused count")
            assert arpy.get_num_threads() == 1
            with arpy.num_threads(2):                     # the block before it left the setting as it was
                assert arpy.get_num_threads() == 2
            assert arpy.get_num_threads() == 1
        arpy.set_num_threads(top)
        assert arpy.get_num_threads() == top and arpy.threads.max_threads() == top
    finally:
        arpy.set_num_threads(0)


def test_numpy_integer_thread_counts_are_taken_and_bools_refused():
    try:
        arpy.set_num_threads(np.int64(2))
        assert arpy.get_num_threads() == 2
        with arpy.num_threads(np.int32(1)):
            assert arpy.get_num_threads() == 1
        assert arpy.get_num_threads() == 2
        for bad in (np.True_, True, np.float64(2.0), 2.0):
            with pytest.raises(ValueError, match="the number of threads must be an integer"):
                arpy.set_num_threads(bad)
            assert arpy.get_num_threads() == 2
    finally:
        arpy.set_num_threads(0)

def thp_mode() -> str:
    from pathlib import Path
    try:
        text = Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
    except OSError:
        return ""
    return text[text.index("[") + 1:text.index("]")] if "[" in text else ""


def test_huge_page_advice_is_a_setting_and_changes_no_list():
    """Lists whose arrays take the advice: with it on, the core advises three arrays of 4 to 18 MiB per
    list here (the search's positions, the rows' first storage of 8 entries per row and, as the rows
    outgrow it, the doubled storage; seen with strace).  The full lists of both methods are then the
    lists built with the advice off, bit for bit, and right (rows against scipy's kd-tree)."""
    from scipy.spatial import cKDTree

    before = arpy.set_huge_pages(False)
    try:
        assert arpy.set_huge_pages(True) is False
        assert arpy.set_huge_pages(True) is True
        for bad in (1, "yes", None):
            with pytest.raises(TypeError, match="True or False"):
                arpy.set_huge_pages(bad)
        rng = np.random.default_rng(5)
        n = 300_000
        x = rng.random((n, 2))
        rc = np.where(x[:, 0] < 0.5, 0.0021, 0.0063)
        assert 24 * n > 4 * 2 ** 20                  # the search's positions (3 x n doubles) above 4 MiB
        lists = {}
        for method in ("cell", "ar"):
            for on in (False, True):
                arpy.set_huge_pages(on)
                lists[method, on] = arpy.neighbor_list(x, rc, method=method, full=True)
            off, on_ = lists[method, False], lists[method, True]
            assert len(on_) > 2 * 8 * n              # (over twice the 8 entries per row first reserved)
            assert off.offsets.tobytes() == on_.offsets.tobytes() and off.indices.tobytes() == on_.indices.tobytes()
        tree = cKDTree(x)
        for p in rng.choice(n, 1000, replace=False):              # rows against an independent search
            near = np.asarray(tree.query_ball_point(x[p], rc[p]), np.int64)
            near = near[(near != p) & (np.sum((x[near] - x[p]) ** 2, axis=1) <= np.minimum(rc[near], rc[p]) ** 2)]
            for method in ("cell", "ar"):
                nl = lists[method, True]
                assert np.array_equal(np.sort(nl.neighbors(p)), np.sort(near)), (method, p)
    finally:
        arpy.set_huge_pages(before)


_HUGE_RUN = """
import re, sys
import numpy as np
import arpy

def anon_huge_kib():
    text = open("/proc/self/smaps_rollup").read()
    return int(re.search(r"AnonHugePages:\\s+(\\d+) kB", text).group(1))

x = np.random.default_rng(6).random((300_000, 2))
rc = np.full(len(x), 0.002)
grown = []
for on in (False, True):                     # (off first: freed huge pages may be reused)
    arpy.set_huge_pages(on)
    a = anon_huge_kib()
    tree = arpy.ARCellList(x, rc)
    grown.append(anon_huge_kib() - a)
    del tree
print(*grown)
"""


@pytest.mark.skipif(sys.platform != "linux" or thp_mode() != "madvise"
                    or not os.path.exists("/proc/self/smaps_rollup"),
                    reason="the advice shows only where the kernel's huge pages are 'madvise' (and smaps_rollup tells)")
def test_huge_page_advice_puts_a_large_tree_on_huge_pages():
    """The AR tree of 3e5 particles keeps 7 MiB of positions: with the advice, their aligned 2 MiB
    pages come on huge pages; without it none of the core's do (NumPy advises its own arrays).  In
    a process of its own, whose memory is fresh (reused memory keeps the pages it has), with glibc's
    default allocator (.ci/setup's MALLOC_* settings for the suite take large arrays from the heap)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    out = subprocess.run([sys.executable, "-c", _HUGE_RUN], check=True, capture_output=True, text=True,
                         timeout=120, env=env).stdout.split()
    off, on = (int(v) for v in out)
    assert on - off >= 2048, (off, on)


class _FakeWorld:
    """What MPIComm reads of an mpi4py communicator to set itself up (rank and size)."""

    def __init__(self, size: int) -> None:
        self.size = size

    def Get_rank(self) -> int:
        return 0

    def Get_size(self) -> int:
        return self.size


def test_an_mpi_comm_of_several_ranks_runs_one_thread_per_rank_unless_the_user_chose(monkeypatch):
    """MPIComm with P > 1 ranks (arpy.threads.one_thread_per_rank): one core thread per rank when the
    OpenMP default stands (here two threads), the user's count when OMP_NUM_THREADS is set or
    set_num_threads was called, and nothing at one rank."""
    from arpy.distributed import MPIComm
    from arpy.threads import _setting

    before = arpy.get_num_threads()
    monkeypatch.setitem(_setting, "requested", 0)      # restored with the count after the test

    def default_of_two() -> None:                      # as if OpenMP's default were two threads
        arpy.set_num_threads(2)
        _setting["requested"] = 0

    try:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
        for size, expected in ((1, 2), (2, 1), (4, 1)):
            default_of_two()
            MPIComm(_FakeWorld(size), abort_on_failure=False)
            assert arpy.get_num_threads() == expected, size
        arpy.set_num_threads(2)                        # the user's count stands, and can still change
        MPIComm(_FakeWorld(2), abort_on_failure=False)
        assert arpy.get_num_threads() == 2
        monkeypatch.setenv("OMP_NUM_THREADS", "2")
        default_of_two()
        MPIComm(_FakeWorld(2), abort_on_failure=False)
        assert arpy.get_num_threads() == 2
    finally:
        arpy.set_num_threads(before)
