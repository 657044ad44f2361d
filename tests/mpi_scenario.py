"""Run under ``mpiexec -n P`` by tests/test_mpi.py: the particles of a seeded set are dealt to the ranks
at random; the ranks bisect, migrate and exchange ghosts through MPI; rank 0 prints, as JSON, the boxes,
every rank's keys and every owned particle's neighbour row (as keys) from its lists over own + ghosts;
then fixed-particle diffusion, 20 steps of moving particles (Simulation(comm=)), the
self-organization of the pulse start and RK4 on fixed particles with reused lists (verlet_skin),
gathered by key; and, given a folder, ``arpy run manufactured`` (Dirichlet walls) into it.  ``mpi_scenario.py MODE`` (one of
:data:`FAILURES`) instead makes one rank fail while the others wait in a collective; ``mpi_scenario.py
cases OUT RUNS`` runs several ``arpy run`` cases in one launch."""

import json
import sys

import numpy as np

import arpy
from arpy.distributed import Laplacian, MPIComm, bisect, exchange_ghosts, gather, migrate
from test_distributed import diffuse, lattice, moving_run
from test_one_path import shifted_run, shifted_set


def scenario(seed: int, periodic: bool):
    """The particle set of a run: positions, cutoffs, keys and the domain (the same on every rank)."""
    rng = np.random.default_rng(seed)
    x = rng.random((2000, 2))
    rc = 0.01 * np.exp(rng.uniform(0, np.log(10), len(x)))
    keys = rng.permutation(len(x)).astype(np.int64) * 5 + 1
    box = arpy.Domain([1.0, 1.0], periodic=periodic)
    return x, rc, keys, box


def run(comm: MPIComm, seed: int, periodic: bool) -> dict | None:
    """One scenario on the ranks of comm; rank 0 gets the record."""
    x, rc, keys, box = scenario(seed, periodic)
    mine = np.random.default_rng(seed + 1).integers(0, comm.size, len(x)) == comm.rank
    dec, _ = bisect(x[mine], comm.size, domain=box, comm=comm)
    xs, ks, f = migrate(comm, dec, x[mine], keys[mine], {"rc": rc[mine]})
    layer = exchange_ghosts(comm, dec, xs, f["rc"], ks, domain=box if periodic else None)
    xg, rg, kg = layer.x, layer.rc, layer.keys
    before = comm.messages
    refreshed = layer.refresh(comm, f["rc"])                # (one refresh: its messages, its values)
    sent = comm.messages - before
    assert refreshed.tobytes() == rg.tobytes()
    nl = arpy.neighbor_list(np.concatenate([xs, xg]), np.concatenate([f["rc"], rg]), full=True)
    kall = np.concatenate([ks, kg])
    rows = {int(ks[p]): np.sort(kall[nl.neighbors(p)]).tolist() for p in range(len(ks))}
    gathered = comm.allgather((ks.tolist(), rows, sent))
    if comm.rank != 0:
        return None
    return {"lo": dec.lo.tolist(), "hi": dec.hi.tolist(), "keys": [g[0] for g in gathered],
            "rows": {k: v for g in gathered for k, v in g[1].items()}, "sent": [g[2] for g in gathered]}


def diffusion(comm: MPIComm) -> dict | None:
    """20 forward-Euler steps of df/dt = nu lap f on the fixed particles of the jittered 40 x 40 lattice
    (tests/test_distributed.py); rank 0 gets f by key (as exact decimal strings of the doubles)."""
    x, eps, keys, rng = lattice(40)
    deal = rng.integers(0, 4, len(x)) % comm.size
    box = arpy.Domain([1.0, 1.0], periodic=True)
    mine = deal == comm.rank
    dec, _ = bisect(x[mine], comm.size, domain=box, comm=comm)
    xs, ks, fl = migrate(comm, dec, x[mine], keys[mine], {"eps": eps[mine]})
    f = diffuse(comm, Laplacian(comm, dec, xs, fl["eps"], ks, domain=box), xs)
    gathered = comm.allgather({int(k): float(v).hex() for k, v in zip(ks, f)})
    return {k: v for g in gathered for k, v in g.items()} if comm.rank == 0 else None


def pulse_start():
    """The start of the §4.3 pulse: 800 random particles between walls and the gradient of
    the pulse (for the monitor of Eq. 2.8)."""
    from arpy.cases.pulse import pulse_setup

    x = np.random.default_rng(1).uniform(-1, 1, (800, 2))
    return x, arpy.Domain(([-1.0, -1.0], [1.0, 1.0])), pulse_setup(2, 1000.0)["grad0"]


def organize(comm: MPIComm) -> dict | None:
    """The distributed self-organization of the pulse start (keys = input order, dealt at random);
    rank 0 gets x and D by key (exact hex strings)."""
    x, box, grad = pulse_start()
    keys = np.arange(len(x), dtype=np.int64)
    mine = np.random.default_rng(comm.size).integers(0, comm.size, len(x)) == comm.rank
    dec, _ = bisect(x[mine], comm.size, domain=box, comm=comm)
    xs, ks, _ = migrate(comm, dec, x[mine], keys[mine])
    out = arpy.self_organize(xs, grad_f=grad, D0=0.3, domain=box, seed=1, comm=comm, keys=ks, decomposition=dec)
    k, xg, Dg = gather(comm, out.keys, out.x, out.D)
    return {int(a): [float(v).hex() for v in (*p, d)] for a, p, d in zip(k, xg, Dg)} if comm.rank == 0 else None


def advection(comm: MPIComm) -> dict | None:
    """20 forward-Euler steps of Simulation(comm=) without re-organization (moving particles,
    tests/test_distributed.py's moving_run); rank 0 gets x and f by key (exact hex strings)."""
    x, eps, keys, _ = lattice(30)
    ks, xs, fs = moving_run(comm, "euler", x, eps, keys, steps=20)
    return ({int(k): [float(v).hex() for v in (*p, f)] for k, p, f in zip(ks, xs, fs)} if comm.rank == 0
            else None)


def shifted(comm: MPIComm, organized: arpy.Particles) -> dict | None:
    """RK4 with re-organizations every 3 steps on a box whose lower corner is not 0 (periodic x in
    [-1, 2], walls in y; tests/test_one_path.py's set, ``organized``); rank 0 gets x, D and f by key
    (exact hex strings)."""
    (k, x, D, F), _ = shifted_run(organized, comm, "rk4", 3)
    return ({int(a): [float(v).hex() for v in (*p, d, f)] for a, p, d, f in zip(k, x, D, F[:, 0])}
            if comm.rank == 0 else None)


def kept(comm: MPIComm, organized: arpy.Particles) -> dict | None:
    """RK4 on the fixed particles ``organized`` (reorganize_every=0) with verlet_skin=0.3 on the box of
    :func:`shifted` (particles cross the periodic faces and change rank); rank 0 gets x and f by key
    (exact hex strings)."""
    (k, x, _, F), _ = shifted_run(organized, comm, "rk4", 0, verlet_skin=0.3)
    return {int(a): [float(v).hex() for v in (*p, f)] for a, p, f in zip(k, x, F[:, 0])} if comm.rank == 0 else None


#: ``arpy run manufactured`` of :func:`manufactured` (Dirichlet walls): its options.
MANUFACTURED = ["--D0", "0.12", "--walls", "mixed", "--T", "0.05", "--k", "2"]


def printed_by(case: str, options: list[str], out: str) -> dict | None:
    """``arpy run CASE OPTIONS --quiet --json --out OUT`` on these ranks: the JSON it printed (rank 0),
    None on the other ranks (they print nothing)."""
    import contextlib
    import io

    from arpy.cli import main

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        status = main(["run", case, *options, "--quiet", "--json", "--out", out])
    assert status == 0, (case, status)
    return json.loads(printed.getvalue()) if printed.getvalue() else None


def manufactured(comm: MPIComm, out: str) -> dict | None:
    """``arpy run manufactured`` (u held on every wall, v given its fluxes) on these ranks, writing into
    ``out``; rank 0 gets the JSON it prints, with ``initial``: each rank's count of the initial set it
    self-organized and kept, and the whole set's N, [[n, N] per rank]."""
    import arpy.cases.reaction_diffusion as case

    organize, sizes = case.self_organize, []

    def recorded(*args, **kwargs):
        ps = organize(*args, **kwargs)
        sizes.append([ps.n, ps.total(ps.n)])
        return ps

    case.self_organize = recorded
    try:
        printed = printed_by("manufactured", MANUFACTURED, out)
    finally:
        case.self_organize = organize
    initial = [s for got in comm.allgather(sizes) for s in got]
    return {**printed, "initial": initial} if printed else None


def cases_run(out: str, runs: dict[str, list[str]]) -> dict | None:
    """``arpy run CASE OPTIONS`` for each ``CASE: OPTIONS`` of runs, one after the other in this launch,
    writing into ``out``; rank 0 gets what each printed ({case: JSON}), and as ``matplotlib`` whether
    each rank had imported matplotlib by the end."""
    printed = {case: printed_by(case, options, out) for case, options in runs.items()}
    loaded = MPIComm().allgather("matplotlib" in sys.modules)
    return {**printed, "matplotlib": loaded} if all(v is not None for v in printed.values()) else None


def reduction_values(rank: int) -> tuple[np.ndarray, int, np.ndarray]:
    """Rank ``rank``'s values for the reductions of :func:`reductions`: doubles (2, 4) with zeros of
    either sign, infinities, a NaN on rank 1 only, and ties; an integer; an int64 array."""
    v = np.array([[0.0 if rank % 2 else -0.0, 1.5 - rank, -np.inf if rank == 2 else 1e300, 7.0],
                  [np.nan if rank == 1 else 2.0 * rank, -0.0, 5e-324 * rank, -7.0]])
    return v, 10 ** 12 + rank, np.array([rank, -3 * rank, 2 ** 40], np.int64)


def reductions(comm: MPIComm) -> dict | None:
    """min, max, sum and add over the ranks of :func:`reduction_values` (MPI_Allreduce), and the first r
    columns of rank r's doubles gathered (MPI_Allgatherv), and numbers sent to every rank (MPI_Alltoallv);
    rank 0 gets what every rank got, the doubles as hex strings (their bits)."""
    v, i, a = reduction_values(comm.rank)
    cat, at = comm.gather_arrays(v[:, :comm.rank].ravel())          # (rank 0: none)
    # (to rank q: (rank + q) % 3 numbers 100 rank + q)
    counts = np.array([(comm.rank + q) % 3 for q in range(comm.size)], np.int64)
    came, sizes = comm.alltoall_arrays(np.repeat(100 * comm.rank + np.arange(comm.size), counts), counts)
    got = [[float(x).hex() for x in comm.min(v).ravel()], [float(x).hex() for x in comm.max(v).ravel()],
           comm.sum(i), comm.add(a).tolist(), [float(x).hex() for x in cat], at.tolist(), came.tolist(),
           sizes.tolist()]
    every = comm.allgather(got)
    return {"every": every} if comm.rank == 0 else None


def fail(comm: MPIComm, mode: str) -> None:
    """One of :data:`FAILURES`; then every rank waits in a collective (for a rank that never comes)."""
    if mode == "disagree":                  # every rank raises, naming the D0 each was given
        x, box, grad = pulse_start()
        arpy.self_organize(x, grad_f=grad, D0=(0.3, 0.25)[comm.rank % 2], domain=box, seed=1, comm=comm)
    elif comm.rank == 0:
        if mode == "raise":
            raise RuntimeError("rank 0 fails on purpose")
        sys.exit(3)
    comm.allgather(None)


#: The failure modes of ``mpi_scenario.py MODE``: rank 0 raises, rank 0 calls sys.exit(3), or the ranks
#: are given different D0 for self_organize(comm=).
FAILURES = ("raise", "exit", "disagree")


def main() -> int:
    """``mpi_scenario.py SEED [OUT]``: the free and the periodic scenario and the diffusion run (with
    OUT, also ``arpy run manufactured`` into OUT); rank 0 prints the records.  ``mpi_scenario.py
    MODE``: the failure ``MODE`` (:data:`FAILURES`).  ``mpi_scenario.py cases OUT RUNS``: ``arpy run``
    of each case of the JSON object RUNS ({case: [options]}) into OUT; rank 0 prints {case: its JSON}."""
    if sys.argv[1] in FAILURES:
        fail(MPIComm(), sys.argv[1])
        return 0
    if sys.argv[1] == "cases":
        printed = cases_run(sys.argv[2], json.loads(sys.argv[3]))
        if printed is not None:
            json.dump(printed, sys.stdout)
        return 0
    seed, comm = int(sys.argv[1]), MPIComm()
    records = {kind: run(comm, seed, kind == "periodic") for kind in ("free", "periodic")}
    records["diffusion"] = diffusion(comm)
    records["advection"] = advection(comm)
    records["organize"] = organize(comm)
    organized = shifted_set()
    records["shifted"] = shifted(comm, organized)
    records["kept"] = kept(comm, organized)
    records["reductions"] = reductions(comm)
    if len(sys.argv) > 2:
        records["manufactured"] = manufactured(comm, sys.argv[2])
    if comm.rank == 0:
        json.dump(records, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
