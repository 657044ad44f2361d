"""Communicators of a distributed run: what the distributed functions need of one (:class:`Comm`), and
the three that provide it: :class:`SerialComm` (one process: the serial path is the parallel path
with P = 1), :class:`MPIComm` (mpi4py, one process per rank) or :class:`ThreadComm` (ranks as
threads of one process, :func:`run_threads`, to check the exchanges in one process).
"""

from __future__ import annotations

import os
import threading
from typing import Any, Callable, Protocol, Sequence

import numpy as np

__all__ = ["Comm", "LAUNCHER_VARIABLES", "MPIComm", "SerialComm", "ThreadComm", "launched_comm", "run_threads"]


class Comm(Protocol):
    """What the distributed functions need of a communicator (an mpi4py communicator wrapped, one
    process alone, or threads standing for ranks).  Collectives: every rank calls them in the same
    order.  Sums are of integers (exact, so independent of the rank count)."""

    rank: int
    size: int

    def allgather(self, value: Any) -> list[Any]: ...

    def alltoall(self, values: Sequence[Any]) -> list[Any]: ...

    def sum(self, value: int) -> int: ...

    def min(self, value: np.ndarray) -> np.ndarray: ...

    def max(self, value: np.ndarray) -> np.ndarray: ...


class _Collectives:
    """sum/min/max from allgather (in rank order; exact for integers, minima and maxima)."""

    size: int

    def allgather(self, value: Any) -> list[Any]:
        raise NotImplementedError

    def _per_rank(self, values: Sequence[Any]) -> list[Any]:
        """The values of an alltoall, checked: one per rank."""
        if len(values) != self.size:
            raise ValueError(f"alltoall needs one value per rank ({self.size}), got {len(values)}")
        return list(values)

    def sum(self, value: int) -> int:
        return int(sum(int(v) for v in self.allgather(int(value))))

    def min(self, value: np.ndarray) -> np.ndarray:
        return np.minimum.reduce([np.asarray(v, dtype=np.float64) for v in self.allgather(value)])

    def max(self, value: np.ndarray) -> np.ndarray:
        return np.maximum.reduce([np.asarray(v, dtype=np.float64) for v in self.allgather(value)])


class SerialComm(_Collectives):
    """One process alone: every collective is the identity, so serial runs take the parallel path
    with P = 1."""

    rank, size = 0, 1

    def allgather(self, value: Any) -> list[Any]:
        return [value]

    def alltoall(self, values: Sequence[Any]) -> list[Any]:
        return self._per_rank(values)


class MPIComm(_Collectives):
    """An mpi4py communicator (default ``MPI.COMM_WORLD``; the ``mpi`` extra), one process per rank:
    ``mpiexec -n P python script.py``."""

    def __init__(self, comm: Any = None) -> None:
        if comm is None:
            from mpi4py import MPI

            comm = MPI.COMM_WORLD
        self._comm, self.rank, self.size = comm, int(comm.Get_rank()), int(comm.Get_size())

    def allgather(self, value: Any) -> list[Any]:
        return list(self._comm.allgather(value))

    def alltoall(self, values: Sequence[Any]) -> list[Any]:
        return list(self._comm.alltoall(self._per_rank(values)))


#: Environment variables an MPI launcher sets in the processes it starts (Open MPI; MPICH's Hydra and
#: Intel MPI; PMIx launchers).
LAUNCHER_VARIABLES = ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK")


def launched_comm() -> MPIComm | None:
    """``MPIComm()`` (MPI.COMM_WORLD) when this process was started by an MPI launcher (``mpiexec``,
    ``mpirun``: one of :data:`LAUNCHER_VARIABLES` is set), else None."""
    if not any(v in os.environ for v in LAUNCHER_VARIABLES):
        return None
    try:
        import mpi4py  # noqa: F401
    except ImportError as exc:
        raise RuntimeError("this process was started by mpiexec, but mpi4py is missing: "
                           "pip install 'arpy-particles[mpi]'") from exc
    return MPIComm()


class _Group:
    def __init__(self, size: int, timeout: float) -> None:
        self.size = size
        self.barrier = threading.Barrier(size, timeout=timeout)
        self.slots: list[Any] = [None] * size


class ThreadComm(_Collectives):
    """Ranks as threads of one process (:func:`run_threads`): the exchanges of a distributed run,
    checked without MPI.  The core releases the GIL, so the ranks also compute at once."""

    def __init__(self, group: _Group, rank: int) -> None:
        self._group, self.rank, self.size = group, rank, group.size

    def allgather(self, value: Any) -> list[Any]:
        g = self._group
        g.slots[self.rank] = value
        g.barrier.wait()
        out = list(g.slots)
        g.barrier.wait()
        return out

    def alltoall(self, values: Sequence[Any]) -> list[Any]:
        return [row[self.rank] for row in self.allgather(self._per_rank(values))]


def run_threads(size: int, fn: Callable[[ThreadComm], Any], timeout: float = 120.0) -> list[Any]:
    """Run ``fn(comm)`` on ``size`` ranks, one thread each; returns their results in rank order.  An
    error on any rank breaks every rank's waiting collective and is raised here (no deadlock)."""
    group = _Group(int(size), timeout)
    results: list[Any] = [None] * size
    errors: list[BaseException] = []

    def target(rank: int) -> None:
        try:
            results[rank] = fn(ThreadComm(group, rank))
        except BaseException as exc:              # (a rank's failure ends the others' collectives)
            errors.append(exc)
            group.barrier.abort()

    threads = [threading.Thread(target=target, args=(r,)) for r in range(size)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        first = next((e for e in errors if not isinstance(e, threading.BrokenBarrierError)), errors[0])
        raise first
    return results
