"""Communicators of a distributed run: what the distributed functions need of one (:class:`Comm`), and
the three that provide it: :class:`SerialComm` (one process: the serial path is the parallel path
with P = 1), :class:`MPIComm` (mpi4py, one process per rank) or :class:`ThreadComm` (ranks as
threads of one process, :func:`run_threads`, to check the exchanges in one process).

No rank is left waiting for one that failed: under MPI, an uncaught exception or a ``sys.exit`` with
a non-zero status on any rank ends the whole job (``MPI_Abort``, :class:`MPIComm`); on thread ranks
the others leave their collective at once with :class:`CollectiveAborted` and :func:`run_threads`
raises the failing rank's error.  The inputs that must be the same on every rank are checked to be
(:func:`arpy.distributed.inputs.agree`), so that ranks given different ones fail together, naming
the difference, instead of mixing them.
"""

from __future__ import annotations

import atexit
import os
import sys
import time
import threading
from typing import Any, Callable, Mapping, NoReturn, Protocol, Sequence

import numpy as np

from ..threads import one_thread_per_rank

__all__ = ["CollectiveAborted", "Comm", "LAUNCHER_VARIABLES", "MPIComm", "SerialComm", "ThreadComm",
           "launched_comm", "order_keys", "rank_list", "run_threads"]


class Comm(Protocol):
    """What the distributed functions need of a communicator (an mpi4py communicator wrapped, one
    process alone, or threads standing for ranks).  Collectives: every rank calls them in the same
    order.  Sums are of integers (exact, so independent of the rank count); minima and maxima are of
    doubles in their total order (-0.0 below 0.0; NaN where any rank has one), so every rank gets the
    same bits whatever order the ranks' values are combined in."""

    rank: int
    size: int

    def allgather(self, value: Any) -> list[Any]: ...

    def alltoall(self, values: Sequence[Any]) -> list[Any]: ...

    def sum(self, value: int) -> int: ...

    def add(self, value: np.ndarray) -> np.ndarray: ...

    def gather_arrays(self, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def alltoall_arrays(self, data: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def min(self, value: np.ndarray) -> np.ndarray: ...

    def max(self, value: np.ndarray) -> np.ndarray: ...

    def exchange(self, sends: Mapping[int, np.ndarray], recv: Mapping[int, np.ndarray]) -> None: ...

    def sparse_alltoall(self, values: Sequence[Any]) -> list[Any]: ...

    def work(self) -> float: ...


def _metered(method: Callable[..., Any]) -> Callable[..., Any]:
    """``method`` of a communicator, its CPU time (:meth:`_Collectives.clock`) added to
    ``exchanging``."""
    def metered(self: "_Collectives", *args: Any) -> Any:
        t0 = self.clock()
        try:
            return method(self, *args)
        finally:
            self.exchanging += self.clock() - t0

    metered.__name__, metered.__doc__ = method.__name__, method.__doc__
    return metered


class _Collectives:
    """sum/min/max from allgather (in rank order; exact for integers, minima and maxima)."""

    size: int
    rank: int
    #: Point-to-point messages this rank has sent by :meth:`exchange` and :meth:`sparse_alltoall`
    #: (one per other rank it had something for; what stays on the rank is no message).
    messages: int = 0
    #: CPU seconds (:meth:`clock`) this rank has spent in its exchanges, waiting for the others included
    #: (an MPI library waits busily).
    exchanging: float = 0.0

    def clock(self) -> float:
        """This rank's CPU time, seconds: its process's (:func:`time.process_time`)."""
        return time.process_time()

    def work(self) -> float:
        """CPU seconds this rank has computed: its :meth:`clock` less the time of its exchanges (the
        differences between two calls measure the work in between; :mod:`arpy.distributed.balance`)."""
        return self.clock() - self.exchanging

    def allgather(self, value: Any) -> list[Any]:
        raise NotImplementedError

    def alltoall(self, values: Sequence[Any]) -> list[Any]:
        raise NotImplementedError

    def exchange(self, sends: Mapping[int, np.ndarray], recv: Mapping[int, np.ndarray]) -> None:
        """Arrays to the ranks that need them and from the ranks that have them, a pattern both sides
        know (as a ghost layer's refresh does): ``sends[r]`` goes to rank r, rank s's array for this
        rank fills ``recv[s]`` (given with the size and dtype to come).  Only ranks with something
        to send or receive take part in a message; every rank calls it (a collective on thread ranks).
        Here: through :meth:`allgather`, the message counted as the MPI communicator sends it."""
        self._checked_ranks(sends, recv)
        self.messages += sum(1 for r in sends if r != self.rank)
        every = self.allgather(dict(sends))
        for r, buf in recv.items():
            buf[...] = every[r][self.rank]

    def sparse_alltoall(self, values: Sequence[Any]) -> list[Any]:
        """:meth:`alltoall` where most values are None (nothing for that rank): only the others are
        sent, and a rank learns who sends to it as the messages come (MPI: the NBX exchange of
        Hoefler et al. 2010, synchronous sends and a non-blocking barrier, no all-to-all of counts).
        Returns one value per rank, None from a rank that sent nothing."""
        values = self._per_rank(values)
        self.messages += sum(1 for r, v in enumerate(values) if v is not None and r != self.rank)
        return self.alltoall(values)

    def _checked_ranks(self, sends: Mapping[int, np.ndarray], recv: Mapping[int, np.ndarray]) -> None:
        bad = [r for r in (*sends, *recv) if not 0 <= int(r) < self.size]
        if bad:
            raise ValueError(f"exchange: rank {bad[0]} is not in [0, {self.size})")

    def _per_rank(self, values: Sequence[Any]) -> list[Any]:
        """The values of an alltoall, checked: one per rank."""
        if len(values) != self.size:
            raise ValueError(f"alltoall needs one value per rank ({self.size}), got {len(values)}")
        return list(values)

    def sum(self, value: int) -> int:
        """The sum over the ranks of an integer (within int64)."""
        return int(self.add(np.array([int(value)], np.int64))[0])

    def add(self, value: np.ndarray) -> np.ndarray:
        """The elementwise sums over the ranks of integer arrays of one shape, int64 (exact)."""
        return np.sum([np.asarray(v, np.int64) for v in self.allgather(np.asarray(value, np.int64))], axis=0)

    def gather_arrays(self, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every rank's numbers (an array of one dtype on every rank, flattened; sizes may differ),
        concatenated in rank order, and where each rank's begin, int64 (P + 1,): rank r's are
        ``out[offsets[r]:offsets[r + 1]]``."""
        parts = self.allgather(np.ascontiguousarray(value).ravel())
        return np.concatenate(parts), np.concatenate([[0], np.cumsum([q.size for q in parts])]).astype(np.int64)

    def alltoall_arrays(self, data: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Numbers to every rank at once: ``data`` (1-D, one dtype on every rank) holds, in rank order,
        ``counts[r]`` numbers for rank r.  Returns what every rank sent to this one, in rank order, and
        how many came from each, int64 (P,)."""
        ends = np.cumsum(np.asarray(counts, np.int64))
        got = self.alltoall(np.split(np.ascontiguousarray(data).ravel(), ends[:-1]))
        return np.concatenate(got), np.array([g.size for g in got], np.int64)

    def min(self, value: np.ndarray) -> np.ndarray:
        """The elementwise minima over the ranks of arrays of doubles of one shape (see :class:`Comm`)."""
        return self._extreme(value, largest=False)

    def max(self, value: np.ndarray) -> np.ndarray:
        """The elementwise maxima over the ranks of arrays of doubles of one shape (see :class:`Comm`)."""
        return self._extreme(value, largest=True)

    def _extreme(self, value: np.ndarray, largest: bool) -> np.ndarray:
        """min or max as the max of int64 keys in the doubles' total order (negated for min), with each
        element's NaN flag beside it: one reduction of 2 n integers."""
        v = np.asarray(value, dtype=np.float64)
        flat = v.ravel()
        nan = np.isnan(flat)
        keys = order_keys(np.where(nan, 0.0, flat))
        got = self._max_keys(np.concatenate([keys if largest else ~keys, nan.astype(np.int64)]))
        keys = got[:flat.size] if largest else ~got[:flat.size]
        out = order_keys(keys, back=True)
        out[got[flat.size:] > 0] = np.nan
        return out.reshape(v.shape)

    def _max_keys(self, keys: np.ndarray) -> np.ndarray:
        """The elementwise maxima over the ranks of int64 arrays of one shape."""
        return np.max([np.asarray(k, np.int64) for k in self.allgather(keys)], axis=0)


#: The bits below the sign of a float64 seen as an int64 (:func:`order_keys`).
_LOW_BITS = np.int64(0x7FFFFFFFFFFFFFFF)


def order_keys(v: np.ndarray, back: bool = False) -> np.ndarray:
    """Doubles (not NaN) -> int64 keys in the same order (-0.0 below 0.0), for exact reductions, sorts
    and bisections over values: the bits, with the low bits of a negative value flipped (its own
    inverse); ``back``: keys -> the doubles."""
    bits = np.ascontiguousarray(v, dtype=np.int64 if back else np.float64).view(np.int64)
    out = bits ^ ((bits >> 63) & _LOW_BITS)
    return out.view(np.float64) if back else out


class SerialComm(_Collectives):
    """One process alone: every collective is the identity, so serial runs take the parallel path
    with P = 1."""

    rank, size = 0, 1

    def allgather(self, value: Any) -> list[Any]:
        return [value]

    def alltoall(self, values: Sequence[Any]) -> list[Any]:
        return self._per_rank(values)


def rank_list(ranks: Sequence[int]) -> str:
    """'rank 3', 'ranks 0, 2' or 'ranks 0-511, 600' (runs of consecutive ranks shortened)."""
    runs: list[list[int]] = []
    for r in ranks:
        if runs and r == runs[-1][1] + 1:
            runs[-1][1] = r
        else:
            runs.append([r, r])
    text = ", ".join(str(a) if a == b else f"{a}, {b}" if b == a + 1 else f"{a}-{b}" for a, b in runs)
    return f"rank{'s' if len(ranks) > 1 else ''} {text}"


# ---------------------------------------------------------------------- MPI
class _AbortOnFailure:
    """What makes one failing rank end a whole MPI job (installed once per process, by the first
    :class:`MPIComm` of more than one rank): an excepthook chained to the previous one (it prints the
    traceback, then one line with the rank, then ``MPI_Abort``), and ``sys.exit`` wrapped to note its
    status, which an atexit handler turns into ``MPI_Abort`` when it is not 0 (a rank that ends
    with status 0 ends normally: after the last collective, the others do not wait for it)."""

    world: Any = None
    status: Any = None

    @classmethod
    def install(cls, world: Any) -> None:
        """Install the hooks for the job of ``world`` (MPI.COMM_WORLD), once."""
        if cls.world is not None:
            return
        cls.world = world
        previous_hook, previous_exit = sys.excepthook, sys.exit

        def excepthook(kind: type[BaseException], exc: BaseException, tb: Any) -> None:
            try:
                previous_hook(kind, exc, tb)
            finally:
                cls.abort(130 if issubclass(kind, KeyboardInterrupt) else 1, f"an uncaught {kind.__name__}: {exc}")

        def exit(status: Any = None) -> NoReturn:
            if threading.current_thread() is threading.main_thread():
                cls.status = status
            previous_exit(status)

        sys.excepthook = excepthook
        sys.exit = exit
        atexit.register(cls.at_exit)

    @classmethod
    def at_exit(cls) -> None:
        """At the end of the process: a status given to ``sys.exit`` that is not 0 ends the job."""
        status = cls.status
        code = 0 if status is None else status if isinstance(status, int) else 1
        if code:
            cls.abort(code, f"sys.exit({status!r})")

    @classmethod
    def abort(cls, status: int, what: str) -> NoReturn:
        """Print one line naming this rank, ``status`` and ``what`` ended it, then end every rank of the
        job with ``status`` (``MPI_Abort``; if that fails, this process alone ends, and the launcher
        then ends the others)."""
        rank, size = cls.world.Get_rank(), cls.world.Get_size()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:                               # (a closed stream: nothing to flush)
                pass
        try:
            sys.stderr.write(f"arpy: rank {rank} of {size} aborts the MPI job (MPI_Abort, exit status {status}) "
                             f"on {what}\n")
            sys.stderr.flush()
            time.sleep(0.25)             # (the launcher forwards what was written before the abort kills it)
            cls.world.Abort(status)
        finally:
            os._exit(status)


class MPIComm(_Collectives):
    """An mpi4py communicator (default ``MPI.COMM_WORLD``; the ``mpi`` extra), one process per rank:
    ``mpiexec -n P python script.py``.

    With more than one rank (and ``abort_on_failure``, the default), a rank that fails ends the whole
    job instead of leaving the others waiting in their next collective: an uncaught exception prints
    its traceback and one line ``arpy: rank R of P aborts the MPI job (MPI_Abort, exit status 1) on an
    uncaught ValueError: ...``, then calls ``MPI_Abort`` with status 1 (130 for Ctrl-C);
    ``sys.exit(status)`` with a status that is not 0 (or None) does the same with that status once the
    process ends (a non-zero ``sys.exit`` that the program catches still counts).  ``sys.exit(0)`` on
    one rank is a normal end (e.g. after the last collective; the others do not wait for it); a bare
    ``raise SystemExit(status)`` is not seen.  The hooks (an excepthook chained to the previous one,
    a wrapper of ``sys.exit`` and an atexit handler) are installed once per process.

    With more than one rank, the core runs one thread per rank unless ``OMP_NUM_THREADS`` is set or
    :func:`arpy.set_num_threads` was called (:func:`arpy.threads.one_thread_per_rank`)."""

    def __init__(self, comm: Any = None, *, abort_on_failure: bool = True) -> None:
        if comm is None:
            comm = _mpi().COMM_WORLD
        self._comm, self.rank, self.size = comm, int(comm.Get_rank()), int(comm.Get_size())
        self._rounds = 0                                  # (sparse_alltoall calls: their tags alternate)
        one_thread_per_rank(self.size)
        if abort_on_failure and self.size > 1:
            _AbortOnFailure.install(_mpi().COMM_WORLD)

    @_metered
    def allgather(self, value: Any) -> list[Any]:
        return list(self._comm.allgather(value))

    @_metered
    def alltoall(self, values: Sequence[Any]) -> list[Any]:
        return list(self._comm.alltoall(self._per_rank(values)))

    @_metered
    def add(self, value: np.ndarray) -> np.ndarray:
        """See :meth:`_Collectives.add`: one MPI_Allreduce of the int64 buffer (no pickling, log P steps)."""
        return self._allreduce(value, "SUM")

    @_metered
    def gather_arrays(self, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """See :meth:`_Collectives.gather_arrays`: the sizes by MPI_Allgather, the numbers by
        MPI_Allgatherv into one buffer (no pickling: nothing per rank in Python)."""
        mine = np.ascontiguousarray(value).ravel()
        sizes = np.empty(self.size, np.int64)
        self._comm.Allgather(np.array([mine.size], np.int64), sizes)
        out = np.empty(int(sizes.sum()), mine.dtype)
        self._comm.Allgatherv(mine, [out, _layout(sizes)])
        return out, np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

    @_metered
    def alltoall_arrays(self, data: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """See :meth:`_Collectives.alltoall_arrays`: the counts by MPI_Alltoall, the numbers by
        MPI_Alltoallv (no pickling: nothing per rank in Python)."""
        send = np.ascontiguousarray(data).ravel()
        sizes = np.ascontiguousarray(counts, dtype=np.int64)
        got = np.empty(self.size, np.int64)
        self._comm.Alltoall(sizes, got)
        out = np.empty(int(got.sum()), send.dtype)
        self._comm.Alltoallv([send, _layout(sizes)], [out, _layout(got)])
        return out, got

    @_metered
    def _max_keys(self, keys: np.ndarray) -> np.ndarray:
        return self._allreduce(keys, "MAX")

    def _allreduce(self, value: np.ndarray, op: str) -> np.ndarray:
        """MPI_Allreduce of an int64 buffer by the MPI operation named ``op``."""
        mine = np.ascontiguousarray(value, dtype=np.int64)
        out = np.empty_like(mine)
        self._comm.Allreduce(mine, out, op=getattr(_mpi(), op))
        return out

    @_metered
    def exchange(self, sends: Mapping[int, np.ndarray], recv: Mapping[int, np.ndarray]) -> None:
        """See :meth:`_Collectives.exchange`: non-blocking receives into the buffers, then non-blocking
        sends of the arrays' bytes (no pickling), then one wait for all."""
        from mpi4py import MPI

        self._checked_ranks(sends, recv)
        comm = self._comm
        requests = [comm.Irecv(buf, source=int(r), tag=_EXCHANGE_TAG) for r, buf in recv.items() if r != self.rank]
        out = {int(r): np.ascontiguousarray(a) for r, a in sends.items()}
        requests += [comm.Isend(a, dest=r, tag=_EXCHANGE_TAG) for r, a in out.items() if r != self.rank]
        self.messages += sum(1 for r in out if r != self.rank)
        if self.rank in recv:
            recv[self.rank][...] = out[self.rank]
        MPI.Request.Waitall(requests)

    @_metered
    def sparse_alltoall(self, values: Sequence[Any]) -> list[Any]:
        """See :meth:`_Collectives.sparse_alltoall` (NBX: each value goes by a synchronous send; a rank
        receives whatever arrives until its own sends are matched and then every rank's, which the
        non-blocking barrier tells)."""
        from mpi4py import MPI

        values = self._per_rank(values)
        comm = self._comm
        # consecutive calls alternate tags: a rank that is through with one may send the next one's
        # messages while another still waits for this one's barrier (never two calls ahead)
        self._rounds += 1
        tag = _SPARSE_TAG + self._rounds % 2
        got: list[Any] = [None] * self.size
        got[self.rank] = values[self.rank]
        sent = [comm.issend(v, dest=r, tag=tag) for r, v in enumerate(values)
                if v is not None and r != self.rank]
        self.messages += len(sent)
        status = MPI.Status()
        barrier = None
        while True:
            if comm.iprobe(source=MPI.ANY_SOURCE, tag=tag, status=status):
                src = status.Get_source()
                got[src] = comm.recv(source=src, tag=tag)
            if barrier is None:
                if MPI.Request.Testall(sent):
                    barrier = comm.Ibarrier()
            elif barrier.Test():
                return got


def _layout(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The counts of a vector collective's parts and where each begins, as MPI takes them (C int); a
    buffer of 2^31 numbers or more raises OverflowError (MPI's int counts cannot say it)."""
    c = np.asarray(counts, np.int64)
    starts = np.cumsum(c) - c
    if c.size and int(starts[-1] + c[-1]) >= 2 ** 31:
        raise OverflowError(f"an exchange of {int(c.sum()):,} numbers: MPI's counts stop below 2^31")
    return c.astype(np.int32), starts.astype(np.int32)


#: The tags of :meth:`MPIComm.exchange` and :meth:`MPIComm.sparse_alltoall` messages (apart from each other
#: and from mpi4py's collectives, which use no tags).
_EXCHANGE_TAG, _SPARSE_TAG = 7301, 7302   # (and 7303)

def _mpi() -> Any:
    """mpi4py's ``MPI`` module; a RuntimeError that says what to install when mpi4py or an MPI library
    is missing (mpi4py's own message is ``cannot load MPI library``)."""
    try:
        from mpi4py import MPI
    except ImportError as exc:
        raise RuntimeError("mpi4py is missing: pip install 'arpy-particles[mpi]' (mpi4py and the MPICH "
                           "wheel)") from exc
    except RuntimeError as exc:
        raise RuntimeError(f"mpi4py found no MPI library ({exc}): pip install mpich (the MPICH wheel, for one "
                           "machine), or build mpi4py against your cluster's MPI (README, 'Many processes')") \
            from exc
    return MPI


#: Environment variables an MPI launcher sets in the processes it starts (Open MPI; MPICH's Hydra and
#: Intel MPI; PMIx launchers).
LAUNCHER_VARIABLES = ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK")


def launched_comm() -> MPIComm | None:
    """``MPIComm()`` (MPI.COMM_WORLD) when this process was started by an MPI launcher (``mpiexec``,
    ``mpirun``: one of :data:`LAUNCHER_VARIABLES` is set), else None."""
    if not any(v in os.environ for v in LAUNCHER_VARIABLES):
        return None
    return MPIComm()                               # (without mpi4py or MPI: what to install, _mpi())


# ---------------------------------------------------------------------- thread ranks
class CollectiveAborted(RuntimeError):
    """A collective of thread ranks that cannot complete: another rank raised, or returned without
    calling it (the ranks did not call the same collectives), or a rank waited longer than the
    timeout.  The message names this rank, the collective and the cause."""


class _Group:
    """What thread ranks share: the values of the collective under way, the number of collectives
    completed (``generation``), how each rank ended (its exception, or None when it returned) and,
    once the collectives are broken, why."""

    def __init__(self, size: int, timeout: float) -> None:
        self.size, self.timeout = size, timeout
        self.cond = threading.Condition()
        self.slots: list[Any] = [None] * size
        self.arrived: set[int] = set()
        self.generation = 0
        self.result: list[Any] = []
        self.calls = [0] * size
        self.ended: dict[int, BaseException | None] = {}
        self.failures: list[tuple[int, BaseException]] = []          # (rank, exception) in time order
        self.cause: str | None = None

    def exchange(self, rank: int, value: Any) -> list[Any]:
        """Every rank's ``value``, in rank order, once every rank has given one (an allgather)."""
        with self.cond:
            self.calls[rank] += 1
            generation = self.generation
            self.slots[rank] = value
            self.arrived.add(rank)
            if len(self.arrived) == self.size and self.cause is None:
                self.result, self.slots, self.arrived = self.slots, [None] * self.size, set()
                self.generation += 1
                self.cond.notify_all()
                return list(self.result)
            done = self.cond.wait_for(lambda: self.generation != generation or self.cause is not None
                                      or None in self.ended.values(), self.timeout)
            if self.generation != generation:
                return list(self.result)
            if self.cause is None:
                gone = [r for r, exc in self.ended.items() if exc is None]
                self.cause = (f"{rank_list(gone)} returned after {self.calls[gone[0]]} collectives without calling "
                              "it (the ranks do not call the same collectives)" if done else
                              f"{rank_list(sorted(set(range(self.size)) - self.arrived))} did not reach it "
                              f"within {self.timeout:g} s")
                self.cond.notify_all()
            raise CollectiveAborted(f"rank {rank} of {self.size} left collective #{self.calls[rank]} "
                                    f"unfinished: {self.cause}")

    def leave(self, rank: int, exc: BaseException | None) -> None:
        """Rank ``rank`` has ended: returned (``exc`` None) or raised ``exc``, which releases every
        rank waiting in a collective."""
        with self.cond:
            self.ended[rank] = exc
            if exc is not None:
                self.failures.append((rank, exc))
                if self.cause is None:
                    self.cause = f"rank {rank} raised {type(exc).__name__}: {exc}"
            self.cond.notify_all()

    def interrupt(self, why: str) -> None:
        """Break the collectives (every rank's next or current one raises :class:`CollectiveAborted`)."""
        with self.cond:
            self.cause = self.cause or why
            self.cond.notify_all()

    def wait(self, threads: Sequence[threading.Thread]) -> list[int]:
        """Wait until every rank has ended, or for at most ``timeout`` more once one has failed (the
        others are released from their collectives; one that is still computing is left running);
        returns the ranks that have not ended."""
        with self.cond:
            self.cond.wait_for(lambda: len(self.ended) == self.size or bool(self.failures))
            self.cond.wait_for(lambda: len(self.ended) == self.size, self.timeout)
            stuck = [r for r in range(self.size) if r not in self.ended]
        for r, t in enumerate(threads):
            if r not in stuck:
                t.join()
        return stuck


class ThreadComm(_Collectives):
    """Ranks as threads of one process (:func:`run_threads`): the exchanges of a distributed run,
    checked without MPI.  The core releases the GIL, so the ranks also compute at once.  A collective
    that cannot complete raises :class:`CollectiveAborted` (another rank failed or returned, or the
    group's timeout passed) instead of waiting."""

    def __init__(self, group: _Group, rank: int) -> None:
        self._group, self.rank, self.size = group, rank, group.size

    def clock(self) -> float:
        """This rank's CPU time, seconds: its thread's (:func:`time.thread_time`)."""
        return time.thread_time()

    @_metered
    def allgather(self, value: Any) -> list[Any]:
        return self._group.exchange(self.rank, value)

    def alltoall(self, values: Sequence[Any]) -> list[Any]:
        return [row[self.rank] for row in self.allgather(self._per_rank(values))]


def _note(exc: BaseException, text: str) -> None:
    """``exc.add_note(text)`` (Python >= 3.11; before, only recorded in ``__notes__``)."""
    add = getattr(exc, "add_note", None)
    if add is not None:
        add(text)
    else:
        exc.__notes__ = [*getattr(exc, "__notes__", []), text]  # type: ignore[attr-defined]


def run_threads(size: int, fn: Callable[[ThreadComm], Any], timeout: float = 120.0) -> list[Any]:
    """Run ``fn(comm)`` on ``size`` ranks, one thread each; returns their results in rank order.

    Every wait ends in bounded time: a collective waits at most ``timeout`` seconds for the other
    ranks, and ends at once when a rank raises or returns without calling it (:class:`CollectiveAborted`).
    When a rank fails, its exception is raised here with a note naming the rank (and what the others
    did); a rank still computing ``timeout`` seconds after that is named and left running (its thread
    is a daemon)."""
    if int(size) < 1:
        raise ValueError(f"run_threads needs size >= 1, got {size!r}")
    group = _Group(int(size), float(timeout))
    results: list[Any] = [None] * group.size

    def target(rank: int) -> None:
        try:
            results[rank] = fn(ThreadComm(group, rank))
        except BaseException as exc:                # (a rank's failure ends the others' collectives)
            group.leave(rank, exc)
        else:
            group.leave(rank, None)

    threads = [threading.Thread(target=target, args=(r,), name=f"arpy thread rank {r}", daemon=True)
               for r in range(group.size)]
    for t in threads:
        t.start()
    try:
        stuck = group.wait(threads)
    except BaseException:                     # (interrupted here: the ranks leave their next collective)
        group.interrupt("run_threads was interrupted")
        raise
    if not group.failures:
        return results
    rank, first = next(((r, e) for r, e in group.failures if not isinstance(e, CollectiveAborted)),
                       group.failures[0])
    _note(first, _outcome(group, rank, first, stuck))
    raise first


def _outcome(group: _Group, rank: int, first: BaseException, stuck: Sequence[int]) -> str:
    """The note on the error :func:`run_threads` raises: which rank raised it, and what the others did."""
    same, released, other = [], [], []
    for r, e in sorted(group.failures, key=lambda f: f[0]):
        if r == rank:
            continue
        if type(e) is type(first) and str(e) == str(first):
            same.append(r)
        elif isinstance(e, CollectiveAborted):
            released.append(r)
        else:
            other.append(f"{rank_list([r])} raised {type(e).__name__}: {e}")
    parts = [f"raised on rank {rank} of {group.size} (thread ranks)"]
    if same:
        parts.append(f"{rank_list(same)} raised it too")
    if released:
        parts.append(f"{rank_list(released)} left {'their collectives' if len(released) > 1 else 'its collective'}"
                     " unfinished")
    parts.extend(other)
    if stuck:
        parts.append(f"{rank_list(stuck)} did not end within {group.timeout:g} s after that (left running)")
    return "; ".join(parts)
