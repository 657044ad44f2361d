"""The distributed layer under MPI: ``mpiexec -n P`` (P = 1, 2, 4) runs tests/mpi_scenario.py in
subprocesses with a timeout; its boxes, ownership and neighbour rows must equal the serial ones
computed here.  A rank that fails ends the whole job within seconds.  MPI comes with the test
environment (mpi4py and the mpich wheel): a missing MPI fails these tests, it does not skip them.
Every launch runs in a process group of its own, killed with its ranks on a timeout
(:func:`mpirun`), and every test has a timeout (pytest-timeout)."""

import itertools
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import arpy
from arpy._bench import run_process_group
from arpy.distributed import bisect
from arpy.io import load_run
from arpy.particles import read_pieces

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from mpi_scenario import MANUFACTURED, pulse_start, scenario  # noqa: E402
from test_distributed import diffuse, lattice, moving_run, on_ranks  # noqa: E402
from test_one_path import shifted_run, shifted_set  # noqa: E402
from test_outputs import by_position, read_pvtu  # noqa: E402

#: Seconds a test of this module may take (pytest-timeout): a hung rank fails the test, it does not hang the suite.
pytestmark = pytest.mark.timeout(240)


def mpiexec() -> str:
    """The mpiexec beside this interpreter (the mpich wheel's), else the one on PATH."""
    local = Path(sys.executable).parent / "mpiexec"
    found = str(local) if local.exists() else shutil.which("mpiexec")
    assert found, "no mpiexec: install the test extra (mpi4py and mpich) or an MPI with mpiexec"
    return found


#: MPICH's progress loop made to yield the core while a rank waits (the test extra's MPICH reads these; other
#: MPIs ignore them): by default a waiting rank spins, and with more ranks than cores (4 ranks on CI's 2) the
#: spinning ranks burn as much CPU as the working ones and slow them down (mpi_scenario.py on 4 ranks:
#: 34-38 s of CPU spinning, 12-13 s yielding after MPICH's default count of idle polls, 10-11 s after 1000).
#: Only when and how ranks wait changes, not what they compute.
YIELD_WHEN_WAITING = {"MPIR_CVAR_CH4_PROGRESS_THROTTLE": "1", "MPIR_CVAR_ENABLE_HEAVY_YIELD": "1",
                      "MPIR_CVAR_CH4_PROGRESS_THROTTLE_NO_PROGRESS_COUNT": "1000"}


def mpirun(parts: int, args: list[str], timeout: float = 60, **kwargs) -> subprocess.CompletedProcess:
    """``mpiexec -n parts python ARGS`` (one OpenMP thread per rank, :data:`YIELD_WHEN_WAITING`; its output
    as text) in a process group of its own, killed with its ranks after ``timeout`` seconds
    (subprocess.TimeoutExpired)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", **YIELD_WHEN_WAITING)
    return run_process_group([mpiexec(), "-n", str(parts), sys.executable, *args], timeout, env=env, **kwargs)


def diffusion_in_process() -> dict[int, str]:
    """The diffusion run of mpi_scenario.py on one thread rank: f by key, as hex strings."""
    x, eps, keys, _ = lattice(40)
    ks, f = on_ranks(1, x, eps, keys, np.zeros(len(x), int), diffuse)
    return {int(k): float(v).hex() for k, v in zip(ks, f)}


def touching_boxes(x, rc, owner, dec, box, r) -> set[int]:
    """The other ranks whose boxes lie within the cutoff of some particle of rank r (periodic axes by
    the minimum image): plain NumPy, particle by box."""
    out = set()
    mine = owner == r
    for q in range(dec.parts):
        if q == r:
            continue
        gap = np.maximum(dec.lo[q] - x[mine], 0) + np.maximum(x[mine] - dec.hi[q], 0)
        if box.any_periodic:
            period = box.hi - box.lo
            for shift in itertools.product((-1, 0, 1), repeat=x.shape[1]):
                xs = x[mine] + np.array(shift) * period * np.asarray(box.periodic)
                gap = np.minimum(gap, np.maximum(dec.lo[q] - xs, 0) + np.maximum(xs - dec.hi[q], 0))
        if np.any(np.sqrt((gap ** 2).sum(axis=1)) <= rc[mine]):
            out.add(q)
    return out


def reductions_wanted(parts: int) -> list:
    """min, max, sum and add over ``parts`` ranks of mpi_scenario.reduction_values, by NumPy: minima and
    maxima in the doubles' total order (-0.0 below 0.0: the keys of sorted()), NaN wherever a rank has one;
    the first r columns of rank r's doubles, concatenated, with where each rank's begin; and what each rank
    receives of the numbers every rank sends to all (one list per rank)."""
    from mpi_scenario import reduction_values

    vals = [reduction_values(r) for r in range(parts)]
    stack = np.stack([v[0].ravel() for v in vals])

    def extreme(pick):
        out = []
        for col in stack.T:
            if np.isnan(col).any():
                out.append(float("nan").hex())
            else:
                out.append(float(pick(col.tolist(), key=lambda x: (x, math.copysign(1.0, x)))).hex())
        return out

    cat = [v[0][:, :r].ravel() for r, v in enumerate(vals)]
    common = [extreme(min), extreme(max), sum(v[1] for v in vals), np.sum([v[2] for v in vals], axis=0).tolist(),
              [float(x).hex() for x in np.concatenate(cat)], np.cumsum([0] + [c.size for c in cat]).tolist()]
    # (rank r receives from rank s: (s + r) % 3 numbers 100 s + r)
    return [common + [[100 * s + r for s in range(parts) for _ in range((s + r) % 3)],
                      [(s + r) % 3 for s in range(parts)]] for r in range(parts)]


@pytest.mark.parametrize("parts", [1, 2, 3])
def test_thread_ranks_and_one_process_reduce_as_the_reference(parts):
    """The reductions of mpi_scenario.reduction_values on thread ranks (and one process) give every rank
    the reference's bits, as MPI ranks do (the test below)."""
    from arpy.distributed import SerialComm, run_threads
    from mpi_scenario import reductions

    got = reductions(SerialComm()) if parts == 1 else run_threads(parts, reductions)[0]
    assert got["every"] == reductions_wanted(parts)


def test_the_layout_of_vector_collectives_refuses_what_mpi_int_counts_cannot_say():
    """MPIComm's gather_arrays and alltoall_arrays pass counts and starts as C ints: their layout is
    exact below 2^31 numbers in all, and beyond it an OverflowError, never counts wrapped around."""
    from arpy.distributed.comm import _layout

    counts, starts = _layout(np.array([2, 0, 3]))
    assert counts.dtype == starts.dtype == np.int32 and counts.tolist() == [2, 0, 3] and starts.tolist() == [0, 2, 2]
    assert _layout(np.array([2 ** 31 - 2, 1]))[1].tolist() == [0, 2 ** 31 - 2]
    with pytest.raises(OverflowError, match="2,147,483,648 numbers"):
        _layout(np.array([2 ** 30, 2 ** 30]))


def test_mpi_ranks_decompose_migrate_and_exchange_like_the_serial_rules(tmp_path):
    """Under mpiexec -n 2, 4 (one process: the in-process references themselves): the boxes, owners and rows of the free and periodic scenarios equal
    the serial ones, 20 diffusion steps on fixed particles and 20 advection-diffusion steps of
    Simulation(comm=) on moving particles give the in-process fields bit for bit, as does RK4 with
    re-organizations on a box whose lower corner is not 0 (tests/test_one_path.py's), as does RK4 on
    fixed particles with reused lists (verlet_skin=0.3) against new lists at every stage, and
    the self-organization of the pulse start (D0 = 0.3) gives the one-process particles bit for bit,
    and min, max, sum and add over the ranks give every rank a NumPy reference's bits (zeros of either
    sign, infinities, NaN on one rank, integers beyond 2^32).  In the launch of -n 2, ``arpy run manufactured`` (Dirichlet walls on ranks) prints the one-process
    summary (N, steps, errors) bit for bit and writes one piece per rank, read back the one-process
    particles and fields; each rank self-organized and kept only its share of the initial set."""
    want, serial_dec, rc_of = {}, {}, {}
    for kind in ("free", "periodic"):
        x, rc, keys, box = scenario(7, kind == "periodic")
        rc_of[kind] = rc
        nl = arpy.neighbor_list(x, rc, full=True, domain=box if kind == "periodic" else None)
        want[kind] = {int(keys[p]): np.sort(keys[nl.neighbors(p)]).tolist() for p in range(len(x))}
        serial_dec[kind] = (x, keys, box)
    reference = diffusion_in_process()
    x, eps, keys, _ = lattice(30)
    moved = {int(k): [float(v).hex() for v in (*p, f)]
             for k, p, f in zip(*moving_run(1, "euler", x, eps, keys, steps=20))}
    x, box, grad = pulse_start()
    ps = arpy.self_organize(x, grad_f=grad, D0=0.3, domain=box, seed=1)
    organized = [[float(v).hex() for v in (*p, d)] for p, d in zip(ps.x, ps.D)]          # in key order
    (k, xs, Ds, Fs), _ = shifted_run(shifted_set(), None, "rk4", 3)
    shifted = {int(a): [float(v).hex() for v in (*p, d, f)] for a, p, d, f in zip(k, xs, Ds, Fs[:, 0])}
    (k, xs, _, Fs), _ = shifted_run(shifted_set(), None, "rk4", 0)                   # (new lists at every stage)
    fixed = {int(a): [float(v).hex() for v in (*p, f)] for a, p, f in zip(k, xs, Fs[:, 0])}
    from arpy.cases import manufactured
    from arpy.cases.reaction_diffusion import manufactured_exact

    options = dict(zip(MANUFACTURED[::2], MANUFACTURED[1::2]))
    walled = manufactured(float(options["--D0"]), options["--walls"], float(options["--T"]), int(options["--k"]))
    exact = manufactured_exact(walled["x"], walled["sim"].t, False)           # (the rms: exact sums of e^2)
    assert all(walled["rms"][k] == math.sqrt(math.fsum((walled[k] - exact[k]) ** 2) / walled["N"]) for k in "uv")
    for parts in (2, 4):
        cli = [str(tmp_path)] if parts == 2 else []
        run = mpirun(parts, [str(HERE / "mpi_scenario.py"), "7", *cli], timeout=120)       # (4 ranks on 2 cores: ~15 s)
        assert run.returncode == 0, run.stderr[-3000:]
        records = json.loads(run.stdout)
        if cli:                                              # (Dirichlet walls on 2 ranks: the one-process run)
            got = records.pop("manufactured")
            row, = got["summary"]["runs"]
            assert len(got["initial"]) == 2 and all(0 < n < N == walled["particles"].n for n, N in got["initial"])
            assert all(row[k] == walled[k] for k in ("N", "steps", "rms", "max", "degenerate")), row
            record, _ = load_run(tmp_path / "manufactured" / "manufactured.npz")
            pieces = read_pieces(tmp_path / "manufactured" / "manufactured.npz", record["pieces"])
            assert len(record["pieces"]["files"]) == 2
            assert all(pieces[k].tobytes() == walled[k].tobytes() for k in ("x", "D", "u", "v"))
        got = records.pop("reductions")["every"]
        assert got == reductions_wanted(parts), parts     # every rank the reference's bits
        advected = records.pop("advection")
        assert {int(k): v for k, v in advected.items()} == moved, parts                 # bitwise, as hex
        diffused = records.pop("diffusion")
        assert {int(k): v for k, v in diffused.items()} == reference, parts         # bitwise, as hex
        got = records.pop("shifted")
        assert {int(k): v for k, v in got.items()} == shifted, parts                # lo != 0: bitwise, as hex
        got = records.pop("kept")
        assert {int(k): v for k, v in got.items()} == fixed, parts                  # verlet_skin: bitwise, as hex
        got = records.pop("organize")
        assert [got[k] for k in sorted(got, key=int)] == organized, parts             # x and D by key, as hex
        for kind, got in records.items():
            x, keys, box = serial_dec[kind]
            dec, owner = bisect(x, parts, domain=box)
            assert got["lo"] == dec.lo.tolist() and got["hi"] == dec.hi.tolist(), (kind, parts)
            assert [sorted(k) for k in got["keys"]] == [sorted(keys[owner == r].tolist()) for r in range(parts)]
            assert {int(k): v for k, v in got["rows"].items()} == want[kind], (kind, parts)
            # a ghost refresh sends one message to each other rank with a box within some own
            # particle's cutoff (by the minimum image along periodic axes), and none to the rest
            assert got["sent"] == [len(touching_boxes(x, rc_of[kind], owner, dec, box, r)) for r in range(parts)]


def test_distributed_benchmark_quick(tmp_path):
    """benchmarks/distributed.py --quick: P = 1 and 2 under mpiexec, the field after the applications
    the same at both (the script's exit status), the exchange costs measured, the whole pulse in 2D and
    3D the same at both with each rank's times, the floor's calls timed, and the page is report() of the JSON."""
    run = run_process_group([sys.executable, str(HERE.parent / "benchmarks" / "distributed.py"), "--quick", "--out",
                             str(tmp_path)], timeout=100)
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    data = json.loads((tmp_path / "distributed_quick.json").read_text())
    assert {(r["d"], r["parts"]) for r in data["runs"]} == {(d, p) for d in (2, 3) for p in (1, 2)}
    assert all(data["comm"][k]["alpha"] > 0 and len(data["comm"][k]["seconds"]) == 6 for k in ("alltoall", "exchange"))
    for r in data["runs"]:
        assert sum(r["owned"]) == r["n"] and len(r["owned"]) == r["parts"]
    # the whole pulse, 2D and 3D: the same error and N at P = 1 and 2, every rank's times in its record
    assert sorted((r["d"], r["parts"]) for r in data["pulse"]) == [(2, 1), (2, 2), (3, 1), (3, 2)]
    for d in (2, 3):
        one, two = sorted((r for r in data["pulse"] if r["d"] == d), key=lambda r: r["parts"])
        assert (one["error"], one["N"]) == (two["error"], two["N"]) and len(two["per_rank"]) == 2
        assert all(0 <= q["idle"] + q["transfer"] <= q["wall"] for q in two["per_rank"])
    # the floor: the same work on both ranks, each rank's calls of both kernels timed
    assert sorted(data["floor"]) == ["2", "3"]
    for rec in data["floor"].values():
        assert len(rec["ranks"]) == 2 and all(0 <= q["idle"] <= q["wall"] for q in rec["ranks"])
        assert all(len(q["times"][k]) == rec["calls"] for q in rec["ranks"] for k in ("laplacian", "energy"))
    sys.path.insert(0, str(HERE.parent / "benchmarks"))
    try:
        import report
    finally:
        sys.path.remove(str(HERE.parent / "benchmarks"))
    assert (tmp_path / "distributed_quick.md").read_text() == report.script("distributed").report(data)


def test_the_benchmarks_timed_comm_times_every_exchange_of_mpi_ranks():
    """benchmarks/distributed.py's TimedComm overrides every method of MPIComm that talks to the other
    ranks (those metered by arpy as exchanges): none of their waiting goes uncounted."""
    from arpy.distributed import MPIComm

    sys.path.insert(0, str(HERE.parent / "benchmarks"))
    import distributed

    metered = {name for name, f in vars(MPIComm).items() if getattr(f, "__code__", None) is not None
               and f.__code__.co_name == "metered"}
    assert {"allgather", "add", "_max_keys", "sparse_alltoall", "exchange"} <= metered
    assert metered <= set(vars(distributed.TimedComm))


def test_the_mpi_example_of_the_readme_runs(tmp_path):
    """docs/examples/mpi_self_organize.py under mpiexec -n 2: it prints the one-process particle count
    and writes a .pvtu with one piece per rank."""
    x = np.random.default_rng(1).uniform(-1, 1, (800, 2))
    from arpy.cases.pulse import pulse_setup

    ps = arpy.self_organize(x, grad_f=pulse_setup(2, 1000.0)["grad0"], D0=0.2, seed=1,
                            domain=arpy.Domain(([-1.0, -1.0], [1.0, 1.0])))
    run = mpirun(2, [str(HERE.parent / "docs" / "examples" / "mpi_self_organize.py")], cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.startswith(f"2 ranks: {ps.n} particles after {len(ps.log)} iterations, converged: True")
    assert sorted(p.name for p in (tmp_path / "pulse_particles").iterdir()) == ["pulse_particles_0.vtu",
                                                                                "pulse_particles_1.vtu"]


#: The ``arpy run`` cases of :func:`test_arpy_run_under_mpiexec_prints_the_one_process_summaries`, one launch
#: for them all: {case: options}.
CASES = {"pulse": ["--k", "2", "--T", "0.03", "--D0", "0.16", "--remeshed", "0", "--no-figure"],
         "burgers": ["--D0", "0.2", "--T", "0.02", "--k", "2", "--remeshed", "0", "--checkpoint-every", "2"],
         "consistency": ["--field", "blob", "--D0-end", "0.22"],      # (two refinements, the fewest allowed)
         "bud-surface": ["--L", "0.45", "--D0", "0.5", "--no-figure"]}


def test_arpy_run_under_mpiexec_prints_the_one_process_summaries(tmp_path):
    """``mpiexec -n 2 python -m arpy run CASE``, for the pulse, Burgers, consistency and bud-surface
    cases one after the other in one launch (tests/mpi_scenario.py ``cases``), prints the summary of the
    one-process run of each, bit for bit, and writes one piece per rank, none gathered (the checks of
    each case: below); rank 0 draws Burgers' figure from the pieces, and with --no-figure (the pulse,
    the bud) no rank draws one; rank 1, which draws none, never imports matplotlib.  (five-spot runs its case function the same way: on thread ranks in
    test_distributed.py; manufactured in the launch of test_mpi_ranks_decompose_migrate_and_exchange...)"""
    run = mpirun(2, [str(HERE / "mpi_scenario.py"), "cases", str(tmp_path), json.dumps(CASES)], timeout=200)
    assert run.returncode == 0, run.stderr[-3000:]
    printed = json.loads(run.stdout)
    assert printed.pop("matplotlib") == [True, False] and sorted(printed) == sorted(CASES)
    pulse_under_mpiexec(printed["pulse"], tmp_path)
    burgers_and_consistency_under_mpiexec(printed, tmp_path)
    bud_surface_under_mpiexec(printed["bud-surface"], tmp_path)
    # (rank 0 draws the figure of the pieces read back, unless --no-figure: then no rank draws)
    assert (tmp_path / "burgers" / "burgers.png").stat().st_size > 0
    assert not [*(tmp_path / "pulse").glob("*.png"), *(tmp_path / "bud-surface").glob("*.png")]


def pulse_under_mpiexec(printed: dict, tmp_path: Path) -> None:
    """``mpiexec -n 2 python -m arpy run pulse --k 2``: the distributed self-organization, time steps
    and re-organizations print the summary of the one-process run (the same particle counts, steps,
    particles, field and error, bit for bit; the mass loss to rounding, an exact sum over the ranks),
    pulse.npz and a .pvtu, each one piece per rank, which read back in key order hold the one-process
    particles (the case on thread ranks: test_distributed.py)."""
    import arpy.cases.pulse as pulse

    kw = dict(D0=0.16, T=0.03, reorganize_every=2)
    serial = pulse.gaussian_pulse(**kw)
    assert serial["N"] != serial["N_initial"]                               # (the re-organizations adapted)
    summary = printed["summary"]
    for key in ("N_initial", "N", "N_max", "steps", "degenerate_max"):
        assert summary[key] == serial[key], key
    assert summary["error"] == serial["error"]
    sidecar = json.loads((tmp_path / "pulse" / "pulse.json").read_text())       # (the record --json printed)
    assert sidecar.pop("pieces")["counts"] and sidecar["ranks"] == 2            # (and the index of the pieces)
    assert sidecar == {k: v for k, v in printed.items() if k not in ("case", "outputs")}
    assert sidecar["columns"] == {"error_history": ["t", "error"]}
    # (the mass: an exact sum over the ranks, numpy's sum on one process)
    assert abs(summary["mass_loss"] - serial["mass_loss"][-1]) <= 1e-9 * abs(serial["mass_loss"][-1])
    record, saved = load_run(tmp_path / "pulse" / "pulse.npz")
    assert sorted(record["pieces"]["files"]) == ["pulse.part00000-of-00002.npz", "pulse.part00001-of-00002.npz"]
    rows = read_pieces(tmp_path / "pulse" / "pulse.npz", record["pieces"])
    assert rows["x"].tobytes() == serial["x"].tobytes() and rows["f"].tobytes() == serial["f"].tobytes()
    assert saved["error_history"][-1].tolist() == [serial["sim"].t, serial["error"]]      # (t, error)
    pieces = sorted(p.name for p in (tmp_path / "pulse" / "pulse_particles").iterdir())
    assert pieces == ["pulse_particles_0.vtu", "pulse_particles_1.vtu"]
    points, data = read_pvtu(tmp_path / "pulse" / "pulse_particles.pvtu")       # (XML, pieces by meshio)
    assert sorted(data) == ["D", "error", "f", "rank"] and set(np.unique(data["rank"])) == {0.0, 1.0}
    final = by_position(serial["x"], serial["f"], serial["D"])
    for a, b in zip(by_position(points[:, :2], data["f"], data["D"]), final):
        np.testing.assert_array_equal(a, b)


def burgers_and_consistency_under_mpiexec(printed: dict, tmp_path: Path) -> None:
    """``mpiexec -n 2 python -m arpy run burgers`` (``... consistency``): the summary of the one-process
    run (particle counts, steps, the error against the spectral reference, the errors of every
    refinement) bit for bit; the particles at T in pieces (Burgers; consistency's errors, rank 0), read
    back equal to the one-process ones, and consistency's finest set with its errors in a .pvtu piece per
    rank (the errors are reductions over the ranks, none gathered); the Burgers run's checkpoints, resumed on one process, end the same.  (five-spot
    runs its case function the same way: on thread ranks in test_distributed.py.)"""
    from arpy.cases import burgers, consistency

    runs = (("burgers", CASES["burgers"], burgers(D0=0.2, T=0.02, reorganize_every=2),
             ("N_initial", "N", "N_max", "steps", "error", "scale_ratio")),
            ("consistency", CASES["consistency"], consistency(field="blob", d0_start=0.25, d0_end=0.22),
             ("N", "err_interp", "p99_interp", "err_laplacian", "failed")))
    for case, options, serial, keys in runs:
        summary = printed[case]["summary"]
        for key in keys:
            assert np.array_equal(summary[key], serial[key]), (case, key)
        record, saved = load_run(tmp_path / case / f"{case.replace('-', '_')}.npz")
        if "pieces" in record:                     # (the particles at T: one piece per rank, none gathered)
            saved.update(read_pieces(tmp_path / case / f"{case.replace('-', '_')}.npz", record["pieces"]))
        arrays = ("err_interp", "err_laplacian", "x_at_max") if case == "consistency" else ("x", "f", "D")
        assert all(saved[k].tobytes() == serial[k].tobytes() for k in arrays), case
    # consistency's finest set: each rank's new particles and their errors (none gathered) in a .pvtu piece
    last = runs[1][2]["last"]
    points, data = read_pvtu(tmp_path / "consistency" / "consistency_particles.pvtu")
    assert set(np.unique(data["rank"])) == {0.0, 1.0}
    for a, b in zip(by_position(points[:, :2], data["D"], data["err_interp"]),
                    by_position(last["x"], last["D"], last["err_interp"])):
        np.testing.assert_array_equal(a, b)
    # the distributed Burgers run wrote checkpoints (rank 0); one process resumes from the last to the same end
    from arpy.cli import main

    (tmp_path / "burgers" / "burgers.npz").unlink()
    assert main(["run", "burgers", *runs[0][1], "--quiet", "--resume", "--out", str(tmp_path)]) == 0
    with np.load(tmp_path / "burgers" / "burgers.npz") as saved:
        assert all(saved[k].tobytes() == runs[0][2][k].tobytes() for k in ("x", "f", "D"))


def bud_surface_under_mpiexec(printed: dict, tmp_path: Path) -> None:
    """``mpiexec -n 2 python -m arpy run bud-surface --L 0.45`` at reduced resolution (D0 = 0.5): the
    self-organization in free space confined to the band (a region) on the ranks gives the one-process
    particles: the same N, iterations and D_p range, every particle away from the band's edges with at
    least N* neighbours (each rank counting its own over its ghosts: the one-process fraction of all
    particles too), and the pieces the ranks write read back as the one-process positions;
    bud_surface(comm=) on 4 thread ranks gives them too, each rank holding only its share."""
    from arpy.cases.bud import bud_surface
    from arpy.distributed import run_threads

    serial = bud_surface(0.45, D0=0.5)
    ps = serial["particles"]
    counts = ps.neighbor_list(full=True).counts()
    assert np.all(counts[serial["interior"]] >= ps.n_star)
    row, = printed["summary"]["runs"]
    for key in ("N_initial", "N", "iterations", "converged", "D_min", "D_max"):
        assert row[key] == serial[key], key
    assert row["N_star_interior"] == 1.0 and row["N_star_all"] == np.mean(counts >= ps.n_star) < 1.0
    record, _ = load_run(tmp_path / "bud-surface" / "bud_L0.45.npz")
    assert len(record["pieces"]["files"]) == 2                  # (one piece per rank, none gathered)
    saved = read_pieces(tmp_path / "bud-surface" / "bud_L0.45.npz", record["pieces"])
    assert saved["x"].tobytes() == ps.x.tobytes() and saved["D"].tobytes() == ps.D.tobytes()
    assert (tmp_path / "bud-surface" / "bud_L0.45_particles.pvtu").exists()
    shares = run_threads(4, lambda comm: bud_surface(0.45, D0=0.5, comm=comm), timeout=300)
    for r in shares:
        assert r["N"] == serial["N"] and r["iterations"] == serial["iterations"]
        assert 0 < r["particles"].n < serial["N"]                  # (its share)
    order = np.argsort(np.concatenate([r["particles"].keys for r in shares]), kind="stable")
    for name in ("x", "D"):
        whole = np.concatenate([getattr(r["particles"], name) for r in shares])[order]
        assert whole.tobytes() == getattr(ps, name).tobytes(), name


@pytest.mark.timeout(60)
@pytest.mark.parametrize("mode, status, printed", [
    ("raise", 1, "arpy: rank 0 of 2 aborts the MPI job (MPI_Abort, exit status 1) on an uncaught RuntimeError: "
                 "rank 0 fails on purpose"),
    ("exit", 3, "arpy: rank 0 of 2 aborts the MPI job (MPI_Abort, exit status 3) on sys.exit(3)"),
    ("disagree", 1, "ValueError: self_organize(comm=): every rank must be given the same D0, but D0 = 0.3 on rank 0; "
                    "0.25 on rank 1"),
], ids=["raise", "exit", "disagree"])
def test_a_failing_rank_ends_the_whole_mpi_job(mode, status, printed):
    """Under mpiexec -n 2, rank 0 raises, or calls sys.exit(3), while rank 1 waits in a collective, or
    the ranks are given different D0 for self_organize(comm=) (every rank raises, naming them): the job
    ends (MPI_Abort) with a status that is not 0 and the rank and its error printed, once, instead of
    hanging (a hang ends at the launch's timeout with TimeoutExpired)."""
    run = mpirun(2, [str(HERE / "mpi_scenario.py"), mode], timeout=30)
    assert run.returncode == status, run.stderr[-3000:]
    assert printed in run.stderr, run.stderr[-3000:]
    if mode != "disagree":                                      # (there, each rank may print its own)
        assert run.stderr.count("arpy: rank") == 1 and run.stderr.count("Traceback") <= 1, run.stderr[-3000:]


@pytest.mark.timeout(60)
def test_a_rank_that_cannot_write_its_checkpoint_ends_the_mpi_job(tmp_path):
    """``mpiexec -n 2 python -m arpy run burgers --checkpoint-every 2`` with the checkpoint path not
    writable (a folder in its place): rank 0, which writes it, fails while rank 1 goes on to the next
    step's collectives; the job ends with status 1 and rank 0's error printed, instead of hanging."""
    (tmp_path / "burgers" / "checkpoint.npz").mkdir(parents=True)
    run = mpirun(2, ["-m", "arpy", "run", "burgers", "--D0", "0.2", "--T", "0.02", "--k", "2", "--remeshed", "0",
                     "--checkpoint-every", "2", "--quiet", "--out", str(tmp_path)], timeout=30)
    assert run.returncode == 1, run.stderr[-3000:]
    line = next((s for s in run.stderr.splitlines() if s.startswith("arpy: rank")), "")
    assert line.startswith("arpy: rank 0 of 2 aborts the MPI job (MPI_Abort, exit status 1) on an uncaught "), \
        run.stderr[-3000:]
    assert "checkpoint.npz" in line
