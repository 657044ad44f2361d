"""Domain decomposition for distributed runs: recursive coordinate bisection and ghost layers of
per-particle width.

The pieces of an SPMD run (one process per rank, particles exchanged between ranks): which rank owns
each particle, which particles a rank needs besides its own, and the exchanges that move them, through
a communicator (:class:`Comm`; one process, MPI ranks, or threads standing for ranks).  Every public
name is importable from ``arpy.distributed``; by concept they live in:

* :mod:`~arpy.distributed.comm`: the communicators, :class:`SerialComm` (the serial path is the
  parallel path with P = 1), :class:`MPIComm` and :class:`ThreadComm` (:func:`run_threads`);
* :mod:`~arpy.distributed.decomposition`: the ranks' boxes, :class:`Decomposition` and :func:`bisect`;
* :mod:`~arpy.distributed.ghosts`: :func:`halo`, :func:`migrate`, :func:`exchange_ghosts` and
  :func:`scatter` (the same set on every rank -> each rank's share);
* :mod:`~arpy.distributed.dcpse`: :class:`DistributedDCPSE` and :class:`Laplacian`, bitwise the same
  for every rank count, and the one-process operator's;
* :mod:`~arpy.distributed.reductions`: :func:`exact_sum`, :func:`gather`, :func:`h_min` and
  :func:`key_ordered`;
* :mod:`~arpy.distributed.pvtu`: :func:`write_pvtu`, one ``.vtu`` piece per rank (large runs);
* :mod:`~arpy.distributed.organize`: :func:`self_organize` over the ranks, :func:`organized` and
  :func:`organize_set`;
* :mod:`~arpy.distributed.resolution`: :class:`RankResolution`, :func:`graded_on_ranks` and
  :func:`field_resolution` of an old set spread over the ranks.

:func:`scatter` and :func:`h_min` are what :class:`arpy.Simulation` takes with ``comm=`` (time steps of
particles that move but are not re-organized: operators at each stage's positions, migration after
each step).
"""

from .comm import Comm, MPIComm, SerialComm, ThreadComm, launched_comm, run_threads
from .dcpse import DistributedDCPSE, Laplacian
from .decomposition import Decomposition, bisect
from .ghosts import GhostLayer, exchange_ghosts, halo, migrate, scatter
from .organize import organize_set, organized, self_organize
from .pvtu import write_pvtu
from .reductions import exact_sum, gather, h_min, key_ordered
from .resolution import RankResolution, field_resolution, graded_on_ranks

__all__ = ["Comm", "Decomposition", "DistributedDCPSE", "GhostLayer", "Laplacian", "MPIComm", "RankResolution",
           "SerialComm", "ThreadComm", "bisect", "exchange_ghosts", "exact_sum", "field_resolution", "gather",
           "graded_on_ranks", "h_min", "halo", "key_ordered", "launched_comm", "migrate", "organize_set", "organized",
           "run_threads", "scatter", "self_organize", "write_pvtu"]
