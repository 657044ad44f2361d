"""Self-organizing particles on several MPI ranks: ``mpiexec -n 4 python mpi_self_organize.py``.

Every rank starts from the same seeded random particles, keeps those of its own box after the
decomposition, adapts them together with the other ranks, and writes its part of the result; rank 0
prints the totals.  It is the same ``arpy.self_organize`` as on one process, given the communicator,
this rank's particles and their global keys; the particles are bitwise the same for any number of
ranks, one process included.
"""

import numpy as np

import arpy
from arpy.cases.pulse import pulse_setup
from arpy.distributed import MPIComm, bisect, gather, migrate, write_pvtu

comm = MPIComm()
box = arpy.Domain(([-1.0, -1.0], [1.0, 1.0]))                 # walls
x = np.random.default_rng(1).uniform(-1, 1, (800, 2))       # the same on every rank
keys = np.arange(len(x), dtype=np.int64)                     # global particle keys
mine = np.arange(len(x)) % comm.size == comm.rank            # any deal will do
dec, _ = bisect(x[mine], comm.size, domain=box, comm=comm)   # boxes by recursive bisection
xs, ks, _ = migrate(comm, dec, x[mine], keys[mine])          # each particle to the rank owning it

out = arpy.self_organize(xs, grad_f=pulse_setup(2, 1000.0)["grad0"], D0=0.2, domain=box, seed=1,
                         comm=comm, keys=ks, decomposition=dec)  # this rank's share of the result

write_pvtu(comm, "pulse_particles.pvtu", out.x, D=out.D)    # one piece per rank, for ParaView
k, x_all, D_all = gather(comm, out.keys, out.x, out.D)      # (small runs) everything on every rank
if comm.rank == 0:
    print(f"{comm.size} ranks: {len(k)} particles after {len(out.log)} iterations, converged: {out.converged}, "
          f"D in [{D_all.min():.3g}, {D_all.max():.3g}]")
