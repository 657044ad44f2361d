"""Domain decomposition for distributed runs: recursive coordinate bisection and ghost layers of
per-particle width.

The pieces of an SPMD run (one process per rank, particles exchanged between ranks): which rank owns
each particle, which particles a rank needs besides its own, and the exchanges that move them, through
a communicator (:class:`Comm`; one process, MPI ranks, or threads standing for ranks).  Every public
name is importable from ``arpy.distributed``; by concept they live in:

* :mod:`~arpy.distributed.comm`: the communicators, :class:`SerialComm` (one process is P = 1), :class:`MPIComm` and :class:`ThreadComm` (:func:`run_threads`);
  :mod:`~arpy.distributed.inputs`: :func:`agree`, the check that the ranks were given the same inputs;
* :mod:`~arpy.distributed.decomposition`: the ranks' boxes, :class:`Decomposition` and :func:`bisect`;
* :mod:`~arpy.distributed.balance`: when the boxes are cut anew, weighted by the measured cost of the
  particles (:class:`~arpy.distributed.balance.CostBalance`);
* :mod:`~arpy.distributed.share`: the phases whose cost per particle varies over space, shared between
  the ranks by their measured cost (:class:`~arpy.distributed.share.Sharing`);
* :mod:`~arpy.distributed.ghosts`: :func:`halo`, :func:`migrate`, :func:`exchange_ghosts` and
  :func:`scatter` (the same set on every rank -> each rank's share);
* :mod:`~arpy.distributed.dcpse`: :class:`DistributedDCPSE` and :class:`Laplacian`, bitwise the same
  for every rank count, and the one-process operator's;
* :mod:`~arpy.distributed.kept`: :class:`~arpy.distributed.kept.KeptGhosts`, the ghost layer and rows
  kept across the operators of moving particles (Verlet lists with a skin over the ranks);
* :mod:`~arpy.distributed.reductions`: :func:`exact_sum`, :func:`gather`, :func:`h_min` and
  :func:`key_ordered`;
* :mod:`~arpy.distributed.pvtu`: :func:`write_pvtu`, one ``.vtu`` piece per rank (large runs);

These are the mechanisms; what runs on them takes a ``comm=``: :func:`arpy.self_organize` (its view of
the particles, :class:`arpy.adapt.view.View`), :class:`arpy.particles.Particles` and
:class:`arpy.Simulation`, the same code at every rank count.
"""

from .comm import CollectiveAborted, Comm, MPIComm, SerialComm, ThreadComm, launched_comm, run_threads
from .inputs import agree
from .dcpse import DistributedDCPSE, Laplacian
from .decomposition import Decomposition, bisect
from .ghosts import GhostLayer, exchange_ghosts, halo, migrate, scatter
from .pvtu import write_pvtu
from .reductions import exact_sum, gather, h_min, key_ordered

__all__ = ["CollectiveAborted", "Comm", "Decomposition", "DistributedDCPSE", "GhostLayer", "Laplacian", "MPIComm",
           "SerialComm", "ThreadComm", "agree", "bisect", "exchange_ghosts", "exact_sum", "gather",
           "h_min", "halo", "key_ordered", "launched_comm", "migrate", "run_threads",
           "scatter", "write_pvtu"]
