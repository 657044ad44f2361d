"""The decomposition and ghost layers of distributed runs, checked in one process: every particle
owned once and by the box that contains it, balanced counts, and each simulated rank's lists over its
own particles and its ghosts holding exactly the serial rows of its own particles (free space,
periodic and mixed boxes, skins, cutoffs spanning a factor 1000, points on cut planes)."""

import itertools
import sys
import threading

import numpy as np
import pytest

import arpy
from arpy.distributed import Laplacian, bisect, exchange_ghosts, gather, halo, migrate, run_threads
from arpy.dcpse.domain import REPAIR

#: Seconds a test of this module may take (pytest-timeout): ranks that wait forever fail the test.
pytestmark = pytest.mark.timeout(60)


def rank_rows(x, rc, parts, domain=None, skin=0.0, method="auto"):
    """Per simulated rank: {global row: sorted global neighbours} of its own particles, from a
    free-space full list over its own particles and ghosts (ghosts carry their periodic shifts)."""
    dec, owner = bisect(x, parts, domain=domain)
    np.testing.assert_array_equal(dec.locate(x), owner)
    ghosts = halo(x, rc, dec, owner, skin=skin, domain=domain)
    rcs = np.broadcast_to(rc, (len(x),))
    rows = {}
    for r, (g, shift) in enumerate(ghosts):
        mine = np.flatnonzero(owner == r)
        ext = np.concatenate([x[mine], x[g] + shift])
        gid = np.concatenate([mine, g])
        nl = arpy.neighbor_list(ext, np.concatenate([rcs[mine], rcs[g]]), full=True, skin=skin,
                                method=method)
        for p in range(mine.size):
            rows[int(mine[p])] = np.sort(gid[nl.neighbors(p)])
    return dec, owner, ghosts, rows


def serial_rows(x, rc, domain=None, skin=0.0):
    nl = arpy.neighbor_list(x, rc, full=True, skin=skin, domain=domain)
    return {p: np.sort(nl.neighbors(p)) for p in range(len(x))}


def assert_same_rows(got, want):
    assert got.keys() == want.keys()
    for p, row in want.items():
        np.testing.assert_array_equal(got[p], row, err_msg=f"row {p}")


@pytest.mark.parametrize("parts", [1, 2, 3, 4, 7])
def test_bisection_owns_each_particle_once_and_balances_counts(parts):
    rng = np.random.default_rng(parts)
    x = rng.random((3000, 3)) * [4.0, 1.0, 2.0]
    x[:400, 0] = 1.5                                     # a plane of ties: cut planes may fall on it
    dec, owner = bisect(x, parts)
    counts = np.bincount(owner, minlength=parts)
    assert counts.sum() == len(x) and dec.parts == parts
    assert np.abs(counts - len(x) / parts).max() <= 400 + 2        # off its share by at most the tie plane
    np.testing.assert_array_equal(dec.locate(x), owner)
    lo, hi = x.min(0), x.max(0)
    np.testing.assert_allclose(np.prod(dec.hi - dec.lo, axis=1).sum(), np.prod(hi - lo), rtol=1e-12)
    w = np.where(x[:, 0] < 2.0, 3, 1)                    # weighted: about equal weight per box
    dec, owner = bisect(x, parts, weights=w)
    per = np.bincount(owner, weights=w, minlength=parts)
    assert np.abs(per - w.sum() / parts).max() <= 3 * 400 + 6


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("lam", [1.0, 10.0, 1000.0])
def test_rank_rows_equal_serial_rows_on_the_ar_benchmark(d, lam):
    x, rc = arpy.ar_benchmark(600 if d == 2 else 300, lam, d=d)
    want = serial_rows(x, rc)
    for parts in (2, 4, 5):
        _, _, ghosts, got = rank_rows(x, rc, parts)
        assert_same_rows(got, want)


@pytest.mark.parametrize("periodic", [True, (True, False)])
def test_rank_rows_equal_serial_rows_in_periodic_and_mixed_boxes(periodic):
    rng = np.random.default_rng(3)
    x = rng.random((2500, 2)) * [2.0, 1.0]
    rc = 0.01 * np.exp(rng.uniform(0, np.log(20), len(x)))          # up to 0.2, thinner than some boxes
    box = arpy.Domain(([0.0, 0.0], [2.0, 1.0]), periodic=periodic)
    for skin in (0.0, 0.01):
        want = serial_rows(x, rc, box, skin)
        for parts in (1, 2, 6):
            _, _, _, got = rank_rows(x, rc, parts, box, skin)
            assert_same_rows(got, want)


def test_ties_at_the_cutoff_and_on_cut_planes():
    """A lattice: points on every cut plane and pairs at exactly the cutoff, in a periodic box."""
    x = np.array(list(itertools.product(range(16), repeat=2)), float) / 16
    box = arpy.Domain([1.0, 1.0], periodic=True)
    for rc in (1 / 16, 2 / 16, np.where(np.arange(len(x)) % 3 == 0, 2 / 16, 1 / 16)):
        want = serial_rows(x, rc, box)
        for parts in (2, 3, 4, 8):
            _, _, _, got = rank_rows(x, rc, parts, box)
            assert_same_rows(got, want)


def test_own_cutoff_ghosts_are_fewer_than_a_uniform_halo():
    """Adaptive cutoffs: the own-cutoff rule sends each rank far fewer ghosts than one width (the
    largest cutoff) would, and every rank still gets the serial rows."""
    rng = np.random.default_rng(5)
    fine = 0.5 + 0.15 * rng.standard_normal((3000, 2))
    fine = fine[np.all((fine > 0) & (fine < 1), axis=1)]
    x = np.concatenate([fine, rng.random((1000, 2))])
    rc = np.concatenate([np.full(len(fine), 0.005), np.full(1000, 0.05)])
    dec, owner, ghosts, got = rank_rows(x, rc, 4)
    assert_same_rows(got, serial_rows(x, rc))
    uniform = halo(x, rc.max(), dec, owner)
    own, wide = sum(g.size for g, _ in ghosts), sum(g.size for g, _ in uniform)
    assert own < 0.5 * wide


def test_bad_input():
    x = np.random.default_rng(0).random((10, 2))
    with pytest.raises(ValueError, match="parts"):
        bisect(x, 0)
    with pytest.raises(ValueError, match="weights"):
        bisect(x, 2, weights=-np.ones(10, int))
    with pytest.raises(ValueError, match="weights"):
        bisect(x, 2, weights=np.full(10, 0.5))


@pytest.mark.parametrize("parts", [1, 2, 3, 4])
@pytest.mark.parametrize("periodic", [False, True])
def test_ranks_as_threads_decompose_migrate_and_exchange_like_the_serial_rules(parts, periodic):
    """SPMD on ranks that are threads, the particles first dealt to the ranks at random: the boxes
    equal the serial bisection's bit for bit, migration leaves each rank exactly the particles its
    box owns (nothing lost or duplicated, fields carried), and each rank's lists over its own
    particles and the exchanged ghosts hold the serial rows, as keys."""
    rng = np.random.default_rng(parts + 10 * periodic)
    x = rng.random((3000, 2))
    rc = 0.01 * np.exp(rng.uniform(0, np.log(10), len(x)))
    keys = rng.permutation(len(x)).astype(np.int64) * 7 + 3
    box = arpy.Domain([1.0, 1.0], periodic=True) if periodic else arpy.Domain([1.0, 1.0])
    dec0, owner0 = bisect(x, parts, domain=box)
    serial = arpy.neighbor_list(x, rc, full=True, domain=box if periodic else None)
    want = {int(keys[p]): np.sort(keys[serial.neighbors(p)]) for p in range(len(x))}
    deal = rng.integers(0, parts, len(x))

    def rank(comm):
        mine = deal == comm.rank
        dec, _ = bisect(x[mine], parts, domain=box, comm=comm)
        xs, ks, f = migrate(comm, dec, x[mine], keys[mine], {"rc": rc[mine]})
        layer = exchange_ghosts(comm, dec, xs, f["rc"], ks, domain=box if periodic else None)
        xg, rg, kg = layer.x, layer.rc, layer.keys
        nl = arpy.neighbor_list(np.concatenate([xs, xg]), np.concatenate([f["rc"], rg]), full=True)
        kall = np.concatenate([ks, kg])
        return dec, ks, {int(ks[p]): np.sort(kall[nl.neighbors(p)]) for p in range(len(ks))}

    out = run_threads(parts, rank)
    seen = []
    for r, (dec, ks, rows) in enumerate(out):
        np.testing.assert_array_equal(dec.lo, dec0.lo)
        np.testing.assert_array_equal(dec.hi, dec0.hi)
        np.testing.assert_array_equal(ks, np.sort(keys[owner0 == r]))
        seen.append(ks)
        for k, row in rows.items():
            np.testing.assert_array_equal(row, want[k], err_msg=f"key {k}")
    allkeys = np.concatenate(seen)
    assert allkeys.size == len(x) and np.unique(allkeys).size == len(x)


@pytest.mark.timeout(10)
def test_mpi_comm_without_mpi4py_or_an_mpi_library_says_what_to_install(tmp_path, monkeypatch):
    """MPIComm() where mpi4py is missing, or where mpi4py finds no MPI library (its RuntimeError
    ``cannot load MPI library``, here from a stand-in package), names the extra and the MPICH wheel."""
    from arpy.distributed import MPIComm

    for name in [m for m in sys.modules if m == "mpi4py" or m.startswith("mpi4py.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "mpi4py", None)
    with pytest.raises(RuntimeError, match=r"mpi4py is missing: pip install 'arpy-particles\[mpi\]'"):
        MPIComm()
    monkeypatch.delitem(sys.modules, "mpi4py")
    (tmp_path / "mpi4py").mkdir()
    (tmp_path / "mpi4py" / "__init__.py").write_text("")
    (tmp_path / "mpi4py" / "MPI.py").write_text("raise RuntimeError('cannot load MPI library')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(RuntimeError, match="found no MPI library .cannot load MPI library.: pip install mpich"):
        MPIComm()


def test_a_failing_rank_raises_instead_of_hanging():
    """A rank that raises releases the others from their collective at once: each raises an error
    naming it and its exception, and run_threads raises that exception with a note naming the rank."""
    released = {}

    def rank(comm):
        if comm.rank == 1:
            raise RuntimeError("rank 1 failed")
        try:
            return comm.sum(1)
        except RuntimeError as exc:
            released[comm.rank] = str(exc)
            raise

    with pytest.raises(RuntimeError, match="rank 1 failed") as info:
        run_threads(3, rank, timeout=60)
    assert info.value.__notes__ == ["raised on rank 1 of 3 (thread ranks); ranks 0, 2 left their collectives unfinished"]
    assert released == {r: f"rank {r} of 3 left collective #1 unfinished: rank 1 raised RuntimeError: rank 1 failed"
                        for r in (0, 2)}


@pytest.mark.timeout(10)
def test_ranks_that_do_not_call_the_same_collectives_fail_at_once():
    """Rank 0 returns while the others wait for it in a collective: they raise at once, naming it, instead
    of waiting for the timeout (60 s here)."""
    with pytest.raises(RuntimeError, match=r"rank [12] of 3 left collective #2 unfinished: rank 0 returned after 1 "
                                           r"collectives without calling it \(the ranks do not call the same"):
        run_threads(3, lambda comm: comm.sum(1) if comm.rank == 0 else (comm.sum(1), comm.sum(2)), timeout=60)


@pytest.mark.timeout(10)
def test_a_collective_waits_at_most_the_timeout():
    """A rank that does not come to a collective (it waits for an event): the others' collective fails after
    the timeout, naming it, and run_threads names it as left running."""
    go = threading.Event()

    def rank(comm):
        if comm.rank == 1:
            go.wait(10)
        return comm.sum(1)

    try:
        with pytest.raises(RuntimeError, match=r"^rank 0 of 2 left collective #1 unfinished: rank 1 did not reach it "
                                               r"within 0.2 s\n") as info:
            run_threads(2, rank, timeout=0.2)
    finally:
        go.set()
    assert info.value.__notes__ == ["raised on rank 0 of 2 (thread ranks); rank 1 did not end within 0.2 s after that "
                                    "(left running)"]


def errors_on_ranks(parts: int, fn) -> list:
    """``fn(comm)`` on thread ranks: each rank's ValueError message (None where it raised none)."""
    def rank(comm):
        try:
            fn(comm)
        except ValueError as exc:
            return str(exc)
        return None

    return run_threads(parts, rank, timeout=60)


@pytest.mark.timeout(30)
def test_ranks_given_different_inputs_fail_on_every_rank_naming_the_difference():
    """Inputs that must be global, given differently to two thread ranks (the domain, dt, the field names,
    the particle set, the number of dimensions, the field names and r* of shares given to
    Particles.from_shares): every rank raises the same ValueError, naming the entry point, the input and
    its value on each rank, before any other collective."""
    from arpy.particles import Particles

    x, eps, _, _ = lattice(12)
    periodic, walls = arpy.Domain([1.0, 1.0], periodic=True), arpy.Domain([1.0, 1.0])
    ps = arpy.Particles(x, eps / 2.0, rstar=2.0, n_star=20, domain=periodic)
    moved = arpy.Particles(x[::-1], eps / 2.0, rstar=2.0, n_star=20, domain=periodic)
    cases = {
        "domain": (lambda comm: Particles.dealt(x, eps, wave(x)[:, None], ["f"], domain=(periodic, walls)[comm.rank],
                                                 rstar=2.0, comm=comm),
                   "the particle set given to every rank (scatter): every rank must be given the same domain, but "
                   f"domain = {periodic!r} on rank 0; {walls!r} on rank 1"),
        "dt": (lambda comm: arpy.Simulation(ps, wave, nu=0.01, D0=0.1, dt=(1e-3, 2e-3)[comm.rank], comm=comm),
               "Simulation(comm=): every rank must be given the same dt, but dt = 0.001 on rank 0; 0.002 on rank 1"),
        "names": (lambda comm: arpy.Simulation(ps, {"u": wave, ("v", "w")[comm.rank]: wave}, nu=0.01, D0=0.1, comm=comm),
                  "every rank must be given the same field names, but field names = ('u', 'v') on rank 0; ('u', 'w') on "
                  "rank 1"),
        "x": (lambda comm: arpy.Simulation((ps, moved)[comm.rank], wave, nu=0.01, D0=0.1, comm=comm),
              "(scatter): every rank must be given the same x, field 'F', but x = float64 array (144, 2) #"),
        "shares": (lambda comm: Particles.from_shares(x[comm.rank::2], eps[comm.rank::2] / 2.0,
                                                      wave(x[comm.rank::2])[:, None], [("f", "g")[comm.rank]],
                                                      np.arange(comm.rank, len(x), 2), domain=periodic,
                                                      rstar=(2.0, 2.5)[comm.rank], comm=comm),
                   "Particles.from_shares: every rank must be given the same field names, rstar, but field names = "
                   "('f',) on rank 0; ('g',) on rank 1 | rstar = 2.0 on rank 0; 2.5 on rank 1"),
        "d": (lambda comm: arpy.self_organize(np.random.default_rng(0).random((50, 2 + comm.rank)), grad_f=np.zeros_like,
                                              D0=0.3, keys=np.arange(50) + 50 * comm.rank, seed=1, comm=comm),
              "self_organize(comm=): every rank must be given the same d, but d = 2 on rank 0; 3 on rank 1"),
    }
    for what, (fn, message) in cases.items():
        first, second = errors_on_ranks(2, fn)
        assert first == second and message in str(first), (what, first, second)


def lattice(n: int, seed: int = 11):
    """A jittered n x n lattice in the periodic unit square, core sizes 3.3 spacings, random keys."""
    rng = np.random.default_rng(seed)
    x = (np.array(list(itertools.product(range(n), repeat=2)), float) + 0.5 + rng.uniform(-0.3, 0.3, (n * n, 2))) / n
    return x, np.full(len(x), 3.3 / n), rng.permutation(len(x)).astype(np.int64), rng


def on_ranks(parts: int, x, eps, keys, deal, work, box=None):
    """``work(comm, lap, xs)`` on thread ranks after bisection, migration and the distributed Laplacian
    (default box: the periodic unit square); returns (keys, values) of all ranks in key order."""
    box = box or arpy.Domain([1.0, 1.0], periodic=True)

    def rank(comm):
        mine = deal == comm.rank
        dec, _ = bisect(x[mine], parts, domain=box, comm=comm)
        xs, ks, fl = migrate(comm, dec, x[mine], keys[mine], {"eps": eps[mine]})
        return ks, work(comm, Laplacian(comm, dec, xs, fl["eps"], ks, domain=box), xs)

    out = run_threads(parts, rank)
    ks, v = np.concatenate([o[0] for o in out]), np.concatenate([o[1] for o in out])
    order = np.argsort(ks)
    return ks[order], v[order]


def wave(p: np.ndarray) -> np.ndarray:
    return np.sin(2 * np.pi * p[:, 0]) * np.cos(2 * np.pi * p[:, 1])


def diffuse(comm, lap, xs, steps: int = 20, nu: float = 0.01) -> np.ndarray:
    """``steps`` forward-Euler steps of df/dt = nu lap f from the wave, dt = 0.2 h^2 / nu (h = 1/40)."""
    dt, f = 0.2 * (1 / 40) ** 2 / nu, wave(xs)
    for _ in range(steps):
        f = f + dt * nu * lap.apply(f)
    return f


def test_fixed_particle_diffusion_is_bitwise_the_same_on_1_to_4_ranks():
    """The distributed DC-PSE Laplacian (rows in key order, ghost values refreshed each step): 20
    forward-Euler steps of df/dt = nu lap f give bitwise the same field on 1, 2, 3 and 4 ranks."""
    x, eps, keys, rng = lattice(40)
    deal = rng.integers(0, 4, len(x))
    ks1, f1 = on_ranks(1, x, eps, keys, deal % 1, diffuse)
    for parts in (2, 3, 4):
        ks, f = on_ranks(parts, x, eps, keys, deal % parts, diffuse)
        np.testing.assert_array_equal(ks, ks1)
        assert f.tobytes() == f1.tobytes(), parts
    assert np.abs(f1 - wave(x[np.argsort(keys)])).max() > 0.05            # it did diffuse


def test_distributed_laplacian_converges_at_order_two():
    """On 3 ranks the Laplacian of sin(2 pi x) cos(2 pi y) against -8 pi^2 f, on lattices of 20^2,
    40^2 and 80^2 jittered particles: the largest error falls at DC-PSE's order 2 (within 0.5)."""
    h, err = [], []
    for n in (20, 40, 80):
        x, eps, keys, rng = lattice(n)
        ks, lap = on_ranks(3, x, eps, keys, rng.integers(0, 3, len(x)), lambda comm, op, xs: op.apply(wave(xs)))
        exact = -8 * np.pi ** 2 * wave(x[np.argsort(keys)])
        h.append(1 / n)
        err.append(np.abs(lap - exact).max() / (8 * np.pi ** 2))
    order = np.polyfit(np.log(h), np.log(err), 1)[0]
    assert abs(order - 2) < 0.5, (order, err)


def test_key_ordered_rows_equal_a_numpy_sort_at_one_and_two_threads():
    """key_ordered (the core's per-row sort) against NumPy's lexsort by (row, key), for a full list and
    a cross list, at 1 and 2 threads; a wrong index is refused."""
    from arpy.distributed import key_ordered

    rng = np.random.default_rng(4)
    x = rng.random((30000, 2))
    keys = rng.permutation(len(x)).astype(np.int64) * 11 - 5000
    nl = arpy.neighbor_list(x, rng.uniform(0.003, 0.012, len(x)), full=True)
    cross = arpy.cross_neighbor_list(rng.random((25000, 2)), 0.01, x, 0.01)
    for lst in (nl, cross):
        want = lst.indices[np.lexsort((keys[lst.indices], lst.rows()))]
        for threads in (1, 2):
            with arpy.num_threads(threads):
                got = key_ordered(lst, keys)
            np.testing.assert_array_equal(got.offsets, lst.offsets)
            np.testing.assert_array_equal(got.indices, want)
    with pytest.raises(ValueError):
        key_ordered(nl, keys[:-1])


def test_exact_sum_is_fsum_on_any_number_of_ranks():
    """exact_sum: math.fsum of all the terms (correctly rounded), bit for bit, on 1-4 thread ranks and
    any deal, with terms over 600 orders of magnitude, both signs, cancellations and subnormals; and
    math.fsum's inf, nan or error for terms that are not finite."""
    import math

    from arpy.distributed import SerialComm, exact_sum

    rng = np.random.default_rng(9)
    v = rng.standard_normal(20000) * 10.0 ** rng.integers(-300, 300, 20000)
    v[:6] = [1e300, 1.0, -1e300, 5e-324, -2.5e-324, 3.0]
    v = np.concatenate([v, -v[100:200], 1.0 + rng.random(3000), -(2.0 + rng.random(1500))])  # (long runs of an exponent)
    want = math.fsum(v)
    for parts in (1, 2, 3, 4):
        deal = rng.integers(0, parts, v.size)
        got = run_threads(parts, lambda comm: exact_sum(comm, v[deal == comm.rank][::-1]))   # any order
        assert all(g == want for g in got), (parts, got, want)
    assert exact_sum(SerialComm(), np.zeros(0)) == 0.0
    # each rank's partials finite, their sum in math.fsum's order overflowing, the exact sum not
    assert run_threads(3, lambda comm: exact_sum(comm, np.array([1e308, 1e308, -1e308])[comm.rank::3])) == [1e308] * 3
    # terms that are not finite: math.fsum's answer (or error) on any number of ranks
    for parts in (1, 2):
        assert run_threads(parts, lambda comm: exact_sum(comm, np.array([1.0, np.inf])[comm.rank::parts])) == \
            [np.inf] * parts
        assert all(np.isnan(g) for g in run_threads(parts, lambda comm: exact_sum(comm, np.array([np.nan, 2.0]))))
        with pytest.raises(ValueError, match="inf"):
            run_threads(parts, lambda comm: exact_sum(comm, np.array([np.inf, -np.inf])[comm.rank::parts]))


@pytest.mark.parametrize("periodic", [False, (True, False)])
def test_walls_mirror_images_on_ranks(periodic):
    """Walls (and walls with one periodic axis): each rank mirrors its own particles and ghosts; 20
    diffusion steps give bitwise the same field on 1-4 ranks, and the Laplacian of a field with zero
    normal derivative at the walls, cos(2 pi x) cos(2 pi y), is bitwise that of the one-process
    DomainDCPSE with the same keys, and closer to -8 pi^2 f than without mirrors by more than half
    (largest error 2.5 % of 8 pi^2 at this resolution; without the mirrors 5.8 %)."""
    x, eps, keys, rng = lattice(40)
    box = arpy.Domain([1.0, 1.0], periodic=periodic)
    deal = rng.integers(0, 4, len(x))
    ks1, f1 = on_ranks(1, x, eps, keys, deal % 1, diffuse, box)
    for parts in (2, 3, 4):
        ks, f = on_ranks(parts, x, eps, keys, deal % parts, diffuse, box)
        np.testing.assert_array_equal(ks, ks1)
        assert f.tobytes() == f1.tobytes(), parts

    def even(p):
        return np.cos(2 * np.pi * p[:, 0]) * np.cos(2 * np.pi * p[:, 1])

    _, lap = on_ranks(3, x, eps, keys, deal % 3, lambda comm, op, xs: op.apply(even(xs)), box)
    order = np.argsort(keys)
    one = arpy.DomainDCPSE(x, eps, domain=box, keys=keys, operators=["laplacian"], strict=False, **REPAIR)
    assert lap.tobytes() == (one.laplacian() @ one.extend(even(x)))[order].tobytes()
    exact = -8 * np.pi ** 2 * even(x[order])
    free = arpy.DCPSE(x, eps, operators=["laplacian"], strict=False)
    assert np.abs(lap - exact).max() < 0.5 * np.abs((free.laplacian() @ even(x))[order] - exact).max()


def _walled_set(periodic, seed: int = 1, n: int = 700):
    """Random particles, core sizes over a factor 4, in a box (lo != 0) with a Dirichlet value on the
    lower wall (moving in x and t), a Neumann flux on the upper one and, without a periodic x, a
    Dirichlet value on the left wall; without a periodic x also boundary particles that coincide (at
    the corner: a particle on each face near the other face; and two particles above one point)."""
    from arpy.dcpse.boundary import Dirichlet, Neumann, conditions

    box = arpy.Domain([[-0.5, 0.25], [0.5, 1.25]], periodic=periodic)
    spec = {"y-": Dirichlet(lambda w, t: np.cos(w[:, 0]) + t), "y+": Neumann(0.3)}
    if not periodic[0]:
        spec["x-"] = Dirichlet(1.0)
    bc = conditions(spec, box)
    rng = np.random.default_rng(seed)
    x = rng.uniform(box.lo, box.hi, (n, 2))
    eps = 0.06 * np.exp(rng.uniform(0, np.log(4), n))
    x = bc.snap(x, eps, 0.2)
    if not periodic[0]:
        x[:4] = [[-0.5, 0.27], [-0.48, 0.25], [-0.3, 0.268], [-0.3, 0.272]]
        eps[:4] = [0.1, 0.12, 0.2, 0.1]
    return box, bc, x, eps, rng.permutation(n).astype(np.int64) * 3 + 1


@pytest.mark.parametrize("periodic", [(True, False), (False, False)])
def test_dirichlet_walls_on_ranks_equal_the_one_process_operator(periodic):
    """Dirichlet walls on thread ranks (1-4): each rank makes the boundary particles of its particles
    and ghosts, keyed by (face, key of their particle); the one-sided rows by the walls ask for their
    balls' particles and those whose boundary particles lie in them.  The Laplacian at the particles
    and the interpolation and Laplacian old -> new points equal bitwise the one-process DomainDCPSE
    with the same keys (its boundary particles made from the whole set), on a periodic x and on walls
    with coinciding boundary particles (of which the one-process operator keeps one each)."""
    from arpy.distributed import DistributedDCPSE

    box, bc, x, eps, keys = _walled_set(periodic)
    points = bc.snap(np.random.default_rng(9).uniform(box.lo, box.hi, (300, 2)), np.full(300, 0.1), 0.2)
    order = np.argsort(keys)

    def f_of(p):
        return np.cos(3 * p[:, 0]) * np.sin(2 * p[:, 1])

    one = arpy.DomainDCPSE(x, eps, domain=box, keys=keys, dirichlet=bc, operators=["laplacian"], strict=False, **REPAIR)
    lap = (one.laplacian() @ one.extend(f_of(x), bc, 0.5))[order]
    to = arpy.DomainDCPSE(x, eps, points, np.full(300, 0.1), domain=box, keys=keys, dirichlet=bc,
                          operators=["interpolation", "laplacian"], strict=False, **REPAIR)
    want = (to.interpolate(f_of(x), bc=bc, t=0.5), to.laplacian() @ to.extend(f_of(x), bc, 0.5))
    assert one.n_boundary > 20 and one.wide_gathers[0].size > 40
    if not periodic[0]:
        assert one.n_boundary < len(bc.projections(x, eps)[0])          # (coinciding boundary particles)
    for parts in (1, 2, 3, 4):
        deal = np.random.default_rng(parts).integers(0, parts, len(x))

        def rank(comm):
            mine = deal == comm.rank
            dec, _ = bisect(x[mine], parts, domain=box, comm=comm)
            xs, ks, fl = migrate(comm, dec, x[mine], keys[mine], {"eps": eps[mine]})
            op = DistributedDCPSE(comm, dec, xs, fl["eps"], ks, domain=box, dirichlet=bc, strict=False)
            got = gather(comm, ks, op.laplacian() @ op.extend(f_of(xs), bc, 0.5))[1]
            at = np.flatnonzero(dec.locate(points) == comm.rank)
            op = DistributedDCPSE(comm, dec, xs, fl["eps"], ks, points[at], np.full(at.size, 0.1), domain=box,
                                  dirichlet=bc, strict=False, operators=["interpolation", "laplacian"])
            return (got, gather(comm, at, op.interpolate(f_of(xs), bc=bc, t=0.5))[1],
                    gather(comm, at, op.laplacian() @ op.extend(f_of(xs), bc, 0.5))[1])

        got, interpolated, laplacian = run_threads(parts, rank)[0]
        assert got.tobytes() == lap.tobytes(), parts
        assert interpolated.tobytes() == want[0].tobytes() and laplacian.tobytes() == want[1].tobytes(), parts


def _sparse_set(d: int, periodic, seed: int):
    """Random particles whose core sizes leave a few stencils without valid moments (repaired)."""
    rng = np.random.default_rng(seed)
    n = 900 if d == 2 else 1500
    x = rng.random((n, d))
    eps = (0.1 if d == 2 else 0.19) * np.exp(rng.uniform(-0.25, 0.25, n))
    return x, eps, rng.permutation(n).astype(np.int64) * 3 + 2, arpy.Domain([1.0] * d, periodic=periodic)


def _laplacian_on_ranks(parts, x, eps, keys, box, f):
    """The distributed Laplacian of f on thread ranks (particles dealt at random): (values by key,
    keys of repaired rows per rank)."""
    deal = np.random.default_rng(parts).integers(0, parts, len(x))

    def rank(comm):
        mine = deal == comm.rank
        dec, _ = bisect(x[mine], parts, domain=box, comm=comm)
        xs, ks, fl = migrate(comm, dec, x[mine], keys[mine], {"eps": eps[mine], "f": f[mine]})
        lap = Laplacian(comm, dec, xs, fl["eps"], ks, domain=box, strict=False)
        return gather(comm, ks, lap.apply(fl["f"]))[1], lap.repaired

    out = run_threads(parts, rank)
    return out[0][0], [o[1] for o in out]


@pytest.mark.parametrize("d, periodic, seed", [(2, True, 1), (2, False, 1), (2, (True, False), 1), (3, True, 4)])
def test_repaired_stencils_next_to_rank_boundaries_equal_the_one_process_operator(d, periodic, seed, monkeypatch):
    """Rows without valid moments are rebuilt over a wider ball (arpy.dcpse.domain.REPAIR), which reaches
    beyond the ghost layer: the rank asks the others for their particles (and periodic images) in
    that ball.  The Laplacian on 1-4 thread ranks is bitwise the one-process DomainDCPSE with the
    same keys (periodic, walled, mixed boxes; 2D and 3D), the repaired rows the same; without the
    requests some rows differ (the case reaches beyond the layer).  Where an answer brings sources, only
    the rows they reach are built again (DomainDCPSE.spliced), fewer than the rank's."""
    import arpy.distributed.dcpse as dist

    x, eps, keys, box = _sparse_set(d, periodic, seed)
    f = np.cos(2 * np.pi * x[:, 0]) * np.cos(2 * np.pi * x[:, 1])
    one = arpy.DomainDCPSE(x, eps, domain=box, keys=keys, operators=["laplacian"], strict=False, **REPAIR)
    assert one.widened.size >= 2 and one.failed.size == 0
    expected = (one.laplacian() @ one.extend(f))[np.argsort(keys)]
    spliced: list[tuple[int, int]] = []
    real = arpy.DomainDCPSE.spliced

    def counted(self, old, columns):
        spliced.append((self.only.size, old.n_col))
        return real(self, old, columns)

    monkeypatch.setattr(arpy.DomainDCPSE, "spliced", counted)
    for parts in (1, 2, 3, 4):
        lap, repaired = _laplacian_on_ranks(parts, x, eps, keys, box, f)
        assert lap.tobytes() == expected.tobytes(), parts
        np.testing.assert_array_equal(np.sort(np.concatenate(repaired)), np.sort(keys[one.widened]))
    assert spliced and all(k < n for k, n in spliced)
    monkeypatch.undo()
    monkeypatch.setattr(dist, "repair_sends", lambda comm, x, rc, points, radius, dom, skin, sends, walls=None: sends)
    assert any(_laplacian_on_ranks(parts, x, eps, keys, box, f)[0].tobytes() != expected.tobytes()
               for parts in (2, 3, 4))


@pytest.mark.parametrize("seed", [1, 7, 8])
def test_one_rank_builds_again_only_when_a_repaired_row_reaches_past_a_face(seed, monkeypatch):
    """One rank in a periodic box: the operator is built once, with the repair; it is built a
    second time (with the periodic images a wider ball needs) only when the ball of some repaired
    row (DomainDCPSE.wide_gathers) crosses a face of the box and the answer brings images the rank
    did not hold (the same sources build the same operator), and either way it is bitwise the
    one-process DomainDCPSE."""
    import arpy.dcpse.domain as dom_mod
    import arpy.distributed.dcpse as dist

    x, eps, keys, box = _sparse_set(2, True, seed)     # (seeds 1, 8: repaired rows by a face; 7: none)
    f = np.cos(2 * np.pi * x[:, 0]) * np.sin(2 * np.pi * x[:, 1])
    one = arpy.DomainDCPSE(x, eps, domain=box, keys=keys, operators=["laplacian"], strict=False, **REPAIR)
    rows, radius = one.wide_gathers
    assert rows.size >= 1 and np.all(radius >= 1.5 * eps[rows])
    assert np.all(np.isin(one.widened, rows)) and np.all(np.isin(one.unrepaired, rows))
    crossing = np.any((x[rows] - radius[:, None] <= 0) | (x[rows] + radius[:, None] >= 1), axis=1)
    rebuilt: list[bool] = []
    for far in (False, True):                        # the rows as they are; and all of them far from the faces
        builds, layers = [], []
        real, real_send = dom_mod.DomainDCPSE, dist.send_ghosts

        def counted(*a, **k):
            builds.append(1)
            return real(*a, **k)

        def sent(*a, **k):
            layers.append(real_send(*a, **k))
            return layers[-1]

        monkeypatch.setattr(dom_mod, "DomainDCPSE", counted)
        monkeypatch.setattr(dist, "send_ghosts", sent)
        if far:
            monkeypatch.setattr(real, "wide_gathers", property(lambda self: (np.zeros(0, np.int64), np.zeros(0))))
        lap, _ = _laplacian_on_ranks(1, x, eps, keys, box, f)
        monkeypatch.undo()
        assert len(layers) == 1 + (not far and bool(crossing.any())), (seed, far)     # (the layer, then the answer)
        grew = len(layers) == 2 and not (np.array_equal(layers[0].keys, layers[1].keys)
                                         and np.array_equal(layers[0].shift, layers[1].shift))
        rebuilt.append(grew)
        assert len(builds) == 1 + grew, (seed, far, crossing.sum())
        if not far:
            assert lap.tobytes() == (one.laplacian() @ one.extend(f))[np.argsort(keys)].tobytes()
    # (here the layer already holds the images in the repaired rows' balls: the answer brings none and the
    # operator is built once; answers that bring sources, and their second build: the test above on 2-4 ranks)
    assert rebuilt == [False, False], seed


def test_one_process_key_order_is_independent_of_numbering():
    """DomainDCPSE with keys: the same particles numbered in another order give bitwise the same
    Laplacian at each key (rows summed by key), while without keys they differ by rounding."""
    x, eps, keys, box = _sparse_set(2, True, 5)
    f = np.sin(2 * np.pi * x[:, 0]) + x[:, 1] ** 2
    perm = np.random.default_rng(9).permutation(len(x))

    def lap(p, k=None):
        op = arpy.DomainDCPSE(x[p], eps[p], domain=box, keys=None if k is None else k[p], operators=["laplacian"],
                              strict=False, **REPAIR)
        out = np.empty(len(x))
        out[p] = op.laplacian() @ op.extend(f[p])
        return out

    ident = np.arange(len(x))
    assert lap(ident, keys).tobytes() == lap(perm, keys).tobytes()
    assert lap(ident).tobytes() != lap(perm).tobytes()
    np.testing.assert_allclose(lap(ident, keys), lap(ident), rtol=0, atol=1e-9 * np.abs(lap(ident)).max())
    with pytest.raises(ValueError, match="keys must have one entry per particle"):
        arpy.DomainDCPSE(x, eps, domain=box, keys=keys[:-1])
    with pytest.raises(ValueError, match="ghosts= with collocation points needs their core sizes"):
        arpy.DomainDCPSE(x, eps, x[:5], domain=box, ghosts=(x[:3], eps[:3]))
    with pytest.raises(ValueError, match="ghosts= is for operators in a box"):
        arpy.DomainDCPSE(x, eps, ghosts=(x[:3], eps[:3]))
    with pytest.raises(ValueError, match="extend needs 903 values"):
        arpy.DomainDCPSE(x, eps, domain=box, ghosts=(x[:3] + 1.0, eps[:3]), strict=False).extend(f)


def moving_run(parts, integrator: str, x, eps, keys, steps: int = 8):
    """A Simulation without re-organization on ``parts`` thread ranks (None: one process, no comm; a
    Comm: its ranks): velocity (0.3, 0.1) with a shear part, nu = 0.01, dt = 0.01, in the periodic unit
    square, the particles given in key order; returns (keys, x, f) in key order."""
    box = arpy.Domain([1.0, 1.0], periodic=True)
    order = np.argsort(keys)
    ps = arpy.Particles(x[order], eps[order] / 2.0, rstar=2.0, n_star=20, domain=box)

    def velocity(p, t, f):
        return np.stack([0.3 + 0.05 * np.sin(2 * np.pi * p[:, 1]), np.full(len(p), 0.1)], axis=1)

    def run(comm):
        sim = arpy.Simulation(ps, wave, velocity=velocity, nu=0.01, dt=0.01, D0=0.1, reorganize_every=0,
                              integrator=integrator, comm=comm)
        for _ in range(steps):
            sim.step()
        k, xs, _, F = sim.gather()
        return keys[order][k], xs, F[:, 0], sim.history()["n"]

    k, xs, fs, n = run(None) if parts is None else run_threads(parts, run)[0] if isinstance(parts, int) else run(parts)
    assert np.all(n == len(x))
    return k, xs, fs


@pytest.mark.parametrize("integrator", ["euler", "rk4"])
def test_moving_particles_are_bitwise_the_same_on_1_to_4_ranks(integrator):
    """Simulation(comm=) without re-organization (operators rebuilt at each stage, migration after
    each step, particles crossing the periodic faces and the ranks' boxes): positions and values
    bitwise the same on 1, 2, 3 and 4 ranks, every particle kept once, and bitwise the one-process
    Simulation's, with forward Euler and with RK4 (a stage's positions stay beside the rank's box on
    every rank count, one process included)."""
    x, eps, keys, _ = lattice(30)
    ks1, x1, f1 = moving_run(1, integrator, x, eps, keys)
    np.testing.assert_array_equal(ks1, np.sort(keys))
    for parts in (2, 3, 4):
        ks, xs, fs = moving_run(parts, integrator, x, eps, keys)
        np.testing.assert_array_equal(ks, ks1)
        assert xs.tobytes() == x1.tobytes() and fs.tobytes() == f1.tobytes(), parts
    ks0, x0, f0 = moving_run(None, integrator, x, eps, keys)
    np.testing.assert_array_equal(ks0, ks1)
    assert x0.tobytes() == x1.tobytes() and f0.tobytes() == f1.tobytes()
    assert np.abs(x1 - x[np.argsort(keys)]).max() > 0.02


def test_a_set_past_its_walls_loads_back_as_saved_from_pieces_and_from_one_file_on_1_to_3_ranks(tmp_path):
    """A set in a walled box with particles just past the walls (as a step can leave them), saved in
    pieces on 2 thread ranks and in one file by one process, loads back on 1, 2 and 3 ranks as saved, bit
    for bit: loading from pieces projected the particles past the walls onto them (it confined the
    positions before bisecting), loading one file on ranks did not; now both take the rows as written."""
    box = arpy.Domain(([0.0, -1.0], [1.0, 1.0]))
    rng = np.random.default_rng(5)
    x = rng.random((40, 2)) * [1.0, 2.0] - [0.0, 1.0]
    x[:3] = [[1.0 + 1e-3, 0.5], [-2e-3, 0.2], [0.5, np.nextafter(-1.0, -2.0)]]
    F = rng.random((40, 2))
    one = arpy.Particles(x, np.full(40, 0.1), 2.0, domain=box, F=F, names=("a", "b")).save(tmp_path / "one.npz")
    run_threads(2, lambda comm: arpy.Particles.dealt(x, np.full(40, 0.1), F, ("a", "b"), domain=box, rstar=2.0,
                                                     comm=comm).save(tmp_path / "pieces.npz"))
    for path in (one, tmp_path / "pieces.npz"):
        for parts in (1, 2, 3):
            keys, xs, _, Fs = run_threads(parts, lambda comm: arpy.Particles.load(path, comm=comm).gather())[0]
            assert np.array_equal(keys, np.arange(40)) and xs.tobytes() == x.tobytes() and Fs.tobytes() == F.tobytes()


@pytest.mark.parametrize("parts", [1, 3])
def test_gather_and_parallel_vtk_output(tmp_path, parts):
    """After migration, gather gives every rank the whole set in key order (positions and fields as
    dealt), and write_pvtu writes one piece per rank and a .pvtu naming them and their arrays: the
    pieces read back (meshio) hold each particle once with its values and its rank."""
    import meshio
    from xml.etree import ElementTree as ET

    from arpy.distributed import gather, write_pvtu

    rng = np.random.default_rng(5)
    x = rng.random((500, 2))
    keys = rng.permutation(500).astype(np.int64) * 3 + 1
    f = np.sin(7 * x[:, 0])
    deal = rng.integers(0, parts, len(x))
    order = np.argsort(keys)

    def rank(comm):
        mine = deal == comm.rank
        dec, _ = bisect(x[mine], parts, comm=comm)
        xs, ks, fl = migrate(comm, dec, x[mine], keys[mine], {"f": f[mine]})
        got = gather(comm, ks, xs, fl["f"])
        write_pvtu(comm, tmp_path / "out.pvtu", xs, f=fl["f"], key=ks.astype(np.float64))
        return got

    for k, xs, fs in run_threads(parts, rank):
        np.testing.assert_array_equal(k, keys[order])
        np.testing.assert_array_equal(xs, x[order])
        np.testing.assert_array_equal(fs, f[order])
    root = ET.parse(tmp_path / "out.pvtu").getroot()
    assert root.get("type") == "PUnstructuredGrid"
    names = sorted(a.get("Name") for a in root.iter("PDataArray") if a.get("Name"))
    assert names == ["f", "key", "rank"]
    sources = [p.get("Source") for p in root.iter("Piece")]
    assert len(sources) == parts
    pieces = [meshio.read(tmp_path / s) for s in sources]
    k = np.concatenate([m.point_data["key"] for m in pieces]).astype(np.int64)
    assert sorted(k.tolist()) == sorted(keys.tolist())
    pts = np.concatenate([m.points for m in pieces])[np.argsort(k)]
    np.testing.assert_array_equal(pts[:, :2], x[order])
    np.testing.assert_array_equal(np.concatenate([m.point_data["f"] for m in pieces])[np.argsort(k)], f[order])
    for r, m in enumerate(pieces):
        assert np.all(m.point_data["rank"] == r)


def _adapt_on_ranks(parts, x, dom, seed, **kw):
    """The distributed self-organization of x (keys = input order, dealt to the ranks at random), gathered
    by key: (keys, x, D, log, converged, owned, final counts per rank, boxes changed) as rank 0 sees them."""
    from arpy.distributed import gather

    keys = np.arange(len(x), dtype=np.int64)
    deal = np.random.default_rng(parts).integers(0, parts, len(x))

    def rank(comm):
        mine = deal == comm.rank
        dec, _ = bisect(x[mine], parts, domain=dom, comm=comm)
        xs, ks, _ = migrate(comm, dec, x[mine], keys[mine])
        out = arpy.self_organize(xs, domain=dom, seed=seed, comm=comm, keys=ks, decomposition=dec, **kw)
        owned = bool(np.all(out.decomposition.locate(out.x) == comm.rank))
        counts = comm.allgather(len(out.keys))
        moved = not np.array_equal(out.decomposition.lo, dec.lo)
        return gather(comm, out.keys, out.x, out.D) + (out.log, out.converged, owned, counts, moved)

    results = run_threads(parts, rank, timeout=300)
    assert all(r[-3] for r in results)                    # each rank owns its particles at the end
    return results[0]


def _front_gradient(p):
    """grad of tanh((r - 0.3) / 0.1), r = |p - (0.5, 0.4)|: a circular front in one corner of [-1, 1]^2."""
    q = p - np.array([0.5, 0.4])
    r = np.maximum(np.linalg.norm(q, axis=1), 1e-12)
    return ((1.0 - np.tanh((r - 0.3) / 0.1) ** 2) / 0.1 / r)[:, None] * q


@pytest.mark.parametrize("case, parts", [("periodic", 3), ("front", 4)])
def test_self_organization_is_bitwise_the_same_on_any_number_of_ranks(case, parts, monkeypatch):
    """The adaptation over thread ranks (own-cutoff ghosts, receiver-side reaches for Eq. 2.9 and the
    insertion clearance, fusion pairs and insertion sites decided where they lie, exact sums,
    migration) against one process: the same particles, bit for bit, by key, the same iterations and the
    stopping rule met; in a periodic box (a smooth target) and between walls (a front in one corner from
    the monitor of Eq. 2.8, where insertion crowds one box: the boxes are bisected anew and, every
    particle costing the same here (the measured densities replaced by ones: tests/test_balance.py cuts
    by uneven ones), end within 1.25 times the mean count); every rank owns its particles in the final
    decomposition."""
    from arpy.distributed import balance

    monkeypatch.setattr(balance, "densities", lambda counts, spent: np.ones(len(counts)))
    if case == "periodic":
        dom = arpy.Domain([1.0, 1.0], periodic=True)
        x = np.random.default_rng(4).random((300, 2))
        kw = dict(resolution=lambda p: 0.04 * (1 + 0.5 * np.sin(2 * np.pi * p[:, 0]) * np.cos(2 * np.pi * p[:, 1])),
                  max_iter=40)
    else:
        dom = arpy.Domain(([-1.0, -1.0], [1.0, 1.0]))
        x = np.random.default_rng(6).uniform(-1, 1, (500, 2))
        kw = dict(grad_f=_front_gradient, D0=0.2)
    serial = arpy.self_organize(x, domain=dom, seed=3, **kw)
    keys, xg, Dg, log, converged, _, counts, rebisected = _adapt_on_ranks(parts, x, dom, 3, **kw)
    if case == "front":             # the front gathers the particles: the boxes were bisected anew
        assert rebisected and max(counts) < 1.25 * sum(counts) / parts
    assert serial.converged and converged and len(log) == len(serial.log)
    assert sum(e["fused"] for e in log) > 0 and sum(e["inserted"] for e in log) > 0
    np.testing.assert_array_equal(keys, np.sort(keys))
    np.testing.assert_array_equal(xg, serial.x)
    np.testing.assert_array_equal(Dg, serial.D)
    assert [e["energy"] for e in log] == [e["energy"] for e in serial.log]


def test_self_organization_from_fewer_particles_than_ranks():
    """Three start particles on 4 and 6 thread ranks (ranks 3 on start without one): ranks without a
    particle, or without a parent of an insertion site, still take part in the collectives of the
    target, the insertion and the descent (they raised on an empty minimum and on k = 0 nearest
    particles); the adapted set is the one process's, bit for bit, in key order."""
    from arpy.adapt.organize import start_share

    dom = arpy.Domain(([0.0, 0.0], [1.0, 1.0]))
    x = np.array([[0.1, 0.1], [0.12, 0.1], [0.9, 0.9]])
    kw = dict(grad_f=lambda p: np.zeros_like(p), D0=0.3, domain=dom, seed=1, max_iter=5)
    one = arpy.self_organize(x, **kw)
    for parts in (4, 6):
        out = run_threads(parts, lambda comm: arpy.self_organize(**start_share(x, comm), comm=comm, **kw))
        order = np.argsort(np.concatenate([o.keys for o in out]))
        np.testing.assert_array_equal(np.concatenate([o.x for o in out])[order], one.x)
        np.testing.assert_array_equal(np.concatenate([o.D for o in out])[order], one.D)


def test_a_right_hand_side_of_the_user_on_ranks():
    """Simulation(comm=) with rhs(t, x, fields, ops) (a gradient, a Laplacian and a reaction term of two
    fields; walls with a Neumann flux on one face, a periodic axis): bitwise the same on 1-3 thread
    ranks and the one-process run; what is not distributed yet raises."""
    from arpy.dcpse.boundary import Neumann

    x, eps, keys, _ = lattice(24)
    box = arpy.Domain([1.0, 1.0], periodic=(True, False))
    ps = arpy.Particles(x, eps / 2.0, rstar=2.0, n_star=20, domain=box)

    def rates(t, p, f, ops):
        gu = ops.gradient("u")
        return {"u": 0.01 * ops.laplacian("u") - 0.2 * gu[:, 0] - f["u"] * f["v"],
                "v": 0.005 * ops.laplacian("v") + f["u"] * f["v"]}

    kw = dict(rhs=rates, dt=0.002, D0=0.1, reorganize_every=0, integrator="rk4",
              boundary={"u": {"y-": Neumann(1.0)}})
    start = {"u": wave, "v": lambda p: 0.5 + 0.1 * p[:, 1]}

    def run(comm):
        sim = arpy.Simulation(ps, start, comm=comm, **kw)
        for _ in range(5):
            sim.step()
        return sim.gather()

    one = run(None)
    first = run_threads(1, run)[0]
    assert all(a.tobytes() == b.tobytes() for a, b in zip(first, one))
    for parts in (2, 3):
        got = run_threads(parts, run)[0]
        assert all(a.tobytes() == b.tobytes() for a, b in zip(got, first)), parts
    # what the ranks do not do yet is refused on more than one rank (one process, P = 1, does it)
    with pytest.raises(NotImplementedError, match="takes cache_order=False"):
        run_threads(2, lambda comm: arpy.Simulation(ps, wave, nu=0.01, D0=0.1, cache_order=True, comm=comm))
    with pytest.raises(ValueError, match="needs a box"):
        run_threads(2, lambda comm: arpy.Simulation(arpy.Particles(x, eps / 2.0, 2.0, 20), wave, nu=0.01, D0=0.1,
                                                    reorganize_every=0, comm=comm))
    arpy.Simulation(ps, wave, nu=0.01, D0=0.1, comm=arpy.distributed.SerialComm(), cache_order=True).step()


@pytest.mark.parametrize("parts", [2, 4])
def test_migration_under_random_moves_keeps_every_key_and_field(parts):
    """Five rounds of random moves (some across the periodic faces, some far across the box) and
    migration on thread ranks: after each, every key is owned once, by the rank whose box holds the
    particle, and its fields (a float, an int and a vector field) are the ones it started with; the
    checksums (exact sums over the ranks) equal math.fsum of the original values."""
    import math

    from arpy.distributed import exact_sum

    rng = np.random.default_rng(parts)
    n = 2000
    x = rng.random((n, 2))
    keys = rng.permutation(n).astype(np.int64) * 3 + 1
    mass, tag, vec = rng.normal(size=n), rng.integers(0, 1 << 40, n), rng.normal(size=(n, 3))
    box = arpy.Domain([1.0, 1.0], periodic=True)
    moves = [rng.normal(scale=s, size=(n, 2)) for s in (0.01, 0.1, 0.5, 0.01, 0.3)]
    deal = rng.integers(0, parts, n)
    by_key = np.argsort(keys)

    def rank(comm):
        mine = deal == comm.rank
        dec, _ = bisect(x[mine], parts, domain=box, comm=comm)
        xs, ks = x[mine], keys[mine]
        fl = {"mass": mass[mine], "tag": tag[mine], "vec": vec[mine]}
        rounds = []
        for move in moves:
            idx = by_key[np.searchsorted(keys[by_key], ks)]          # the particles' rows in the input
            xs = box.wrap(xs + move[idx])
            xs, ks, fl = migrate(comm, dec, xs, ks, fl)
            rounds.append((ks, bool(np.all(dec.locate(xs) == comm.rank)), fl, exact_sum(comm, fl["mass"])))
        return rounds

    out = run_threads(parts, rank)
    for i in range(len(moves)):
        ks = np.concatenate([o[i][0] for o in out])
        assert ks.size == n and np.array_equal(np.sort(ks), np.sort(keys))
        assert all(o[i][1] for o in out)
        idx = by_key[np.searchsorted(keys[by_key], ks)]
        for name, ref in (("mass", mass), ("tag", tag), ("vec", vec)):
            np.testing.assert_array_equal(np.concatenate([o[i][2][name] for o in out]), ref[idx])
        assert all(o[i][3] == math.fsum(mass) for o in out)


@pytest.mark.parametrize("d, periodic, seed", [(2, True, 1), (2, False, 2), (3, (True, True, False), 3)])
def test_old_to_new_operators_on_ranks_equal_the_one_process_operator(d, periodic, seed):
    """Old particles with a hole, new points everywhere (a re-organization's old -> new): rows repaired
    over wider balls (failed and wild ones, fetched from other ranks), points in the hole without any
    stencil (the nearest old value: a k-nearest request over the ranks, ties by key) and bounded rows
    clipped to their nearest particles (the median row from every rank's rows).  Interpolation,
    bounded interpolation and the Laplacian at the new points are bitwise those of the one-process
    DomainDCPSE with the same keys on 1, 2 and 4 thread ranks."""
    from arpy.distributed import DistributedDCPSE

    rng = np.random.default_rng(seed)
    x = rng.random((2500 if d == 2 else 4000, d))
    x = x[np.linalg.norm(x - 0.5, axis=1) > 0.38]
    h = 0.06 if d == 2 else 0.15
    eps = h * np.exp(rng.uniform(-0.25, 0.25, len(x)))
    keys = rng.permutation(len(x)).astype(np.int64) * 3 + 2
    y = rng.random((600, d))
    ye = h * np.exp(rng.uniform(-0.3, 0.3, len(y)))
    box = arpy.Domain([1.0] * d, periodic=periodic)
    f = np.cos(2 * np.pi * x[:, 0]) + x[:, 1] ** 2
    one = arpy.DomainDCPSE(x, eps, y, ye, domain=box, keys=keys, operators=["interpolation", "laplacian"],
                           strict=False, **REPAIR)
    assert one.widened.size > 100 and one.clipped_rows().size > 30 and (d == 3 or one.failed.size > 50)
    want = (one.interpolate(f), one.interpolate(f, bounded=True), one.laplacian() @ one.extend(f))
    for parts in (1, 2, 4):
        deal = np.random.default_rng(parts).integers(0, parts, len(x))

        def rank(comm):
            mine = deal == comm.rank
            dec, _ = bisect(x[mine], parts, domain=box, comm=comm)
            xs, ks, fl = migrate(comm, dec, x[mine], keys[mine], {"eps": eps[mine], "f": f[mine]})
            own = dec.locate(y) == comm.rank
            op = DistributedDCPSE(comm, dec, xs, fl["eps"], ks, y[own], ye[own], domain=box, strict=False,
                                  operators=["interpolation", "laplacian"])
            return (np.flatnonzero(own), op.interpolate(fl["f"]), op.interpolate(fl["f"], bounded=True),
                    op.laplacian() @ op.extend(fl["f"]))

        out = run_threads(parts, rank)
        at = np.concatenate([o[0] for o in out])
        for i, w in enumerate(want):
            got = np.empty(len(y))
            got[at] = np.concatenate([o[i + 1] for o in out])
            assert got.tobytes() == w.tobytes(), (parts, i)


def test_global_median_is_numpys_median_on_any_number_of_ranks():
    """The median row size over the ranks (from their histograms) equals np.median of all the rows,
    odd and even counts, ranks without rows."""
    from arpy.distributed.reductions import global_median

    rng = np.random.default_rng(0)
    for n in (1, 2, 7, 100, 101):
        counts = rng.integers(0, 60, n)
        for parts in (1, 3):
            deal = rng.integers(0, parts, n)
            got = run_threads(parts, lambda comm: global_median(comm, counts[deal == comm.rank]))
            assert all(g == np.median(counts) for g in got), (n, parts)


@pytest.mark.parametrize("case", ["pulse", "vortex"])
def test_adaptive_simulation_on_ranks_is_bitwise_the_one_process_run(case):
    """Simulation(comm=) with re-organizations every 3 steps (the monitor of Eq. 2.8 from distributed
    DC-PSE gradients, Eq. 2.9 over the ranks, the self-organization on the ranks with the old set's
    resolution, old -> new interpolation and the right-hand side from the old values): the particles,
    their D and f, and the particle count of every step are bitwise those of the one-process run on
    2 and 3 thread ranks; the pulse between walls with forward Euler, a blob in the reversing vortex in
    the periodic square with RK4."""
    if case == "pulse":
        from arpy.cases.pulse import pulse_setup

        setup = pulse_setup(2, 1000.0)
        box = arpy.Domain(setup["box"])
        x0 = np.random.default_rng(1).uniform(*setup["box"], (800, 2))
        ps = arpy.self_organize(x0, grad_f=setup["grad0"], D0=0.12, domain=box, seed=1)
        f0 = lambda p: setup["exact"](p, 0.0)  # noqa: E731
        kw = dict(flow=setup["flow"], nu=1e-3, D0=0.12, integrator="euler", reorganize_every=3, seed=1)
        T = 0.05
    else:
        from arpy.cases.reversing_vortex import blob, blob_monitor, vortex

        torus = arpy.Domain([1.0, 1.0], periodic=True)
        x0 = np.random.default_rng(1).random((500, 2))
        ps = arpy.self_organize(x0, resolution=lambda p: blob_monitor(p, 0.2), domain=torus, seed=1)
        f0 = blob
        kw = dict(velocity=vortex(2.5), nu=1e-3, D0=0.2, integrator="rk4", dt=0.01, reorganize_every=3, seed=1)
        T = 0.05
    one = arpy.Simulation(ps, f0, **kw).run(T)
    assert sum(one.history()["reorganized"]) >= 2 and len(set(one.history()["n"])) >= 2
    for parts in (2, 3):
        def run(comm):
            sim = arpy.Simulation(ps, f0, comm=comm, **kw).run(T)
            return sim.gather(), sim.history()["n"]

        (keys, x, D, F), n = run_threads(parts, run, timeout=300)[0]
        np.testing.assert_array_equal(keys, np.arange(one.n))
        assert x.tobytes() == one.x.tobytes() and D.tobytes() == one.D.tobytes(), parts
        assert F[:, 0].tobytes() == one.f.tobytes(), parts
        np.testing.assert_array_equal(n, one.history()["n"])


def in_key_order(shares: list[dict], names=("x", "f", "D")) -> dict:
    """The ranks' shares of a case's particles at T (each rank's ``keys`` and rows, no rank holding the
    whole set) put together in key order."""
    keys = np.concatenate([r["keys"] for r in shares])
    order = np.argsort(keys, kind="stable")
    return {"keys": keys[order], **{k: np.concatenate([r[k] for r in shares])[order] for k in names}}


def test_the_advection_case_on_ranks_is_the_one_process_case():
    """arpy.cases.advection (Sec. 4.2: RK4, periodic, bounded interpolation, re-organizations) with comm=
    on 2 thread ranks: the same particles, field, particle counts and errors (the median by reductions,
    no rank holding every error) as one process, bit for bit, and the half-time snapshot each rank's
    own (none gathered), put together in key order the one-process snapshot; each rank adapted and
    kept only its share of the initial set."""
    from arpy.cases import advection

    one = advection(D0=0.25, T=0.1)
    assert one["median_error"] == np.median(np.abs(one["f"] - blob_of(one["x"])) / np.abs(blob_of(one["x"])).max())
    two = run_threads(2, lambda comm: advection(D0=0.25, T=0.1, comm=comm), timeout=300)
    for r in two:
        assert (r["N"], r["N_max"], r["steps"], r["error"], r["median_error"]) == (
            one["N"], one["N_max"], one["steps"], one["error"], one["median_error"])
        assert 0 < r["keys"].size < one["N"] and 0 < r["half"]["keys"].size < one["half"]["keys"].size
        assert 0 < r["particles"].n < one["particles"].n            # (its share of the initial set)
    assert sum(r["particles"].n for r in two) == one["particles"].n
    half = in_key_order([r["half"] for r in two])
    assert all(half[k].tobytes() == one["half"][k].tobytes() for k in ("keys", "x", "f", "D"))
    whole = in_key_order(two)
    assert all(whole[k].tobytes() == one[k].tobytes() for k in ("keys", "x", "f", "D"))


def blob_of(x):
    from arpy.cases.reversing_vortex import blob

    return blob(x)


@pytest.mark.parametrize("case", ["burgers", "five-spot"])
def test_the_burgers_and_five_spot_cases_on_ranks_are_the_one_process_cases(case):
    """arpy.cases.burgers (Sec. 4.4: periodic, Euler, dt from h_min over the ranks) and five_spot
    (Sec. 4.5: walls, the injection well set on each rank's particles, each rank's own snapshots, none
    gathered, particles that a step carries past a wall: test_the_outer_boxes_own_what_lies_past_the_walls)
    with comm= on 2 and 3 thread ranks: the same particles, field, counts and snapshots (put together in
    key order) as one process, bit for bit, each rank holding only its share of the initial set."""
    from arpy.cases import burgers, five_spot

    if case == "burgers":
        kw: dict = dict(D0=0.2, T=0.02, reorganize_every=2, reference=False)
        fn, keys = burgers, ("N_initial", "N", "N_max", "steps", "scale_ratio")
    else:
        kw = dict(D0=0.2, T=0.001, reorganize_every=10, snapshots=(0.0, 0.0005))
        fn, keys = five_spot, ("N_initial", "N", "steps", "f_min", "f_max")
    one = fn(**kw)
    assert sum(one["sim"].history()["reorganized"]) >= 2
    for parts in (2, 3):
        shares = run_threads(parts, lambda comm: fn(**kw, comm=comm), timeout=300)
        whole = in_key_order(shares)
        assert all(whole[k].tobytes() == one[k].tobytes() for k in ("keys", "x", "f", "D")), parts
        for r in shares:
            assert all(r[k] == one[k] for k in keys), parts
            assert 0 < r["particles"].n < one["N_initial"], parts          # (its share of the initial set)
            if case == "five-spot":
                np.testing.assert_array_equal(r["n"], one["n"])
                assert sorted(r["snapshots"]) == sorted(one["snapshots"])
        for t, shot in (one["snapshots"] if case == "five-spot" else {}).items():
            got = in_key_order([r["snapshots"][t] for r in shares])
            assert all(got[k].tobytes() == shot[k].tobytes() for k in ("keys", "x", "f", "D")), (parts, t)
            assert all(r["snapshots"][t]["keys"].size < shot["keys"].size for r in shares)


def test_the_outer_boxes_own_what_lies_past_the_walls():
    """Along walled (and free) axes the boxes on the decomposed box's faces reach on beyond it: a point
    past a wall belongs to the box on that face, and a ghost's gap is measured to that open box; along
    periodic axes the boxes stay closed."""
    x = np.random.default_rng(3).random((400, 2))
    walls = arpy.Domain([1.0, 1.0])
    dec, owner = bisect(x, 4, domain=walls)
    np.testing.assert_array_equal(dec.locate(x), owner)
    past = np.array([[-1e-9, 0.3], [0.3, 1.0 + 1e-9], [1.5, -0.2], [0.5, 0.5]])
    got = dec.locate(past)
    assert np.all(got >= 0)
    for p, r in zip(past, got):                          # the owner is the box nearest to the point
        inner = np.clip(p, 0.0, 1.0)
        assert r == dec.locate(inner[None])[0]
    lo, hi = dec.box(int(got[2]))
    assert np.isinf(lo[1]) and lo[1] < 0 and hi[0] == np.inf
    torus = arpy.Domain([1.0, 1.0], periodic=[True, False])
    dec, _ = bisect(x, 4, domain=torus)
    assert np.all(dec.locate(np.array([[1.2, 0.5], [0.5, -0.1]])) == [-1, dec.locate(np.array([[0.5, 0.0]]))[0]])
    assert all(np.all(np.isfinite(dec.box(r)[0][0])) for r in range(4))


def test_the_consistency_case_on_ranks_is_the_one_process_case(monkeypatch):
    """arpy.cases.consistency (Sec. 4.1) with comm=: each adaptation on the ranks and the operators old ->
    new by DistributedDCPSE; the errors of every refinement (maxima, medians, percentiles, where the
    largest sits, rows without a stencil: reductions, no rank holding every error) and the finest set
    (each rank's errors, put together in key order) are bitwise those of one process, on a steep
    tanh front (W = 0.03; N ~ 2.2e3 to 2.6e3) between walls with the fourth-derivative monitor (3 ranks; the periodic blob:
    test_mpi.py, under mpiexec), and under the paper's stencil rule (each new set displaced until its own
    rows and those from the old set are valid: displace_set with old=, 2 ranks); every adaptation leaves
    each rank only its share of the set."""
    import arpy.cases.convergence as convergence
    from arpy.cases import consistency

    keys = ("D0", "N", "h", "err_interp", "err_laplacian", "median_interp", "median_laplacian", "p99_interp",
            "x_at_max", "D_at_max", "failed", "failed_before", "displaced", "inserted")
    organize, sizes = convergence.self_organize, []

    def recorded(*args, **kwargs):                      # (each rank's share of each adapted set, and N)
        out = organize(*args, **kwargs)
        sizes.append((out.n, out.total(out.n)))
        return out

    monkeypatch.setattr(convergence, "self_organize", recorded)
    for kw, parts in ((dict(d0_start=0.4, d0_end=0.3, factor=0.9, width=0.03, monitor="fourth", seed=2), 3),
                      (dict(d0_start=0.4, d0_end=0.3, width=0.1, stencil_rule="displace", seed=1), 2)):
        one = consistency(**kw)
        if "stencil_rule" in kw:
            assert one["displaced"].sum() > 0 and one["failed_before"].sum() > one["displaced"].sum()
        sizes.clear()
        shares = run_threads(parts, lambda comm: consistency(**kw, comm=comm), timeout=300)
        assert len(sizes) == parts * (len(one["N"]) + 1) and all(0 < n < N for n, N in sizes)
        assert set(one["N"].tolist()) <= {N for _, N in sizes}
        for r in shares:
            assert all(r[k].tobytes() == one[k].tobytes() for k in keys), kw
            assert 0 < r["last"]["keys"].size < one["N"][-1]                 # (this rank's errors, none gathered)
        last = in_key_order([r["last"] for r in shares], ("x", "D", "err_interp"))
        assert all(last[k].tobytes() == one["last"][k].tobytes() for k in ("keys", "x", "D", "err_interp"))


def test_a_distributed_run_resumes_from_its_checkpoint_on_any_number_of_ranks(tmp_path, monkeypatch):
    """arpy.cases.advection with comm= and a Checkpoint: the state every 2 steps, each rank's particles
    and its rows of the half-time snapshot in a piece of their own (in key order, with the keys); a run on
    2 thread ranks killed after the checkpoint at step 4, resumed on 3 ranks (one rank without a piece to
    read) and on one process, ends bitwise as the uninterrupted one-process run (particles, field, the
    half-time snapshot of the case's shares), as do 2 ranks resumed from the last state the one process
    writes (one file: each rank takes a part of its snapshot).  The initial set, adapted in shares, is
    written in pieces (none gathered) that read back as the one-process set, and a resumed rank loads
    only its share of it."""
    from arpy.cases import advection
    from arpy.cases.checkpoint import Checkpoint

    kw = dict(D0=0.28, T=0.15, reorganize_every=3)
    one = advection(**kw)
    step = arpy.Simulation._step               # (what run() and step() take every step through)

    def dying(self, dt):
        if self.steps == 5:
            raise KeyboardInterrupt
        return step(self, dt)

    monkeypatch.setattr(arpy.Simulation, "_step", dying)
    path = tmp_path / "checkpoint.npz"
    with pytest.raises(KeyboardInterrupt):
        run_threads(2, lambda comm: advection(**kw, comm=comm, checkpoint=Checkpoint(path, every=2, comm=comm)))
    monkeypatch.setattr(arpy.Simulation, "_step", step)
    pieces = sorted(tmp_path.glob("checkpoint.part*-of-00002.npz"))       # (each rank's own, in key order)
    for name in ("keys", "half.keys"):
        keys = [np.load(p)[name] for p in pieces]
        assert len(pieces) == 2 and all(np.all(np.diff(k) > 0) for k in keys)
        np.testing.assert_array_equal(np.sort(np.concatenate(keys)), np.arange(sum(k.size for k in keys)))
    assert not any(k.startswith("record_half") for k in np.load(path).files)     # (the index holds no rows)
    assert len(list(tmp_path.glob("checkpoint_initial.part*-of-00002.npz"))) == 2   # (the initial set in pieces)
    back = arpy.Particles.load(tmp_path / "checkpoint_initial.npz")
    assert back.x.tobytes() == one["particles"].x.tobytes() and back.D.tobytes() == one["particles"].D.tobytes()
    resumed = run_threads(3, lambda comm: advection(**kw, comm=comm, checkpoint=Checkpoint(path, resume=True,
                                                                                          comm=comm)))
    whole = advection(**kw, checkpoint=Checkpoint(path, every=2, resume=True))
    assert "record_half_x" in np.load(path).files                        # (its last state: one file, records)
    again = run_threads(2, lambda comm: advection(**kw, comm=comm, checkpoint=Checkpoint(path, resume=True,
                                                                                        comm=comm)))
    for r in [*resumed, whole, *again]:
        assert r["steps"] == one["steps"] and r["N"] == one["N"]
    for shares in (resumed, again):                       # (each resumed rank: its share of the initial set)
        assert all(r["particles"].n < one["particles"].n for r in shares)
        assert sum(r["particles"].n for r in shares) == one["particles"].n
    for half in (in_key_order([r["half"] for r in resumed]), whole["half"], in_key_order([r["half"] for r in again])):
        assert all(half[k].tobytes() == one["half"][k].tobytes() for k in ("keys", "x", "f", "D"))
    for r in (in_key_order(resumed), whole, in_key_order(again)):
        assert all(r[k].tobytes() == one[k].tobytes() for k in ("x", "f", "D"))



def test_the_distributed_pulse_holds_only_shares_and_keeps_the_one_process_identity(tmp_path):
    """gaussian_pulse(comm=) on 2 thread ranks adapts and simulates shares of the set (no rank holds the
    whole initial set): the simulation's identity (the SHA-256 of the whole initial set, hashed in key
    chunks over the ranks) is the one-process run's, the initial set its checkpoint writes in pieces
    reads back as the one-process initial set, the particles at T gathered are the one-process ones; a
    share given to a Simulation without its ranks is refused."""
    from arpy.cases.pulse import gaussian_pulse
    from arpy.cases.checkpoint import Checkpoint

    small = dict(D0=0.3, T=0.004, reorganize_every=2, mass_points=11)
    one = gaussian_pulse(**small)

    def share(comm):
        r = gaussian_pulse(**small, comm=comm, checkpoint=Checkpoint(tmp_path / "run.npz", every=2, comm=comm))
        with pytest.raises(ValueError, match="need comm= of those ranks"):
            arpy.Simulation(r["particles"], np.zeros_like, D0=0.3, nu=1e-3)
        return r, r["sim"].particles.gather()

    for r, (_, x, D, F) in run_threads(2, share, timeout=300):
        assert 0 < r["particles"].n < r["N_initial"] == one["N_initial"] and r["N"] == one["N"]
        assert r["sim"].identity == one["sim"].identity
        assert x.tobytes() == one["x"].tobytes() and F[:, 0].tobytes() == one["f"].tobytes()
        # the mass integral, its mesh points dealt over the ranks (some to a rank beyond its box)
        assert r["mass_loss"].tobytes() == one["mass_loss"].tobytes()
    back = arpy.Particles.load(tmp_path / "run_initial.npz")
    assert back.x.tobytes() == one["particles"].x.tobytes() and back.D.tobytes() == one["particles"].D.tobytes()


def test_the_pulse_mass_integral_moves_mesh_points_at_most_a_core_size_beyond_a_box(monkeypatch):
    """The pulse's mass integral deals its mesh points over 3 thread ranks (Decomposition.deal), a point
    at most the largest core size of the particles beyond its rank's box: each operator's skin (and so
    its ghost layer's widening) is bounded by it (unbounded, this set's points moved 0.17 beyond a box, 2.5
    core sizes, and each rank held about as many ghosts as own particles); the mass is the one process's."""
    import arpy.cases.pulse as pulse

    small = dict(D0=0.04, T=1e-9, mass_points=41)
    one = pulse.gaussian_pulse(**small)
    skins: list[tuple[float, float]] = []

    class Spy(pulse.DistributedDCPSE):
        def __init__(self, comm, dec, x, eps, *args, **kw):
            super().__init__(comm, dec, x, eps, *args, **kw)
            skins.append((kw["skin"], comm.max(np.array([eps.max(initial=0.0)]))[0]))

    monkeypatch.setattr(pulse, "DistributedDCPSE", Spy)
    for r in run_threads(3, lambda comm: pulse.gaussian_pulse(**small, comm=comm), timeout=300):
        assert r["mass_loss"].tobytes() == one["mass_loss"].tobytes()
    assert skins and any(s > 0 for s, _ in skins) and all(s <= most for s, most in skins)


def _moved_outside(rng, x, lo, hi, periodic):
    """Positions x (n, d) advected so that many leave the box [lo, hi]: a third by up to half an edge,
    some far beyond (up to 1e6 edges), some onto the faces and just past them (the next double),
    the rest a little; along ``periodic`` axes by at most half an edge (the positions are then
    wrapped by the caller)."""
    n, d = x.shape
    edge = hi - lo
    y = x + rng.normal(scale=0.02, size=(n, d)) * edge
    kind = rng.integers(0, 6, n)
    axis = rng.integers(0, d, n)
    side = rng.integers(0, 2, n).astype(bool)
    rows = np.arange(n)
    face = np.where(side, hi[axis], lo[axis])
    y[kind == 1] += rng.uniform(-0.5, 0.5, (np.count_nonzero(kind == 1), d)) * edge
    far = kind == 2
    reach = edge[axis[far]] * 10.0 ** rng.uniform(-3, 6, far.sum())
    y[rows[far], axis[far]] = face[far] + np.where(side[far], reach, -reach)
    on = kind == 3
    y[rows[on], axis[on]] = face[on]
    past = kind == 4
    y[rows[past], axis[past]] = np.nextafter(face[past], np.where(side[past], np.inf, -np.inf))
    per = np.asarray(periodic, bool)
    wide = np.abs(y - x) > 0.5 * edge
    y = np.where(per & wide, x + np.sign(y - x) * 0.49 * edge, y)             # (periodic: at most half an edge)
    return y


_MIGRATION_BOXES = {
    "free space": (arpy.Domain(), False),
    "walls, lo != 0": (arpy.Domain(([-2.0, 0.5], [1.0, 1.75])), False),
    "periodic, lo != 0": (arpy.Domain(([-2.0, 0.5], [1.0, 1.75]), periodic=True), True),
    "periodic x, walls y": (arpy.Domain(([0.25, -1.0], [2.0, 0.0]), periodic=(True, False)), (True, False)),
    "3d, periodic z": (arpy.Domain(([0.0, -1.0, 3.0], [1.0, 1.0, 4.0]), periodic=(False, False, True)),
                       (False, False, True)),
}


@pytest.mark.parametrize("parts", [2, 3])
@pytest.mark.parametrize("where", list(_MIGRATION_BOXES))
def test_migration_conserves_every_particle_and_field_also_outside_the_decomposed_box(parts, where):
    """distributed.migrate on thread ranks, after moves that carry many particles out of the decomposed
    box (past its outer faces, far beyond them, onto them and one double past them, across periodic
    faces), twice: every key ends on exactly one rank (the sorted keys of all ranks are the input
    keys), on the rank whose box holds it, with its position and fields bit for bit (a field of random
    bit patterns: NaNs with payloads, infinities, subnormals, -0.0; int64; a float vector; bool), in
    key order; the counts and the exact sums over the ranks are the input's.  Positions advected past a
    periodic face are wrapped first (as a simulation step does); given unwrapped, migrate raises
    instead of losing them."""
    import math

    from arpy.distributed import exact_sum

    box, periodic = _MIGRATION_BOXES[where]
    rng = np.random.default_rng([parts, list(_MIGRATION_BOXES).index(where)])
    d = 3 if where.startswith("3d") else 2
    n = 900
    lo, hi = (np.zeros(d), np.ones(d)) if box.lo is None else (box.lo, box.hi)
    x0 = lo + rng.random((n, d)) * (hi - lo)
    x0[:40] = lo + rng.integers(0, 5, (40, d)) / 4 * (hi - lo)              # on the faces and the middle
    keys = rng.permutation(n).astype(np.int64) * 5 + 2
    fields = {"bits": rng.integers(0, 2 ** 64 - 1, n, dtype=np.uint64, endpoint=True).view(np.float64),
              "tag": rng.integers(-(2 ** 62), 2 ** 62, n), "vec": rng.normal(size=(n, 3)), "flag": rng.random(n) < 0.3,
              "mass": rng.normal(size=n)}
    fields["bits"][:6] = [np.nan, -np.nan, np.inf, -np.inf, -0.0, 5e-324]
    fields["bits"][6] = np.array([0x7FF0000000000123], np.uint64).view(np.float64)[0]     # a NaN with a payload
    moves = [_moved_outside(rng, x0, lo, hi, periodic)]
    moves.append(_moved_outside(rng, box.wrap(moves[0]), lo, hi, periodic))
    moved = [box.wrap(m) for m in moves]
    assert any(not np.array_equal(a, b) for a, b in zip(moves, moved)) == bool(np.any(periodic))
    outside = [np.any((m < lo) | (m > hi), axis=1) for m in moved]
    assert all(o.sum() > n // 10 for o in outside) or np.all(periodic)   # (many beyond the outer faces)
    deal = rng.integers(0, parts, n)
    if parts == 3:
        deal[deal == 2] = 0                       # (a rank that starts with no particle)
    order = np.argsort(keys)

    def rows(ks):
        """The rows of the input that hold the keys ks (each key once)."""
        at = order[np.searchsorted(keys[order], ks)]
        assert np.array_equal(keys[at], ks)
        return at

    def rank(comm):
        mine = deal == comm.rank
        dec, _ = bisect(x0[mine], parts, domain=box, comm=comm)
        xs, ks, fl = x0[mine], keys[mine], {k: v[mine] for k, v in fields.items()}
        out = []
        for step in range(3):                     # dealt -> owned, then the two moves
            if step:
                xs = moved[step - 1][rows(ks)]
            xs, ks, fl = migrate(comm, dec, xs, ks, fl)
            out.append((ks, xs, fl, bool(np.all(dec.locate(xs) == comm.rank)), comm.sum(len(ks)),
                        exact_sum(comm, fl["mass"]), comm.sum(int(np.sum(fl["tag"] % 1000003)))))
        return out

    results = run_threads(parts, rank, timeout=60)
    for step in range(3):
        ks = np.concatenate([r[step][0] for r in results])
        assert np.array_equal(np.sort(ks), np.sort(keys)), f"step {step}: keys lost or duplicated"
        at = rows(ks)
        want_x = x0 if step == 0 else moved[step - 1]
        assert np.concatenate([r[step][1] for r in results]).tobytes() == want_x[at].tobytes()
        for name, v in fields.items():
            got = np.concatenate([r[step][2][name] for r in results])
            assert got.dtype == v.dtype and got.tobytes() == v[at].tobytes(), f"step {step}: field {name}"
        for r in results:
            assert np.all(np.diff(r[step][0]) > 0)                         # each rank's in key order
            assert r[step][3], "a particle is not on the rank whose box holds it"
            assert r[step][4] == n
            assert r[step][5] == math.fsum(fields["mass"])
            assert r[step][6] == int(np.sum(fields["tag"] % 1000003))
    if np.any(periodic):                          # not wrapped: an error on every rank count, no loss
        def unwrapped(comm):
            mine = deal == comm.rank
            dec, _ = bisect(x0[mine], parts, domain=box, comm=comm)
            return migrate(comm, dec, moves[0][mine], keys[mine])

        with pytest.raises(ValueError, match="outside the decomposed box"):
            run_threads(parts, unwrapped, timeout=60)


@pytest.mark.parametrize("parts", [2, 3])
@pytest.mark.parametrize("where", ["free space", "walls, lo != 0", "periodic x, walls y"])
def test_particles_migrate_conserves_every_particle_and_field(parts, where):
    """arpy.particles.Particles.migrate on thread ranks after moves past the outer faces (wrapped
    across the periodic ones): gathered, the set holds every key once with its position, D and fields
    bit for bit, each rank's particles in its own box, and the exact sums are the input's."""
    import math

    from arpy.particles import Particles

    box, periodic = _MIGRATION_BOXES[where]
    rng = np.random.default_rng([parts, 7, list(_MIGRATION_BOXES).index(where)])
    n = 700
    lo, hi = (np.zeros(2), np.ones(2)) if box.lo is None else (box.lo, box.hi)
    x = lo + rng.random((n, 2)) * (hi - lo)
    D = rng.uniform(0.01, 0.05, n)
    F = rng.integers(0, 2 ** 64 - 1, (n, 3), dtype=np.uint64, endpoint=True).view(np.float64)
    F[:, 2] = rng.normal(size=n)
    moved = box.wrap(_moved_outside(rng, x, lo, hi, periodic))
    assert np.any((moved < lo) | (moved > hi))

    def rank(comm):
        p = Particles.dealt(x, D, F, ("a", "b", "c"), domain=box, rstar=2.0, comm=comm)
        p.x = moved[p.keys]                       # (keys are the rows of the input)
        p.migrate()
        mine = bool(np.all(p.decomposition.locate(p.x) == comm.rank))
        return p.gather(), mine, p.total(p.n), p.fsum(p.F[:, 2])

    for (k, xs, Ds, Fs), mine, total, s in run_threads(parts, rank, timeout=60):
        assert np.array_equal(k, np.arange(n)) and mine and total == n
        assert xs.tobytes() == moved.tobytes() and Ds.tobytes() == D.tobytes() and Fs.tobytes() == F.tobytes()
        assert s == math.fsum(F[:, 2])


def test_key_places_are_the_places_in_key_order_with_no_rank_holding_every_key(monkeypatch):
    """key_places (a sample sort): on 1 to 5 thread ranks, distinct int64 keys over 18 decades and both
    signs, dealt unevenly (one rank without keys), and on 3 ranks keys repeated within and across ranks,
    the place of each rank's keys among all of them is np.searchsorted of the whole sorted set; at P = 4 no rank receives more than half of the N keys in
    any collective (gathering them all, it took N on every rank); with 2 samples a rank on 5 ranks, the
    places are still exact."""
    from arpy.distributed import SerialComm, reductions
    from arpy.distributed.reductions import key_places

    class Held:
        """A communicator that notes the most keys one collective brought this rank."""

        def __init__(self, comm):
            self.comm, self.rank, self.size, self.most = comm, comm.rank, comm.size, 0

        def allgather(self, value):
            return self._noted(self.comm.allgather(value))

        def alltoall(self, values):
            return self._noted(self.comm.alltoall(values))

        def gather_arrays(self, value):
            got = self.comm.gather_arrays(value)
            self._noted([got[0]])
            return got

        def alltoall_arrays(self, data, counts):
            got = self.comm.alltoall_arrays(data, counts)
            self._noted([got[0]])
            return got

        def _noted(self, got):
            self.most = max(self.most, sum(int(np.size(g)) for g in got))
            return got

    rng = np.random.default_rng(3)
    n = 20000
    keys = np.unique(rng.integers(-(10 ** 18), 10 ** 18, n + 100))[:n]
    keys = rng.permutation(keys)
    want = np.searchsorted(np.sort(keys), keys)
    assert np.array_equal(key_places(SerialComm(), keys), want)
    for parts in (1, 2, 3, 4, 5):
        deal = rng.choice(parts, n, p=np.r_[0.0, np.full(parts - 1, 1.0 / (parts - 1))] if parts > 2 else None)
        held = run_threads(parts, lambda comm: (lambda c: (key_places(c, keys[deal == comm.rank]), c.most))(Held(comm)))
        for r, (places, _) in enumerate(held):
            assert np.array_equal(places, want[deal == r]), (parts, r)
        if parts == 4:
            assert max(most for _, most in held) < n / 2, [most for _, most in held]
    # repeated keys (View.new_keys numbers new particles by their parents' keys): the keys below each
    repeated = rng.integers(0, 50, 3000)
    deal = rng.integers(0, 3, repeated.size)
    want = np.searchsorted(np.sort(repeated), repeated)
    for r, places in enumerate(run_threads(3, lambda comm: key_places(comm, repeated[deal == comm.rank]))):
        assert np.array_equal(places, want[deal == r])
    # fewer samples than ranks (as at P > KEY_SAMPLES, at random places): the places are still exact
    monkeypatch.setattr(reductions, "KEY_SAMPLES", 2)
    deal = rng.integers(0, 5, n)
    want = np.searchsorted(np.sort(keys), keys)
    for r, places in enumerate(run_threads(5, lambda comm: key_places(comm, keys[deal == comm.rank]))):
        assert np.array_equal(places, want[deal == r])


def test_the_median_over_ranks_is_numpys_median_with_nothing_gathered():
    """exact_median (Reductions.gmedian), exact_quantile and order_statistic, by a bisection over the
    values' bits with exact counts: on 1 and 3 thread ranks (one rank without values) bitwise np.median,
    np.quantile (weights of the two order statistics below and above 0.5) and np.sort(v)[k] of every
    rank's values together, for odd and even counts, negative values, ties and 12 decades; NaN with a
    NaN, or with no values."""
    from arpy.distributed.reductions import exact_median, exact_quantile, order_statistic

    qs = (0.0, 0.01, 0.37, 0.5, 0.99, 1.0)

    rng = np.random.default_rng(5)
    for n in (1, 2, 7, 64, 301):
        v = rng.normal(size=n) * 10.0 ** rng.integers(-6, 6, n)
        v[: n // 4] = v[-1]                                         # (ties)
        parts = [v[: n // 2], np.zeros(0), v[n // 2:]]
        ks = sorted({0, (n - 1) // 2, n - 1})
        got = run_threads(3, lambda comm: (exact_median(comm, parts[comm.rank]),
                                           [order_statistic(comm, parts[comm.rank], k) for k in ks],
                                           [exact_quantile(comm, parts[comm.rank], q) for q in qs]))
        assert exact_median(None, v) == np.median(v)
        want = [float(np.quantile(v, q)).hex() for q in qs]
        assert [exact_quantile(None, v, q).hex() for q in qs] == want, n
        for med, stats, quantiles in got:
            assert med == np.median(v) and stats == [np.sort(v)[k] for k in ks], n
            assert [a.hex() for a in quantiles] == want, n
    assert np.isnan(exact_median(None, np.array([1.0, np.nan, 2.0]))) and np.isnan(exact_median(None, np.zeros(0)))
    assert np.isnan(exact_quantile(None, np.array([1.0, np.nan]), 0.5)) and np.isnan(exact_quantile(None, [], 0.5))
    # one process reads its sorted keys directly; the ranks bisect: the same bits, signed zeros included
    z = np.array([0.0, -0.0, 1.0, -0.0, -2.0, 0.0])
    one = [order_statistic(None, z, k).hex() for k in range(z.size)]
    assert one == ["-0x1.0000000000000p+1", "-0x0.0p+0", "-0x0.0p+0", "0x0.0p+0", "0x0.0p+0", "0x1.0000000000000p+0"]
    assert all(got == one for got in run_threads(2, lambda comm: [order_statistic(comm, z[comm.rank::2], k).hex()
                                                                  for k in range(z.size)]))


@pytest.mark.parametrize("guard", [True, False])
def test_a_spliced_interpolation_rebuilds_the_rows_whose_spline_radii_a_new_source_shrinks(guard):
    """DistributedDCPSE builds again only the rows a new source can change (dcpse._spliced).  Off the
    particles a row also reads its sources' spline radii (half the distance to their nearest other
    source): here a new source s lies outside the ball of the point p but nearer to p's source q than
    any other, so q's radius shrinks below |p - q| and p's row changes.  The splice rebuilds that row
    and equals the operator built afresh, bit for bit; without the guard for radii (guard=False) it
    would not."""
    from arpy.distributed.dcpse import _spliced

    box = arpy.Domain([[0.0, 0.0], [1.0, 1.0]])
    q = np.array([0.5, 0.5])
    p = q + [-0.0095, 0.0]                                   # (within q's radius 0.01, not within 0.008)
    th = np.radians(np.linspace(150, 210, 5))
    ghosts = np.concatenate([p + 0.012 * np.stack([np.cos(th), np.sin(th)], 1), [q, q + [0.0, 0.02]]])
    more = np.concatenate([ghosts, [q + [0.016, 0.0]]])      # (|p - s| = 0.0255, outside p's ball 0.015)
    x, cx, ce = np.array([[0.2, 0.2], [0.21, 0.2], [0.2, 0.21]]), p[None, :], np.array([0.015])

    def op(g, only=None):
        return arpy.DomainDCPSE(x, np.full(3, 0.05), cx, ce, domain=box, ghosts=(g, np.full(len(g), 0.05)),
                                keys=np.arange(3 + len(g)), order=2, strict=False, widen=0, max_lebesgue=None,
                                operators=["interpolation"], only=only)

    old = op(ghosts)
    spliced = _spliced(old, old.sources, cx, ce, guard, lambda only: op(more, only)).interpolation()
    fresh = op(more).interpolation()
    assert spliced.indices.tobytes() == fresh.indices.tobytes()
    assert (spliced.data.tobytes() == fresh.data.tobytes()) == guard


def test_collocation_points_outside_their_ranks_box_are_refused_on_every_rank():
    """DistributedDCPSE off the particles reads the stencil of a point from the rank's particles and
    ghosts, which hold every source only for points in the rank's box: a point beyond it (here rank 1
    is given all the points) is refused with ValueError on every rank (no rank left waiting), not
    answered with a stencil that lacks sources."""
    from arpy.distributed import DistributedDCPSE

    rng = np.random.default_rng(3)
    x = rng.random((800, 2))
    eps = np.full(len(x), 0.12)
    box = arpy.Domain([1.0, 1.0], periodic=True)
    y = rng.random((50, 2))

    def rank(comm):
        dec, _ = bisect(x[comm.rank::2], 2, domain=box, comm=comm)
        xs, ks, fl = migrate(comm, dec, x[comm.rank::2], np.arange(len(x))[comm.rank::2], {"eps": eps[comm.rank::2]})
        pts = y if comm.rank == 1 else y[dec.locate(y) == 0]
        try:
            DistributedDCPSE(comm, dec, xs, fl["eps"], ks, pts, np.full(len(pts), 0.12), domain=box)
        except ValueError as e:
            return str(e)
        return None

    got = run_threads(2, rank)
    assert all(g is not None and "rank's box" in g for g in got)
    assert "on this rank" in got[1] and "other ranks" in got[0]


@pytest.mark.parametrize("periodic", [False, (True, False)])
@pytest.mark.parametrize("corner", [0.0, -7.25])
def test_nearest_values_equal_brute_force_and_ask_only_near_ranks(periodic, corner):
    """nearest_values on 1-4 thread ranks, particles dealt at random: the values of the k nearest
    particles of every rank by (distance, key), minimum image along periodic axes, as a brute-force
    search over the whole set gives them; points anywhere (in a hole, outside the box, on a rank without
    particles or with fewer than k); a box at 0 and one whose lower corner is not 0.  A point with k own
    particles nearer than every other rank's box asks no other rank."""
    from arpy.distributed.dcpse import nearest_values

    rng = np.random.default_rng(7)
    box = arpy.Domain((corner + np.zeros(2), corner + np.ones(2)), periodic=periodic)
    x = rng.random((900, 2))
    x = x[np.linalg.norm(x - 0.5, axis=1) > 0.3] + corner          # a hole: points there reach far
    keys = rng.permutation(x.shape[0]).astype(np.int64) * 5 + 1
    vals = rng.normal(size=x.shape[0])
    pts = np.concatenate([rng.random((60, 2)), [[0.5, 0.5], [1.3, 0.2], [-0.4, 0.9]]]) + corner
    period = np.asarray(box.period)

    def brute(k):
        delta = np.abs(pts[:, None] - x[None])
        delta = np.where(period > 0, np.minimum(delta, np.where(period > 0, period, np.inf) - delta), delta)
        dist = np.sqrt((delta ** 2).sum(-1))
        order = np.lexsort((np.broadcast_to(keys, dist.shape), dist), axis=1)
        return vals[order[:, :k]]

    for parts in (1, 2, 3, 4):
        # rank 3 of 4 holds three particles only (fewer than k = 6)
        owner = rng.integers(0, min(parts, 3), x.shape[0])
        if parts == 4:
            owner[:3] = 3

        def rank(comm):
            mine = owner == comm.rank
            out = [nearest_values(comm, x[mine], keys[mine], vals[mine], box, pts[comm.rank::parts], k)
                   for k in (1, 6)]
            # a point amid this rank's own particles: no other rank's box is near, no message
            dec, _ = bisect(x[mine], parts, domain=box, comm=comm)
            xs, ks, fl = migrate(comm, dec, x[mine], keys[mine], {"v": vals[mine]})
            depth = np.minimum(xs - dec.lo[comm.rank], dec.hi[comm.rank] - xs).min(axis=1, initial=np.inf)
            inner = xs[np.argsort(-depth)[:1]] + 1e-6
            sent = comm.messages
            nearest_values(comm, xs, ks, fl["v"], box, inner, 1)
            return out, comm.messages - sent, bool(depth.size and depth.max() > 0.01)

        for r, (out, messages, probed) in enumerate(run_threads(parts, rank)):
            for k, got in zip((1, 6), out):
                np.testing.assert_array_equal(got, brute(k)[r::parts])
            assert not probed or messages == 0
            assert probed or parts == 4 and r == 3


@pytest.mark.parametrize("corner", [0.0, -3.5])
def test_deal_shares_points_evenly_within_the_skin(corner):
    """Decomposition.deal: the same ranks on every call, each point with the rank owning it or with that
    of a box touching its box, within the returned skin of it, the counts even (most=inf) and as locate
    gives them where no point may move (most=0); one box keeps every point.  A box at 0 and one whose
    lower corner is not 0."""
    from arpy.distributed.decomposition import box_gap2

    rng = np.random.default_rng(3)
    box = arpy.Domain((np.full(3, corner), np.full(3, corner + 1.0)))
    x = rng.random((3000, 3)) ** 2 + corner                  # dense by the lower corner
    pts = rng.random((5000, 3)) ** 3 + corner
    for parts in (1, 2, 3, 5):
        dec, _ = bisect(x, parts, domain=box)
        owner = dec.locate(pts)
        rank, skin = dec.deal(pts)
        again, _ = dec.deal(pts)
        assert np.array_equal(rank, again)
        counts = np.bincount(rank, minlength=parts)
        assert counts.max() - counts.min() <= 1 and counts.sum() == len(pts)
        lo, hi = dec.boxes()
        for r in range(parts):
            assert np.all(box_gap2(pts[rank == r], lo[r], hi[r]) <= skin * skin)
        moved = rank != owner
        assert (parts == 1) == (not moved.any()) and (skin == 0) == (not moved.any())
        for a, b in set(zip(owner[moved].tolist(), rank[moved].tolist())):       # (between touching boxes)
            assert b in dec.reaching(dec.lo[a], dec.hi[a]).tolist()
        still, none = dec.deal(pts, most=0.0)
        assert np.array_equal(still, owner) and none == 0.0


def test_deal_evens_a_chain_of_boxes_through_the_middle_one():
    """Three slabs, the points densest in the first: the third's excess reaches the first through the
    second (each hands on the points by its faces), so the skin stays within a fraction of a slab,
    not across the middle one."""
    rng = np.random.default_rng(42)
    box = arpy.Domain((np.array([2.0, -1.0]), np.array([3.0, 0.5])))
    x = np.column_stack([2 + rng.random(3000) ** 2, -1 + 1.5 * rng.random(3000)])
    g = np.stack(np.meshgrid(np.linspace(2.05, 2.95, 60), np.linspace(-0.95, 0.45, 80), indexing="ij"), -1)
    g = g.reshape(-1, 2)
    dec, _ = bisect(x, 3, domain=box)
    assert np.all(dec.lo[:, 0] == 2.0) and np.all(dec.hi[:, 0] == 3.0)      # (slabs along y)
    before = np.bincount(dec.locate(g), minlength=3)
    first, last = int(np.argmin(dec.lo[:, 1])), int(np.argmax(dec.lo[:, 1]))
    assert before[first] < len(g) / 3 < before[last]                   # (the excess is two slabs away)
    rank, skin = dec.deal(g)
    counts = np.bincount(rank, minlength=3)
    assert counts.max() - counts.min() <= 2
    middle = 3 - first - last
    assert skin < 0.25 * (dec.hi[middle, 1] - dec.lo[middle, 1])
