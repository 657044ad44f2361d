"""Benchmark: a fixed-particle DC-PSE step distributed over MPI ranks (arpy.distributed), P = 1 against 2.

The set: a jittered square lattice in the periodic unit square (2D, N = 1e6; 3D, N = 2e5 in the
periodic unit cube), core size 3.3 spacings (2D) or 2.3 spacings (3D), keys a random permutation,
the particles first dealt to the ranks at random.  Each rank runs, timed: the bisection (``bisect``),
the migration to the owners (``migrate``), the ghost exchange and the DC-PSE Laplacian over its
particles and ghosts (``Laplacian``: halo, alltoall, lists, key order, assembly), and 10 applications
with a ghost refresh each.  Per phase the slowest rank's time is reported, with the ghosts per owned
particle and the imbalance; every rank uses one OpenMP thread, and each P runs in its own
``mpiexec``, ranks bound to cores.  The field after the 10 applications is compared across P (bitwise).

    python benchmarks/distributed.py           # 2D N = 1e6 and 3D N = 2e5 at P = 1, 2 (and 4: correctness)
    python benchmarks/distributed.py --quick   # 2D N = 1e4, 3D N = 8e3 at P = 1, 2 (seconds)

Also: the cost of one exchange by payload (alpha per message, beta per byte), and from these a model
of the step's efficiency at 64 and 1024 ranks for 1e8 particles (:func:`model`).

Then the self-organization of the pulse start (arpy.self_organize with comm=) at D0 = 0.02 (quick: 0.3),
P = 1 and 2: the particles compared across P (bitwise), per-phase times of the slowest rank; and a whole
adaptive simulation of the pulse (Simulation(comm=), re-organizations included; 2D, N_max ~ 1.8e5, and
3D, ~ 5e4) at P = 1, 2 and 4 (quick: 1, 2), with every rank's compute, waiting and transfer times per
phase (:class:`TimedComm`); ``--baseline PYTHON`` runs it with another build too, side by side.  The
floor of that waiting (:func:`worker_floor`, ``--only-floor``): the same work on both ranks, a barrier
after each call.

Results: ``results/distributed.json`` and ``.md`` (the page, from the JSON by :func:`report`).
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from arpy._bench import run_process_group
from arpy.distributed import MPIComm

HERE = Path(__file__).resolve().parent
PHASES = ("bisect", "migrate", "build", "apply")
APPLY = 10


def lattice(n_side: int, d: int, seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A jittered lattice of n_side^d particles in the unit cube, core sizes, keys, and the random deal."""
    rng = np.random.default_rng(seed)
    axes = np.meshgrid(*[np.arange(n_side)] * d, indexing="ij")
    x = (np.stack([a.ravel() for a in axes], axis=1) + 0.5 + rng.uniform(-0.3, 0.3, (n_side ** d, d))) / n_side
    eps = np.full(len(x), (3.3 if d == 2 else 2.3) / n_side)
    return x, eps, rng.permutation(len(x)).astype(np.int64), rng.integers(0, 1 << 30, len(x))


def worker(d: int, n_side: int) -> None:
    """One rank of the SPMD run (under mpiexec); rank 0 prints the record as JSON."""
    import arpy
    from arpy.distributed import Laplacian, MPIComm, bisect, migrate

    comm = MPIComm()
    x, eps, keys, deal = lattice(n_side, d)
    box = arpy.Domain(np.ones(d), periodic=True)
    mine = deal % comm.size == comm.rank
    t = {}
    t0 = time.perf_counter()
    dec, _ = bisect(x[mine], comm.size, domain=box, comm=comm)
    t["bisect"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    xs, ks, fl = migrate(comm, dec, x[mine], keys[mine], {"eps": eps[mine]})
    t["migrate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    lap = Laplacian(comm, dec, xs, fl["eps"], ks, domain=box)
    t["build"] = time.perf_counter() - t0
    f = np.sin(2 * np.pi * xs[:, 0])
    t0 = time.perf_counter()
    for _ in range(APPLY):
        f = f + 1e-5 * lap.apply(f)
    t["apply"] = time.perf_counter() - t0
    # what this rank sends to the others: a ghost's position, core size and key at the build, its
    # value at each application
    sent = sum(len(g) for r, g in enumerate(lap.ghosts.sends) if r != comm.rank)
    rows = comm.allgather({"t": t, "owned": int(len(ks)), "ghosts": int(lap.ghosts.keys.size),
                           "bytes_build": int(sent * (d + 2) * 8), "bytes_apply": int(sent * 8),
                           "f": dict(zip(ks.tolist(), (float(v).hex() for v in f)))})
    if comm.rank == 0:
        fields = {}
        for r in rows:
            fields.update(r.pop("f"))
        digest = hashlib.sha256(" ".join(fields[k] for k in sorted(fields)).encode()).hexdigest()
        json.dump({"ranks": rows, "field_digest": digest, "n": int(len(x))}, sys.stdout)


#: Phases of the distributed self-organization, summed over its iterations (the log's timings).
SO_PHASES = ("t_fuse_insert", "t_resolution", "t_lists", "t_forces")


def worker_organize(D0: float) -> None:
    """One rank of the distributed self-organization of the pulse start (800 random particles in
    [-1, 1]^2 with walls, the monitor of Eq. 2.8 at Pe = 1000); rank 0 prints the record as JSON."""
    import arpy
    from arpy.cases.pulse import pulse_setup
    from arpy.distributed import MPIComm, bisect, gather, migrate

    comm = MPIComm()
    box = arpy.Domain(([-1.0, -1.0], [1.0, 1.0]))
    x = np.random.default_rng(1).uniform(-1, 1, (800, 2))
    keys = np.arange(len(x), dtype=np.int64)
    mine = keys % comm.size == comm.rank
    t0 = time.perf_counter()
    dec, _ = bisect(x[mine], comm.size, domain=box, comm=comm)
    xs, ks, _ = migrate(comm, dec, x[mine], keys[mine])
    out = arpy.self_organize(xs, grad_f=pulse_setup(2, 1000.0)["grad0"], D0=D0, domain=box, seed=1, comm=comm, keys=ks,
                             decomposition=dec)
    total = time.perf_counter() - t0
    phases = {p: float(sum(e[p] for e in out.log)) for p in SO_PHASES}
    k, xg, Dg = gather(comm, out.keys, out.x, out.D)
    rows = comm.allgather({"total": total, "phases": phases, "owned": int(out.keys.size)})
    if comm.rank == 0:
        digest = hashlib.sha256(" ".join(float(v).hex() for v in np.concatenate([xg.ravel(), Dg])).encode())
        json.dump({"ranks": rows, "digest": digest.hexdigest(), "n": int(len(k)), "iterations": len(out.log),
                   "converged": bool(out.converged)}, sys.stdout)


#: The floor's particles per rank (n_side per d, about a rank's share of the whole pulse at P = 2) and
#: calls of each kernel.
FLOOR_SIZES = {False: ({2: 297, 3: 30}, 20), True: ({2: 40, 3: 12}, 3)}


def worker_floor(quick: bool) -> None:
    """The waiting this machine adds by itself: every rank runs the same work on the same particles,
    a barrier after each call, for the pulse's two heaviest kernels (the DC-PSE Laplacian build of
    the right-hand side, order 4, and the self-organization's neighbour list and energy with its
    gradient) on a jittered lattice of about a rank's share of the pulse at P = 2 in a periodic box;
    rank 0 prints per d each rank's wall, compute and waiting seconds and its calls' compute times."""
    from mpi4py import MPI

    import arpy
    from arpy.adapt.forces import energy_terms

    comm = MPI.COMM_WORLD
    sides, calls = FLOOR_SIZES[quick]
    out = {}
    for d, n_side in sides.items():
        x, eps, _, _ = lattice(n_side, d)
        box = arpy.Domain([1.0] * d, periodic=True)
        D = eps / 3.0

        def laplacian() -> None:
            arpy.DomainDCPSE(x, eps, domain=box, order=4, strict=False).laplacian()

        def energy() -> None:
            energy_terms(x, D, arpy.neighbor_list(x, 3.0 * D, full=True, domain=box), domain=box, cutoff=3.0)

        times: dict[str, list[float]] = {"laplacian": [], "energy": []}
        idle = 0.0
        comm.Barrier()
        t0 = time.perf_counter()
        for _ in range(calls):
            for name, kernel in (("laplacian", laplacian), ("energy", energy)):
                t = time.perf_counter()
                kernel()
                t1 = time.perf_counter()
                times[name].append(t1 - t)
                comm.Barrier()
                idle += time.perf_counter() - t1
        wall = time.perf_counter() - t0
        rows = comm.allgather({"wall": wall, "idle": idle, "times": times})
        out[str(d)] = {"n": int(x.shape[0]), "calls": calls, "ranks": rows}
    if comm.Get_rank() == 0:
        json.dump(out, sys.stdout)


def floor_lines(floor: dict) -> list[str]:
    """The page's lines of :func:`worker_floor`'s record."""
    lines = ["", "## The floor: the same work on every rank", "",
             "`python benchmarks/distributed.py --only-floor`: both ranks run the same work on the same particles, "
             "a barrier after each call (one OpenMP thread per rank, ranks bound to the two cores): the pulse's two "
             "heaviest kernels, the DC-PSE Laplacian build of order 4 and the self-organization's neighbour list "
             "with its energy and gradient, alternately, on a jittered lattice of about a rank's share of the "
             "pulse at P = 2 in a periodic box. Whatever a rank waits here comes from the machine, not from arpy: "
             "calls of the same work take different times on the two cores. Spread: the standard deviation of a "
             "rank's calls over their mean; difference: the mean of |rank 0's call - rank 1's| over the mean call.",
             "", "| d | N per rank | calls | kernel | mean call per rank [ms] | spread per rank | difference |",
             "|---|---|---|---|---|---|---|"]
    for d, rec in floor.items():
        for kernel in ("laplacian", "energy"):
            t = [np.array(r["times"][kernel]) for r in rec["ranks"]]
            diff = float(np.mean(np.abs(t[0] - t[-1])) / np.mean(np.concatenate(t)))
            lines.append(f"| {d} | {rec['n']:,} | {rec['calls']} | {kernel} | "
                         + ", ".join(f"{1e3 * a.mean():.1f}" for a in t) + " | "
                         + ", ".join(f"{a.std() / a.mean():.3f}" for a in t) + f" | {diff:.3f} |")
    lines.append("")
    for d, rec in floor.items():
        waits = [r["idle"] / r["wall"] for r in rec["ranks"]]
        lines.append(f"- {d}D: waiting " + ", ".join(f"{100 * w:.1f}" for w in waits)
                     + f" % of the ranks' wall times ({rec['ranks'][0]['wall']:.1f} s), the same work on each.")
    return lines


#: Payloads of the communication benchmark, in doubles per rank and message.
PAYLOADS = (0, 16, 256, 4096, 65536, 1048576)


def worker_comm(quick: bool) -> None:
    """The cost of one exchange as arpy makes them, by payload: ``MPIComm.alltoall`` of NumPy arrays
    (pickled, one message to every rank: the ghost set-up's and the refresh's exchange before they
    went to the neighbours only) and ``MPIComm.exchange`` (the arrays' bytes, to the other rank: the
    refresh's now); rank 0 prints the median seconds per call of each as JSON."""
    from arpy.distributed import MPIComm

    comm = MPIComm()
    out: dict[str, dict[int, float]] = {"alltoall": {}, "exchange": {}}
    other = (comm.rank + 1) % comm.size
    for size in PAYLOADS:
        arr = np.ones(size)
        reps = (20 if quick else 200) if size <= 4096 else (3 if quick else 20)
        for kind in out:
            times = []
            for _ in range(reps):
                comm.allgather(None)
                t0 = time.perf_counter()
                if kind == "alltoall":
                    comm.alltoall([arr] * comm.size)
                else:
                    comm.exchange({other: arr}, {other: np.empty(size)})
                times.append(time.perf_counter() - t0)
            out[kind][size * 8] = float(np.median(times))
    worst = comm.allgather(out)
    if comm.rank == 0:
        json.dump({k: {str(b): max(w[k][b] for w in worst) for b in out[k]} for k in out}, sys.stdout)


def comm_call(quick: bool) -> list[str]:
    """The worker arguments of the communication benchmark."""
    return ["--worker-comm", str(int(quick))]


def comm_record(seconds: dict[str, dict[str, float]], parts: int = 2) -> dict:
    """For each kind of exchange: seconds per call by bytes per message, and the fit t = alpha + beta
    * bytes (least squares; alpha at least the empty message's time)."""
    out: dict[str, Any] = {"parts": parts}
    for kind, by_bytes in seconds.items():
        b = np.array(sorted(int(k) for k in by_bytes), float)
        t = np.array([by_bytes[str(int(k))] for k in b])
        beta, alpha = np.polyfit(b, t, 1)
        out[kind] = {"seconds": {str(int(k)): float(v) for k, v in zip(b, t)},
                     "alpha": float(max(alpha, t[0])), "beta": float(beta)}
    return out


#: Core size over lattice spacing of the benchmark's sets (2D, 3D): the ghost layer's width.
CORE = {2: 3.3, 3: 2.3}


def ghost_ratio(n: float, d: int) -> float:
    """Ghosts per owned particle of a cubic subdomain of n particles on the lattice, its layer CORE[d]
    spacings wide on every face: (1 + 2a / n^(1/d))^d - 1."""
    return (1 + 2 * CORE[d] / n ** (1 / d)) ** d - 1


#: How much wider (in core sizes) the ghost layer of :func:`ghost_cost`'s second build is.
GHOST_SKIN = 2.0
#: The lattices (d: particles per side) :func:`ghost_cost` measures on, full and quick: small enough that
#: the ghosts are a good part of the sources (at N = 1e6 in 2D they are 1 %, and their cost is lost in
#: the noise of the build).
GHOST_SIDES = {False: {2: 200, 3: 30}, True: {2: 60, 3: 12}}


def ghost_cost(d: int, n_side: int, repeat: int = 5) -> dict:
    """What a ghost costs against an owned particle in the fixed-particle step, on one process (its
    ghosts: the periodic images of the box): the build with the step's ghost layer and with one
    GHOST_SKIN core sizes wider (the same rows, more ghosts), and the applications, each the best of
    ``repeat``.  A ghost is a source, never a row: it costs its exchange, its place in the cells and
    the pairs it is tested in, not an assembly.  Per ghost c_g: the build's growth over the ghosts
    added; per owned particle c: the step less its ghosts' share; ``ratio`` c_g / c."""
    import arpy
    from arpy.distributed import Laplacian, SerialComm, bisect

    x, eps, keys, _ = lattice(n_side, d)
    order = np.argsort(keys)
    x, eps, keys = x[order], eps[order], keys[order]
    box, comm = arpy.Domain(np.ones(d), periodic=True), SerialComm()
    dec, _ = bisect(x, 1, domain=box, comm=comm)
    build: dict[float, float] = {}
    ghosts: dict[float, int] = {}
    apply = np.inf
    for _ in range(repeat):
        for skin in (0.0, GHOST_SKIN):
            t0 = time.perf_counter()
            lap = Laplacian(comm, dec, x, eps, keys, domain=box, skin=skin * float(eps[0]))
            build[skin] = min(build.get(skin, np.inf), time.perf_counter() - t0)
            ghosts[skin] = int(lap.ghosts.keys.size)
            if skin == 0.0:
                f = np.sin(2 * np.pi * x[:, 0])
                t0 = time.perf_counter()
                for _ in range(APPLY):
                    f = f + 1e-5 * lap.apply(f)
                apply = min(apply, time.perf_counter() - t0)
    n, g0, g1 = len(x), ghosts[0.0], ghosts[GHOST_SKIN]
    per_ghost = (build[GHOST_SKIN] - build[0.0]) / (g1 - g0)
    per_owned = (build[0.0] + apply - g0 * per_ghost) / n
    return {"d": d, "n": n, "ghosts": [g0, g1], "build": [build[0.0], build[GHOST_SKIN]], "apply": apply,
            "per_owned": per_owned, "per_ghost": per_ghost, "ratio": per_ghost / per_owned}


def ghost_costs(sizes: dict[int, int]) -> dict[str, dict]:
    """:func:`ghost_cost` of each lattice (d: n_side), printed as it goes; keyed by str(d) (JSON)."""
    out = {}
    for d, n_side in sizes.items():
        c = out[str(d)] = ghost_cost(d, n_side)
        print(f"{d}D N = {c['n']:,}: a ghost costs {c['ratio']:.3f} of an owned particle "
              f"({1e6 * c['per_ghost']:.2f} against {1e6 * c['per_owned']:.2f} us)", flush=True)
    return out


def model(res: dict, N: float = 1e8, ranks: tuple[int, ...] = (64, 1024)) -> list[dict]:
    """The expected time of the benchmark's step (a build and APPLY applications) for N particles on P
    ranks, from the measured P = 1 costs per particle, the ghost ratio g of a cubic subdomain and the
    measured per-message and per-byte costs: compute n c (1 + r g), with r the measured cost of a ghost
    against an owned particle (:func:`ghost_cost`; 1 where not measured) and c the P = 1 step per owned
    particle less its ghosts' share, plus the exchanges of a step, the ghosts' bytes included:
    "alltoall", as before, 1 + APPLY pickled all-to-alls of P messages each; "neighbours", as now, the
    set-up's pickled messages and APPLY refreshes by ``exchange`` (buffers), 3^d - 1 messages each (to
    the neighbouring boxes).  Efficiency: n c over the total."""
    pickled, buffers = res["comm"]["alltoall"], res["comm"]["exchange"]
    out = []
    for d in sorted({r["d"] for r in res["runs"]}):
        one = next(r for r in res["runs"] if r["d"] == d and r["parts"] == 1)
        r_g = res.get("ghost_cost", {}).get(str(d), {}).get("ratio", 1.0)
        per = (one["phases"]["build"] + one["phases"]["apply"]) / one["n"] / (1 + r_g * sum(one["ghosts"]) / one["n"])
        for P in ranks:
            n = N / P
            g = ghost_ratio(n, d)
            compute = per * n * (1 + r_g * g)
            build, apply = g * n * (d + 2) * 8, g * n * APPLY * 8          # bytes: at the set-up, the refreshes
            neighbours = 3 ** d - 1
            for name, comm in (
                    ("alltoall", (1 + APPLY) * P * pickled["alpha"] + (build + apply) * pickled["beta"]),
                    ("neighbours", neighbours * (pickled["alpha"] + APPLY * buffers["alpha"])
                     + build * pickled["beta"] + apply * buffers["beta"])):
                out.append({"d": d, "P": P, "n": n, "ghosts": g, "ghost_cost": r_g, "compute": compute,
                            "exchange": name, "comm": comm, "efficiency": per * n / (compute + comm)})
    return out


#: Phases of a simulation step in its log (arpy.simulation.PHASES), summed over the run.
RUN_PHASES = ("t_monitor", "t_organize_lists", "t_organize_rest", "t_interpolate", "t_rhs")


#: The phases of a whole run that :class:`TimedComm` tells apart, by the functions on the stack at an
#: exchange (:data:`_PART_OF`; the innermost decides, the self-organization outside a re-organization
#: being the initial one): the initial self-organization, the Simulation's construction (dealing the
#: set), the monitor, the re-organization's self-organization, its old -> new interpolation, the
#: right-hand side of a step, the rest of a step (the migration after it, its global figures), the
#: mass integrals, and the rest.
RUN_PARTS = ("initial", "setup", "monitor", "organize", "interpolate", "rhs", "step", "mass", "other")
_PART_OF = {("cases/pulse.py", "_mass"): "mass", ("adapt/resolution.py", "field_resolution"): "monitor",
            ("adapt/organize.py", "self_organize"): "organize", ("arpy/reorganization.py", "reorganize"): "interpolate",
            ("arpy/simulation.py", "_rhs"): "rhs", ("arpy/simulation.py", "_step"): "step",
            ("arpy/simulation.py", "__init__"): "setup"}


def run_part(frame: Any) -> str:
    """The phase (:data:`RUN_PARTS`) of the code at ``frame``, from the functions on its stack."""
    found = []
    while frame is not None:
        code = frame.f_code
        part = next((p for (f, n), p in _PART_OF.items() if n == code.co_name and code.co_filename.endswith(f)), None)
        if part is not None:
            found.append(part)
        frame = frame.f_back
    if not found:
        return "other"
    if found[0] == "organize" and "interpolate" not in found:
        return "initial"
    return found[0]


class TimedComm(MPIComm):
    """MPIComm() that also times its exchanges (collectives, ghost refreshes, sparse all-to-alls):
    ``idle``, the seconds spent waiting for the other ranks (a barrier before each), and ``transfer``,
    those in the exchange itself; and per phase of the run (:func:`run_part` at each exchange),
    ``parts[phase] = [compute wall, compute CPU, waiting, transferring]`` seconds, the compute being
    what ran since the previous exchange (CPU: this process's, ``time.process_time``).  :meth:`close`
    counts what ran after the last exchange (as ``other``)."""

    def __init__(self) -> None:
        super().__init__()
        self.idle = self.transfer = 0.0
        self.exchanging = 0.0          # (the CPU time of the exchanges, the barriers' too: arpy.distributed.balance)
        self.parts: dict[str, list[float]] = {p: [0.0, 0.0, 0.0, 0.0] for p in RUN_PARTS}
        self._mark = (time.perf_counter(), time.process_time())

    def _account(self, part: str) -> list[float]:
        t, c = time.perf_counter(), time.process_time()
        rec = self.parts[part]
        rec[0] += t - self._mark[0]
        rec[1] += c - self._mark[1]
        return rec

    def close(self) -> None:
        """Count the compute since the last exchange."""
        self._account("other")
        self._mark = (time.perf_counter(), time.process_time())

    def _timed(self, collective: Any, *args: Any) -> Any:
        rec = self._account(run_part(sys._getframe(2)))
        t0, c0 = time.perf_counter(), time.process_time()
        self._comm.Barrier()
        t1 = time.perf_counter()
        self.exchanging += time.process_time() - c0
        out = collective(*args)
        t2 = time.perf_counter()
        self.idle += t1 - t0
        self.transfer += t2 - t1
        rec[2] += t1 - t0
        rec[3] += t2 - t1
        self._mark = (t2, time.process_time())
        return out

    def allgather(self, value: Any) -> list[Any]:
        return self._timed(super().allgather, value)

    def alltoall(self, values: Any) -> list[Any]:
        return self._timed(super().alltoall, values)

    def exchange(self, sends: Any, recv: Any) -> None:
        self._timed(super().exchange, sends, recv)

    def sparse_alltoall(self, values: Any) -> list[Any]:
        return self._timed(super().sparse_alltoall, values)

    def add(self, value: Any) -> Any:
        return self._timed(super().add, value)

    def gather_arrays(self, value: Any) -> Any:
        return self._timed(super().gather_arrays, value)

    def alltoall_arrays(self, data: Any, counts: Any) -> Any:
        return self._timed(super().alltoall_arrays, data, counts)

    def _max_keys(self, keys: Any) -> Any:
        return self._timed(super()._max_keys, keys)


def worker_pulse(d: int, D0: float, T: float, k: int, mass_points: int) -> None:
    """One rank of the Sec. 4.3 pulse in d dimensions (:func:`arpy.cases.gaussian_pulse`, forward
    Euler, a re-organization every k steps) over a :class:`TimedComm`; rank 0 prints the record as
    JSON: per rank the wall time, the log's phases, the particles owned at T and the seconds in
    collectives (waiting, transferring)."""
    from arpy.cases import gaussian_pulse

    comm = TimedComm()
    t0 = time.perf_counter()
    r = gaussian_pulse(d=d, D0=D0, T=T, reorganize_every=k, comm=comm, mass_points=mass_points)
    wall = time.perf_counter() - t0
    comm.close()
    idle, transfer = comm.idle, comm.transfer
    log = r["sim"].log
    phases = {p: float(sum(e[p] for e in log)) for p in RUN_PHASES}
    phases["steps"] = float(sum(e["t_step"] for e in log))
    rows = comm.allgather({"wall": wall, "phases": phases, "owned": int(r["sim"].n), "idle": idle,
                           "transfer": transfer, "parts": comm.parts})
    if comm.rank == 0:
        json.dump({"ranks": rows, "N_initial": r["N_initial"], "N": r["N"], "N_max": r["N_max"], "steps": r["steps"],
                   "reorganizations": int(sum(e["reorganized"] for e in log)), "error": r["error"],
                   "mass_loss": float(r["mass_loss"][-1])}, sys.stdout)


def pulse_record(rec: dict, d: int, D0: float, T: float, k: int, parts: int) -> dict:
    """The whole pulse's record (``--worker-pulse``) with the slowest rank's times and every rank's
    own (``per_rank``)."""
    rec = dict(rec)
    ranks = rec.pop("ranks")
    return {**rec, "d": d, "D0": D0, "T": T, "k": k, "parts": parts, "wall": max(r["wall"] for r in ranks),
            "phases": {p: max(r["phases"][p] for r in ranks) for p in (*RUN_PHASES, "steps")},
            "owned": [r["owned"] for r in ranks], "per_rank": ranks}


#: The whole-simulation runs (d, D0, T, k, mass points per axis): 2D N_max ~ 1.8e5, 3D ~ 5e4.
PULSE_RUNS = {False: ((2, 0.008, 0.0004, 4, 301), (3, 0.1, 0.1, 4, 41)),
              True: ((2, 0.3, 0.004, 2, 31), (3, 1.0, 0.05, 2, 11))}


def pulse_calls(quick: bool) -> list[list[str]]:
    """The worker arguments of the whole-pulse runs."""
    return [["--worker-pulse", str(d), repr(D0), repr(T), str(k), str(m)] for d, D0, T, k, m in PULSE_RUNS[quick]]


def pulse_records(recs: list[dict], quick: bool, parts: int, runs: Any = None) -> list[dict]:
    """The whole-pulse records of one P from the batch's outputs (of the ``runs``, default every run of
    :data:`PULSE_RUNS`), printed as they come."""
    out = []
    for rec, (d, D0, T, k, _) in zip(recs, PULSE_RUNS[quick] if runs is None else runs):
        out.append(pulse_record(rec, d, D0, T, k, parts))
        r = out[-1]
        print(f"pulse {d}D D0 = {D0} P = {parts}: N_max = {r['N_max']:,}, {r['steps']} steps, {r['wall']:.2f} s",
              flush=True)
    return out


def run_pulses(quick: bool, ranks: Any, *pythons: str, warm: bool = True, repeat: int = 1) -> list[list[dict]]:
    """The whole-pulse records at each P of ``ranks``, each run in its own mpiexec, with each of the
    interpreters ``pythons`` (other builds; default this one), each run of one right after the same
    run of the other (first one, then the other in turn), so that all see the machine alike: one list
    of records per interpreter.  Each run is made ``repeat`` times; the record of the median wall time
    is kept, with every run's wall time, waiting (:func:`balance`), error and N in its ``repeats``.
    The first run is made once more before them all and left out (``warm``, where nothing ran
    before): the first of a series runs slower on this machine (measured: 63.3 s against 60.0 s for
    the other build right after it, the same build at the same speed as the other in alternate runs)."""
    pythons = pythons or (sys.executable,)
    if warm and len(ranks):
        launch(ranks[0], pulse_calls(quick)[:1], python=pythons[0])
    out: list[list[dict]] = [[] for _ in pythons]
    for parts in ranks:
        for call, run in zip(pulse_calls(quick), PULSE_RUNS[quick]):
            got: list[list[dict]] = [[] for _ in pythons]
            for i in range(repeat):
                for j in (range(len(pythons)) if i % 2 == 0 else reversed(range(len(pythons)))):
                    got[j] += pulse_records(launch(parts, [call], python=pythons[j]), quick, parts, [run])
            for recs, runs in zip(out, got):
                kept = sorted(runs, key=lambda r: r["wall"])[(len(runs) - 1) // 2]
                recs.append({**kept, "repeats": [{"wall": r["wall"], "waiting": balance(r)["waiting"],
                                                  "error": r["error"], "N": r["N"]} for r in runs]})
    return out


def revision(python: str) -> str:
    """The git revision (short) of the arpy that ``python`` imports, or '?' where it is not in a git tree."""
    where = subprocess.run([python, "-c", "import arpy, pathlib; print(pathlib.Path(arpy.__file__).parent)"],
                           capture_output=True, text=True).stdout.strip()
    out = subprocess.run(["git", "-C", where or ".", "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return out.stdout.strip() if out.returncode == 0 and where else "?"


def same_pulse(pulse: list[dict]) -> bool:
    """Whether every run of the pulse of one build (its repeats too) gives the error and N of the P = 1
    run of its dimension."""
    first = {r.get("d", 2): r for r in sorted(pulse, key=lambda r: r["parts"], reverse=True)}
    return all((q["error"], q["N"]) == (first[r.get("d", 2)]["error"], first[r.get("d", 2)]["N"])
               for r in pulse for q in r.get("repeats", [r]))


def worker_memory(arpy_args: list[str]) -> None:
    """One rank of ``arpy run`` (``arpy_args``: the case and its options) under mpiexec, its printed text
    dropped; then every rank's peak resident memory (``resource.getrusage`` ru_maxrss: the kernel's
    high-water mark, VmHWM), and its resident memory before the run (after Python, NumPy, mpi4py and
    arpy's CLI were imported); rank 0 prints them as JSON, in bytes."""
    import contextlib
    import io
    import resource

    from arpy.cli import main as arpy_main

    comm = MPIComm()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    with contextlib.redirect_stdout(io.StringIO()):
        code = arpy_main(["run", *arpy_args])
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    rows = comm.allgather({"start": before, "peak": peak, "exit": code})
    if comm.rank == 0:
        json.dump(rows, sys.stdout)


#: The run of the memory benchmark (``--memory``): the 2D pulse at a D0 where the particles dominate the
#: memory, a few steps (no re-organization, to keep the run short: the initial self-organization is the
#: same computation), a checkpoint every 2; and the same at a D0 where they do not (the baseline).
MEMORY_RUN = ["pulse", "--d", "2", "--T", "{T}", "--D0", "{D0}", "--k", "0", "--mass-every", "0", "--remeshed", "0",
              "--checkpoint-every", "2", "--quiet"]
#: (D0, T) of the memory benchmark's runs: the measured one (full: D0 = 0.0025, 1.7e6 particles, 4 steps,
#: so that a checkpoint is written during the run; a size where the particle data is most of the one
#: process's peak, so that the share of it each rank holds sets the ratio rather than what every rank holds
#: without particles: Python, NumPy, mpi4py, arpy and, on rank 0, matplotlib, about 135 MiB; each of the
#: two runs takes about half an hour here) and the baseline (the default D0, 2.4e3 particles; a coarser D0
#: is no baseline: the mass's mesh points, 301^2, then take the coarse particles' wide stencils), full and
#: --quick.
MEMORY_SIZES = {False: ((0.0025, 6e-6), (0.08, 6e-5)), True: ((0.03, 1e-4), (0.08, 1e-4))}


def memory_record(quick: bool, out: Path) -> dict:
    """Peak resident memory per rank of ``arpy run pulse`` with checkpoints (:data:`MEMORY_RUN`) at P = 1
    and P = 4 (oversubscribed on this machine, which is fine for memory), at the size where the particles
    dominate and at the baseline size, the four runs at once (each in its own mpiexec); the run's particle
    counts from its results (pulse.json)."""
    from concurrent.futures import ThreadPoolExecutor

    def one(what: str, D0: float, T: float, parts: int) -> dict:
        folder = out / f"memory_{what}_{parts}"
        argv = [a.format(D0=D0, T=T) for a in MEMORY_RUN] + ["--out", str(folder)]
        ranks = launch(parts, [["--worker-memory", json.dumps(argv)]])[0]
        summary = json.loads((folder / "pulse" / "pulse.json").read_text())["summary"]
        r = {"what": what, "D0": D0, "T": T, "parts": parts, "ranks": ranks,
             **{k: summary[k] for k in ("N_initial", "N", "N_max", "steps")}}
        print(f"memory: {what} D0 = {D0} P = {parts}: N_max = {r['N_max']:,}, peak RSS per rank "
              + ", ".join(f"{q['peak'] / 2 ** 20:.0f}" for q in ranks) + " MiB", flush=True)
        return r

    # the runs at once (memory does not depend on the time they take), the measured ones first
    runs = [(what, D0, T, parts) for (D0, T), what in zip(MEMORY_SIZES[quick], ("particles", "baseline"))
            for parts in (1, 4)]
    with ThreadPoolExecutor(len(runs)) as pool:
        return {"runs": list(pool.map(lambda run: one(*run), runs)), "date": time.strftime("%Y-%m-%d")}


def memory_lines(mem: dict) -> list[str]:
    """The page's section on the memory benchmark (:func:`memory_record`)."""
    runs = {(r["what"], r["parts"]): r for r in mem["runs"]}
    lines = ["", "## Peak resident memory per rank: `arpy run pulse` with checkpoints", "",
             "`python benchmarks/distributed.py --memory`: `mpiexec -n P arpy run "
             + " ".join(MEMORY_RUN).replace("{T}", "T").replace("{D0}", "D0") + "` with D0 and T of the table "
             "(one OpenMP thread per rank; P = 4 oversubscribes the two cores, which changes no memory). Each rank's "
             "peak resident memory is its high-water mark (`getrusage` ru_maxrss, VmHWM) at the end; 'at start' is "
             "its resident memory after Python, NumPy, mpi4py and arpy's CLI were imported, before the run. The "
             "baseline run (a D0 of few particles) shows what a rank holds without particle data."
             + (f" Measured {mem['date']}." if mem.get("date") else ""), "",
             "| run | D0 | T | steps | N at t = 0 | N max | P | rank | at start (MiB) | peak (MiB) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    def mib(v: float | None) -> str:
        return "–" if v is None else f"{v / 2 ** 20:.0f}"

    for r in mem["runs"]:
        for i, q in enumerate(r["ranks"]):
            lines.append(f"| {r['what']} | {r['D0']:g} | {r['T']:g} | {r['steps']} | {r['N_initial']:,} | "
                         f"{r['N_max']:,} | {r['parts']} | {i} | {mib(q['start'])} | {mib(q['peak'])} |")
    lines += [""] + [f"- {r['what']} at P = {r['parts']}: {r['stopped']}." for r in mem["runs"] if r.get("stopped")]
    one, four = runs.get(("particles", 1)), runs.get(("particles", 4))
    base = runs.get(("baseline", 1))
    if one and four:
        ratio = four["ranks"][0]["peak"] / one["ranks"][0]["peak"]
        lines += [f"- Rank 0 at P = 4 peaks at {ratio:.2f} times its peak at P = 1 (target at most 0.4: "
                      f"{'met' if ratio <= 0.4 else 'not met'})."]
        if base:
            data = one["ranks"][0]["peak"] - base["ranks"][0]["peak"]
            lines.append(f"- The baseline run peaks at {base['ranks'][0]['peak'] / 2 ** 20:.0f} MiB at P = 1; the run "
                         f"of {one['N_max']:,} particles adds {data / 2 ** 20:.0f} MiB to it "
                         f"({data / one['N_max']:.0f} bytes per particle at its largest), so the particle data is "
                         f"{data / one['ranks'][0]['peak']:.0%} of rank 0's peak at P = 1. (Without particle data a rank "
                         "peaks in the mass integral, its 301^2 mesh points interpolated 16,384 at a time and shared "
                         "out over the ranks, and rank 0 in the figure, drawn with matplotlib.)")
            fixed = runs.get(("baseline", 4), base)["ranks"][0]["peak"]
            share = (four["ranks"][0]["peak"] - fixed) / data
            lines.append(f"- What the target needs: rank 0 at P = 4 at most {0.4 * one['ranks'][0]['peak'] / 2 ** 20:.0f} "
                         f"MiB, and its baseline run alone peaks at {fixed / 2 ** 20:.0f} MiB. Its particle data adds "
                         f"{share:.2f} times what the one process's adds (rank 0 holds about a quarter of the particles, "
                         "and ghosts). " + (
                             f"At that share the target is met where the particles add at least "
                             f"{(fixed - 0.4 * base['ranks'][0]['peak']) / (0.4 - share) / 2 ** 20:.0f} MiB at P = 1."
                             if share < 0.4 else "At that share no size meets it."))
    return lines


def launch(parts: int, calls: list[list[str]], timeout: float = 7200, python: str = sys.executable) -> list[Any]:
    """This script under one ``mpiexec -n parts`` (ranks bound to cores, one OpenMP thread each)
    running the workers ``calls`` (their arguments) one after the other, with the interpreter ``python``
    (and the arpy it imports; default this one); the JSON rank 0 printed for each.  mpiexec runs in a
    process group of its own, ended with its ranks on a timeout or when this script is interrupted or
    terminated (:func:`arpy._bench.run_process_group`)."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [mpiexec(python), "-n", str(parts), "-bind-to", "core", python, str(Path(__file__).resolve()),
           "--workers", json.dumps(calls)]
    out = run_process_group(cmd, timeout, env=env)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout)


def workers(calls: list[list[str]]) -> None:
    """Run the workers ``calls`` in this process one after the other; rank 0 prints the list of their
    JSON records (each worker prints its own on rank 0 only)."""
    import contextlib
    import io

    printed = []
    for call in calls:
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            main(call)
        printed.append(buf.getvalue())
    if all(printed):
        json.dump([json.loads(p) for p in printed], sys.stdout)


def mpiexec(python: str = sys.executable) -> str:
    local = Path(python).parent / "mpiexec"
    return str(local) if local.exists() else "mpiexec"


def fixed_step(rec: dict, d: int, parts: int) -> dict:
    """The fixed-particle step's record from the JSON rank 0 printed (``--worker d n_side``)."""
    ranks = rec["ranks"]
    return {"d": d, "n": rec["n"], "parts": parts, "digest": rec["field_digest"],
            "phases": {ph: max(r["t"][ph] for r in ranks) for ph in PHASES},
            "owned": [r["owned"] for r in ranks], "ghosts": [r["ghosts"] for r in ranks],
            "bytes_build": [r["bytes_build"] for r in ranks], "bytes_apply": [r["bytes_apply"] for r in ranks]}


def organized_record(rec: dict, D0: float, parts: int) -> dict:
    """The distributed self-organization's record (``--worker-organize D0``)."""
    ranks = rec["ranks"]
    return {"D0": D0, "parts": parts, "n": rec["n"], "iterations": rec["iterations"], "converged": rec["converged"],
            "digest": rec["digest"], "total": max(r["total"] for r in ranks),
            "phases": {p: max(r["phases"][p] for r in ranks) for p in SO_PHASES},
            "owned": [r["owned"] for r in ranks]}


def balance(r: dict) -> dict[str, Any]:
    """A whole-pulse record's balance per phase (:data:`RUN_PARTS`): each rank's compute CPU seconds and
    waiting, the imbalance (the largest rank's compute CPU over the mean), and the largest rank's
    waiting over its wall time."""
    out: dict[str, Any] = {"waiting": max(q["idle"] / q["wall"] for q in r["per_rank"]), "phases": {}}
    for part in RUN_PARTS:
        cpu = [q["parts"][part][1] for q in r["per_rank"]]
        if sum(cpu) > 0.01 * r["parts"]:
            out["phases"][part] = {"cpu": cpu, "waiting": [q["parts"][part][2] for q in r["per_rank"]],
                                   "imbalance": max(cpu) / (sum(cpu) / len(cpu))}
    return out


def _runs(r: dict, key: str, scale: float = 1.0, unit: str = "s", digits: int = 2) -> str:
    """'runs a, b, c s': ``key`` (times ``scale``) of each of a record's repeated runs (:func:`run_pulses`),
    or '' for one run."""
    runs = r.get("repeats", [])
    if len(runs) < 2:
        return ""
    return "runs " + ", ".join(f"{scale * q[key]:.{digits}f}" for q in runs) + f" {unit}"


def balance_lines(pulse: list[dict], before: list[dict], baseline: str = "?", floor: dict | None = None) -> list[str]:
    """The page's table of the balance per phase of the whole pulse on several ranks (:func:`balance`),
    this build's (now) and, when measured, the ``before`` build's (revision ``baseline``) side by side;
    with the waiting of the same work on each rank (:func:`worker_floor`'s record) when measured."""
    rows = [(b, r) for b, recs in (("before", before), ("now", pulse)) for r in recs
            if r["parts"] > 1 and all("parts" in q for q in r["per_rank"])]
    ones = [(b, r) for b, recs in (("before", before), ("now", pulse)) for r in recs if r["parts"] == 1]
    if not rows:
        return []
    lines = ["", "Balance per phase (`TimedComm` attributes each stretch of compute to the phase that calls the "
             "next exchange): each rank's compute CPU seconds, the imbalance (the largest over the mean) and each "
             "rank's waiting at the phase's exchanges. Build: `now` this one (boxes cut by the measured cost of the "
             "particles outside the shared phases, `arpy.distributed.balance`; the self-organization's insertion "
             "scoring, grade and interpolation of the sampled resolution shared between the ranks by their measured "
             "cost, `arpy.distributed.share`)"
             + (f", `before` the build of `--baseline` (revision {baseline}), each of its runs beside the same "
                "run of this one" if before else "") + "."
             + (f" Each run was made {len(pulse[0]['repeats'])} times, the two builds in turn; the table and the "
                "figures are those of the run of the median wall time, and the lines below give every run's wall "
                "time and waiting." if len(pulse[0].get("repeats", [])) > 1 else ""), "",
             "| d | P | build | phase | compute CPU per rank [s] | imbalance | waiting per rank [s] |",
             "|---|---|---|---|---|---|---|"]
    for b, r in sorted(rows, key=lambda br: (br[1].get("d", 2), br[1]["parts"], br[0] != "before")):
        bal = balance(r)
        for part, ph in bal["phases"].items():
            lines.append(f"| {r.get('d', 2)} | {r['parts']} | {b} | {part} | " + ", ".join(f"{c:.2f}" for c in ph["cpu"])
                         + f" | {ph['imbalance']:.3f} | " + ", ".join(f"{w:.2f}" for w in ph["waiting"]) + " |")
    lines.append("")
    if before:
        lines += [f"- {r.get('d', 2)}D, P = 1, {b}: wall {r['wall']:.2f} s" + (f" ({_runs(r, 'wall')})" if _runs(r, "wall")
                                                                              else "") + "." for b, r in ones]
    for b, r in rows:
        bal = balance(r)
        cpu = [sum(q["parts"][p][1] for p in RUN_PARTS) for q in r["per_rank"]]
        imbalance = max(cpu) / (sum(cpu) / len(cpu))
        if r["parts"] <= 2:
            same = (floor or {}).get(str(r.get("d", 2)))
            target = (f"target 5 %: {'met' if bal['waiting'] <= 0.05 else 'not met'}"
                      + (f"; the same work on each rank waits up to "
                         f"{100 * max(q['idle'] / q['wall'] for q in same['ranks']):.1f} % here, see the floor below"
                         if same else ""))
        else:
            target = (f"oversubscribed: no measure; target a compute imbalance of at most 1.05: "
                      f"{'met' if imbalance <= 1.05 else 'not met'}")
        walls, waits = _runs(r, "wall"), _runs(r, "waiting", 100.0, "%", 1)
        lines.append(f"- {r.get('d', 2)}D, P = {r['parts']}, {b}: wall {r['wall']:.2f} s" + (f" ({walls})" if walls else "")
                     + f"; waiting at most {100 * bal['waiting']:.1f} % of a rank's wall time ("
                     + (f"{waits}; " if waits else "") + f"{target}); "
                     f"compute CPU per rank " + ", ".join(f"{c:.1f}" for c in cpu) + f" s, imbalance {imbalance:.3f}.")
    return lines


def report(res: dict) -> str:
    """The Markdown page of a result (results/distributed.md is this of results/distributed.json)."""
    lines = ["# Distributed fixed-particle step (arpy.distributed), P = 1 against 2", "",
             "A jittered lattice in the periodic unit square (2D) or cube (3D), core size 3.3 (2D) or 2.3 (3D) "
             "spacings, the particles dealt to the ranks at random; per rank: bisection, migration to the owners, "
             f"the ghost exchange with the DC-PSE Laplacian over own particles and ghosts (build), and {APPLY} "
             "applications with a ghost refresh each (apply). Times are the slowest rank's, in seconds, one "
             "OpenMP thread per rank, ranks bound to cores, each P in its own mpiexec.", "",
             "    python benchmarks/distributed.py           # 2D N = 1e6, 3D N = 2e5",
             "    python benchmarks/distributed.py --quick   # small sizes, seconds", "",
             "P = 4 runs on the two cores of this machine (four ranks, oversubscribed): its times say nothing "
             "about speed, its field is compared with P = 1. Bytes: what the slowest rank sends to the others "
             "per step (a ghost's position, core size and key at the build, its value at each application).", "",
             "| d | N | P | bisect | migrate | build | apply | total | speed-up | ghosts / owned | imbalance | "
             "MB sent per step | field as at P = 1 |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for d in sorted({r["d"] for r in res["runs"]}):
        rows = sorted((r for r in res["runs"] if r["d"] == d), key=lambda r: r["parts"])
        base = sum(rows[0]["phases"].values())
        for r in rows:
            total = sum(r["phases"].values())
            ghosts = sum(r["ghosts"]) / sum(r["owned"])
            imb = max(r["owned"]) / (sum(r["owned"]) / r["parts"])
            sent = max(b + APPLY * a for b, a in zip(r["bytes_build"], r["bytes_apply"])) / 1e6
            speed = f"{base / total:.2f}" if r["parts"] <= 2 else "(oversubscribed)"
            lines.append(f"| {d} | {r['n']:,} | {r['parts']} | " + " | ".join(f"{r['phases'][p]:.3f}" for p in PHASES)
                         + f" | {total:.3f} | {speed} | {ghosts:.3f} | {imb:.3f} | {sent:.2f} | "
                         + ("yes" if r["digest"] == rows[0]["digest"] else "NO") + " |")
    lines += ["", "## Findings", ""]
    for d in sorted({r["d"] for r in res["runs"]}):
        rows = sorted((r for r in res["runs"] if r["d"] == d and r["parts"] <= 2), key=lambda r: r["parts"])
        if len(rows) > 1:
            s = sum(rows[0]["phases"].values()) / sum(rows[-1]["phases"].values())
            build = rows[0]["phases"]["build"] / rows[-1]["phases"]["build"]
            lines.append(f"- {d}D, N = {rows[0]['n']:,}: P = {rows[-1]['parts']} is {s:.2f} times as fast as P = 1 "
                         f"(target 1.6: {'met' if s >= 1.6 else 'not met'}); the build alone {build:.2f} times.")
        one = next(r for r in res["runs"] if r["d"] == d and r["parts"] == 1)
        lines.append(f"- {d}D: ghosts per owned particle at P = 1 (the periodic images of the whole box, a cube of "
                     f"{one['n']:,}) {sum(one['ghosts']) / one['n']:.4f}; the cube model below gives "
                     f"{ghost_ratio(one['n'], d):.4f}.")
    comm = res.get("comm")
    if comm:
        kinds = (("alltoall", "`MPIComm.alltoall` of NumPy arrays, pickled, one message to every rank (the "
                              "exchange of the ghosts before)"),
                 ("exchange", "`MPIComm.exchange`, the arrays' bytes to the ranks that need them (a ghost "
                              "refresh now)"))
        lines += ["", "## Communication cost and a model for 64 and 1024 ranks", "",
                  f"One exchange as arpy makes it between {comm['parts']} ranks of this machine (shared memory), "
                  "median seconds per call by bytes per message:", "",
                  "| exchange | " + " | ".join(f"{int(b):,} B" for b in comm["exchange"]["seconds"]) + " | alpha [µs] "
                  "| beta [ns/B] |", "|---|" + "---|" * (len(comm["exchange"]["seconds"]) + 2)]
        for kind, what in kinds:
            c = comm[kind]
            lines.append(f"| {what} | " + " | ".join(f"{1e6 * v:.1f} µs" for v in c["seconds"].values())
                         + f" | {1e6 * c['alpha']:.1f} | {1e9 * c['beta']:.3f} |")
        lines += ["", "alpha and beta: the fit t = alpha + beta bytes.", "",
                  f"The model (`model()`): N = 1e8 particles of the same lattices, n = N / P per rank in a cubic box, "
                  f"ghosts per owned particle (1 + 2a / n^(1/d))^d - 1 (a = {CORE[2]} in 2D, {CORE[3]} in 3D: "
                  "checked against P = 1 above), the compute of the measured P = 1 step per owned particle (less "
                  "its ghosts' share) times (1 + r ghosts / owned), r the cost of a ghost against an owned particle "
                  "measured below (1 where it was not), and the exchanges of a step with the ghosts' bytes: "
                  "alltoall, as before, "
                  f"1 + {APPLY} pickled all-to-alls of P messages; neighbours, as arpy exchanges now, the set-up's "
                  f"pickled messages and {APPLY} refreshes of buffers, each 3^d - 1 messages (to the neighbouring "
                  "boxes), at the alphas and betas above (between machines beta is larger; the set-up's "
                  "non-blocking barrier, log P rounds of empty messages, is left out).", ""]
        cost = res.get("ghost_cost")
        if cost:
            lines += ["What a ghost costs (`ghost_cost()`, one process, the best of 5, on lattices small enough that "
                      "the ghosts are a good part of the sources): the step's build with its "
                      f"ghost layer and with a layer {GHOST_SKIN:g} core sizes wider (the same rows, more ghosts), and "
                      f"the {APPLY} applications. A ghost is a source, never a row: it costs its exchange, its place "
                      "in the cells and the pairs it is tested in, not the assembly of a row. Per ghost: the build's "
                      "growth over the ghosts added; per owned particle: the step less its ghosts' share.", "",
                      "| d | N | ghosts (layer, wider) | build [s] (layer, wider) | apply [s] | per owned [µs] | "
                      "per ghost [µs] | r = ghost / owned |", "|---|---|---|---|---|---|---|---|"]
            for d in sorted(cost, key=int):
                c = cost[d]
                lines.append(f"| {c['d']} | {c['n']:,} | {c['ghosts'][0]:,}, {c['ghosts'][1]:,} | "
                             f"{c['build'][0]:.3f}, {c['build'][1]:.3f} | {c['apply']:.3f} | "
                             f"{1e6 * c['per_owned']:.2f} | {1e6 * c['per_ghost']:.2f} | {c['ratio']:.3f} |")
            lines.append("")
        lines += ["| d | P | n per rank | ghosts / owned | compute [s] | exchange | communication [s] | efficiency |",
                  "|---|---|---|---|---|---|---|---|"]
        for m in model(res):
            lines.append(f"| {m['d']} | {m['P']} | {m['n']:,.0f} | {m['ghosts']:.3f} | {m['compute']:.2f} | "
                         f"{m['exchange']} | {m['comm']:.4f} | {m['efficiency']:.2f} |")
        lines.append("")
        rows = model(res)
        for m in (m for m in rows if m["exchange"] == "alltoall"):
            nb = next(q for q in rows if q["exchange"] == "neighbours" and q["d"] == m["d"] and q["P"] == m["P"])
            lines.append(f"- {m['d']}D, P = {m['P']}: efficiency {m['efficiency']:.2f} with the all-to-all exchanges, "
                         f"{nb['efficiency']:.2f} with today's between neighbouring boxes only; the ghosts add "
                         f"{100 * m['ghost_cost'] * m['ghosts']:.0f} % to the compute, the messages "
                         f"{100 * m['comm'] / m['compute']:.0f} % "
                         f"(neighbours only: {100 * nb['comm'] / nb['compute']:.0f} %).")
    organize = sorted(res.get("organize", []), key=lambda r: r["parts"])
    if organize:
        lines += ["", "## Self-organization on the ranks", "",
                  "The start of the Sec. 4.3 pulse (800 random particles between walls, the monitor of Eq. 2.8, "
                  f"D0 = {organize[0]['D0']}) adapted by `arpy.self_organize(comm=)`, the particles dealt to "
                  "the ranks by key. Times in seconds, the slowest rank's; the phases are the log's, summed over "
                  "the iterations (forces: the descent and the scan, with their exchanges).", "",
                  "| P | N | iterations | fuse + insert | resolution | lists | forces | total | speed-up | "
                  "imbalance | particles as at P = 1 |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in organize:
            imb = max(r["owned"]) / (sum(r["owned"]) / r["parts"])
            lines.append(f"| {r['parts']} | {r['n']:,} | {r['iterations']} | "
                         + " | ".join(f"{r['phases'][p]:.2f}" for p in SO_PHASES)
                         + f" | {r['total']:.2f} | {organize[0]['total'] / r['total']:.2f} | {imb:.3f} | "
                         + ("yes" if r["digest"] == organize[0]["digest"] else "NO") + " |")
    pulse = sorted(res.get("pulse", []), key=lambda r: (r.get("d", 2), r["parts"]))
    if pulse:
        lines += ["", "## A whole adaptive simulation on the ranks", "",
                  "The Sec. 4.3 pulse (`gaussian_pulse`, forward Euler; 2D Pe = 1000, 3D Pe = 100) run by "
                  "`Simulation(comm=...)`: the initial self-organization, the steps and the re-organizations "
                  "(monitor, self-organization, old -> new) on the ranks. Seconds, the slowest rank's; the phases "
                  "are the log's, summed over the steps; wall: the whole run, the initial self-organization and "
                  "the mass integrals included. Imbalance: the largest rank's particle count at T over the mean."
                  + (f" Each run was made {len(pulse[0]['repeats'])} times (`--repeat`): the run of the median wall "
                     "time is shown, every run's wall time is in the lines below the balance per phase."
                     if len(pulse[0].get("repeats", [])) > 1 else ""),
                  "", "| d | D0 | T | P | N_max | steps | re-organizations | monitor | SO lists | SO rest | interp. | "
                  "rhs | steps | wall | speed-up | imbalance | error | as at P = 1 |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        first = {r.get("d", 2): r for r in reversed(pulse)}
        for r in pulse:
            p0 = first[r.get("d", 2)]
            imb = max(r["owned"]) / (sum(r["owned"]) / r["parts"])
            lines.append(f"| {r.get('d', 2)} | {r['D0']} | {r['T']} | {r['parts']} | {r['N_max']:,} | {r['steps']} | "
                         f"{r['reorganizations']} | "
                         + " | ".join(f"{r['phases'][p]:.2f}" for p in (*RUN_PHASES, "steps"))
                         + f" | {r['wall']:.2f} | "
                         + (f"{p0['wall'] / r['wall']:.2f}" if r["parts"] <= 2 else "(oversubscribed)")
                         + f" | {imb:.3f} | {r['error']:.3e} | "
                         + ("yes" if (r["error"], r["N"]) == (p0["error"], p0["N"]) else "NO") + " |")
        timed = [r for r in pulse if r.get("per_rank")]
        if timed:
            lines += ["", "Per rank: compute (the wall time outside collectives), waiting for the other ranks (a "
                          "barrier before each collective) and transferring (the collective itself), seconds; the "
                          "compute imbalance is the largest rank's compute over the mean.", "",
                      "| d | P | rank | particles at T | compute | waiting | transferring | compute imbalance |",
                      "|---|---|---|---|---|---|---|---|"]
            for r in timed:
                comp = [q["wall"] - q["idle"] - q["transfer"] for q in r["per_rank"]]
                for i, q in enumerate(r["per_rank"]):
                    lines.append(f"| {r.get('d', 2)} | {r['parts']} | {i} | {q['owned']:,} | {comp[i]:.2f} | "
                                 f"{q['idle']:.2f} | {q['transfer']:.2f} | "
                                 + (f"{max(comp) / (sum(comp) / len(comp)):.3f}" if i == 0 else "") + " |")
        lines += balance_lines(pulse, res.get("pulse_before", []), res.get("baseline", "?"), res.get("floor"))
        lines.append("")
        for d in sorted(first):
            p0, last = first[d], [r for r in pulse if r.get("d", 2) == d and r["parts"] <= 2][-1]
            if last is p0:
                continue
            lines.append(f"- {d}D: P = {last['parts']} runs the whole simulation {p0['wall'] / last['wall']:.2f} times "
                         f"as fast as P = 1 (target 1.5: {'met' if p0['wall'] / last['wall'] >= 1.5 else 'not met'}); "
                         f"the steps alone {p0['phases']['steps'] / last['phases']['steps']:.2f} times.")
    if res.get("floor"):
        lines += floor_lines(res["floor"])
    if "memory" in res:
        lines += memory_lines(res["memory"])
    lines += ["", f"Run of {res['date']} on {res['machine']}, Python {res['python']}, {res['mpi']}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--workers"]:
        workers(json.loads(argv[1]))
        return 0
    if argv[:1] == ["--worker"]:
        worker(int(argv[1]), int(argv[2]))
        return 0
    if argv[:1] == ["--worker-organize"]:
        worker_organize(float(argv[1]))
        return 0
    if argv[:1] == ["--worker-pulse"]:
        worker_pulse(int(argv[1]), float(argv[2]), float(argv[3]), int(argv[4]), int(argv[5]))
        return 0
    if argv[:1] == ["--worker-memory"]:
        worker_memory(json.loads(argv[1]))
        return 0
    if argv[:1] == ["--worker-floor"]:
        worker_floor(bool(int(argv[1])))
        return 0
    if argv[:1] == ["--worker-comm"]:
        worker_comm(bool(int(argv[1])))
        return 0
    from arpy._bench import benchmark_args, write_page

    def extra(parser):
        parser.add_argument("--only-pulse", action="store_true",
                            help="measure the whole simulation again, the rest of the JSON kept")
        parser.add_argument("--only-comm", action="store_true",
                            help="measure the exchanges again (P = 2), the rest of the JSON kept")
        parser.add_argument("--repeat", type=int, default=3, metavar="R",
                            help="with --only-pulse: make each run R times (the median wall time's run is shown, "
                                 "with every run's wall time and waiting; default 3)")
        parser.add_argument("--only-floor", action="store_true",
                            help="measure the waiting of the same work on both ranks (P = 2) again, the rest of "
                                 "the JSON kept")
        parser.add_argument("--only-ghosts", action="store_true",
                            help="measure what a ghost costs again (one process), the rest of the JSON kept")
        parser.add_argument("--memory", action="store_true",
                            help="measure the peak memory per rank of arpy run pulse with checkpoints at P = 1 and "
                                 "4 again, the rest of the JSON kept (full size: about 50 min on 2 cores)")
        parser.add_argument("--baseline", metavar="PYTHON",
                            help="also run the whole pulse with this interpreter (another build of arpy, e.g. "
                                 "/work/main/.venv/bin/python) for the per-phase balance before and after")

    args = benchmark_args(__doc__, argv, HERE / "results", extra)

    tag = "distributed" + ("_quick" if args.quick else "")
    path = args.out / f"{tag}.json"

    def again(measure: Callable[[], dict[str, Any]], drop: tuple[str, ...] = ()) -> dict[str, Any]:
        """The results of the JSON (read first: they must exist) with the parts ``measure()`` returns
        measured again and those of ``drop`` left out, written back with the page."""
        res = json.loads(path.read_text())
        for key in drop:
            res.pop(key, None)
        res.update(measure())
        path.write_text(json.dumps(res, indent=1))
        print(f"wrote {write_page(args.out, tag, report)}")
        return res

    if args.memory:
        import tempfile

        def memory() -> dict[str, Any]:
            with tempfile.TemporaryDirectory() as tmp:
                return {"memory": memory_record(args.quick, Path(tmp))}

        again(memory)
        return 0
    if args.only_comm:
        again(lambda: {"comm": comm_record(launch(2, [comm_call(args.quick)])[0], 2)})
        return 0
    if args.only_floor:
        again(lambda: {"floor": launch(2, [["--worker-floor", str(int(args.quick))]])[0]})
        return 0
    sizes = {2: 100, 3: 20} if args.quick else {2: 1000, 3: 58}
    if args.only_ghosts:
        again(lambda: {"ghost_cost": ghost_costs(GHOST_SIDES[args.quick])})
        return 0
    ranks = (1, 2) if args.quick else (1, 2, 4)
    if args.only_pulse:
        def pulse() -> dict[str, Any]:
            if not args.baseline:
                return {"pulse": run_pulses(args.quick, ranks, repeat=args.repeat)[0]}
            now, before = run_pulses(args.quick, ranks, sys.executable, args.baseline, repeat=args.repeat)
            return {"pulse": now, "pulse_before": before, "baseline": revision(args.baseline)}

        res = again(pulse, drop=("pulse_before", "baseline"))
        return 0 if same_pulse(res["pulse"]) and same_pulse(res.get("pulse_before", [])) else 1
    D0 = 0.3 if args.quick else 0.02
    runs, organize, pulse, comm, floor = [], [], [], {}, {}
    # per P: the fixed-particle steps, then (P = 1, 2) the self-organization and the whole pulse, and
    # (P = 2) the exchange costs
    for parts in (1, 2) if args.quick else (1, 2, 4):
        calls = [["--worker", str(d), str(n_side)] for d, n_side in sizes.items()]
        if parts <= 2:
            calls += [["--worker-organize", repr(D0)], *pulse_calls(args.quick)]
        if parts == 2:
            calls += [comm_call(args.quick), ["--worker-floor", str(int(args.quick))]]
        # quick (the tests): one mpiexec for them all; full: one each, so that no measurement runs late
        # in a long process (measured: the 3D pulse at P = 2 computed 10 % slower after the others)
        recs = launch(parts, calls) if args.quick else [rec for call in calls for rec in launch(parts, [call])]
        for rec, d in zip(recs, sizes):
            runs.append(fixed_step(rec, d, parts))
            r = runs[-1]
            print(f"{d}D N = {r['n']:,} P = {parts}: " + ", ".join(f"{p} {r['phases'][p]:.3f} s" for p in PHASES)
                  + f"; ghosts {sum(r['ghosts'])}", flush=True)
        if parts <= 2:
            organize.append(organized_record(recs[len(sizes)], D0, parts))
            r = organize[-1]
            print(f"self-organization D0 = {D0} P = {parts}: N = {r['n']:,}, {r['iterations']} iterations, "
                  f"{r['total']:.2f} s", flush=True)
            pulse += pulse_records(recs[len(sizes) + 1: len(sizes) + 1 + len(PULSE_RUNS[args.quick])], args.quick,
                                   parts)
        if parts == 2:
            comm, floor = comm_record(recs[-2], parts), recs[-1]
    pulse += run_pulses(args.quick, [p for p in ranks if p > 2], warm=False)[0]
    runs.sort(key=lambda r: (r["d"], r["parts"]))
    from mpi4py import MPI

    res = {"machine": platform.platform(), "python": sys.version.split()[0], "date": time.strftime("%Y-%m-%d"),
           "mpi": MPI.Get_library_version().splitlines()[0].strip(), "quick": args.quick, "runs": runs,
           "organize": organize, "comm": comm, "pulse": pulse, "floor": floor,
           "ghost_cost": ghost_costs(GHOST_SIDES[args.quick])}
    if args.baseline:
        res["pulse_before"], = run_pulses(args.quick, ranks, args.baseline, warm=False)
        res["baseline"] = revision(args.baseline)
    if path.is_file():       # (the memory runs are measured by --memory alone)
        kept = json.loads(path.read_text()).get("memory")
        if kept:
            res["memory"] = kept
    path.write_text(json.dumps(res, indent=1))
    print(f"wrote {write_page(args.out, tag, report)}")
    same = all(r["digest"] == next(q for q in runs if q["d"] == r["d"])["digest"] for r in runs) and all(
        r["digest"] == organize[0]["digest"] for r in organize) and same_pulse(pulse) and same_pulse(
        res.get("pulse_before", []))
    return 0 if same else 1

if __name__ == "__main__":
    sys.exit(main())
