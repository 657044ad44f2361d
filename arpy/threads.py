"""Threads and memory of arpy's Fortran core.

The core's parallel loops (OpenMP) use every core by default, or ``OMP_NUM_THREADS`` when it is set
(threadpoolctl's ``threadpool_limits`` works too: it sets the same OpenMP default).  Under MPI, an
:class:`arpy.distributed.MPIComm` of more than one rank makes that one thread per rank unless the user
chose a count (:func:`one_thread_per_rank`): P ranks of every core's threads each would share the
cores P times over.
:func:`set_num_threads` overrides that for the whole process, and :func:`num_threads` does so for a
``with`` block.  Results do not depend on the number of threads: every parallel loop writes each
output from exactly one iteration and splits no floating-point sum between threads.  Every core
routine releases the GIL, so Python threads may call arpy at the same time.

On Linux the core asks the kernel to back its large work arrays (4 MiB and more: neighbour lists,
AR trees and their hand-off of many particles) with transparent huge pages, which cuts the cost of
touching fresh memory (a list of 1e6 particles: about 11,000 page faults fewer, 15 to 25 % of its
time).  :func:`set_huge_pages` turns that off, for systems where huge pages are scarce.
"""


from __future__ import annotations

import os
import warnings
from contextlib import contextmanager
from typing import Iterator

import numpy as np

from . import _bridge
from ._validate import is_integer

__all__ = ["MAX_THREADS_PER_CORE", "get_num_threads", "max_threads", "num_threads", "one_thread_per_rank",
           "set_huge_pages", "set_num_threads"]


#: :func:`set_num_threads` takes at most this many threads per core (``os.cpu_count()``): more
#: only slow the loops down, and a count of millions kills the interpreter when the OpenMP runtime
#: starts that many threads.
MAX_THREADS_PER_CORE = 4


def max_threads() -> int:
    """The largest count :func:`set_num_threads` takes: :data:`MAX_THREADS_PER_CORE` per core."""
    return MAX_THREADS_PER_CORE * (os.cpu_count() or 1)


def _thread_count(n: object) -> int:
    """``n`` checked as a thread count: an integer (Python or NumPy, not bool) in [0, :func:`max_threads`],
    None as 0 (OpenMP's default); ValueError otherwise."""
    if n is None:
        return 0
    if not is_integer(n) or n < 0:
        raise ValueError(f"the number of threads must be an integer >= 1 (or 0/None: the default), got {n!r}")
    if n > max_threads():
        raise ValueError(f"the number of threads must be at most {max_threads()} ({MAX_THREADS_PER_CORE} per core, "
                         f"{os.cpu_count() or 1} cores), got {int(n)}")
    return int(n)


def set_num_threads(n: int | None) -> None:
    """Use ``n`` threads in the core's parallel loops (``None`` or 0: OpenMP's default).

    Parameters
    ----------
    n : int or None
        Number of threads, 1 to :func:`max_threads` (4 per core; a NumPy integer is fine); ``None``
        or 0 returns to OpenMP's default (``OMP_NUM_THREADS``, else every core).

    Raises
    ------
    ValueError
        For anything else (a bool, a float, a negative count, more than :func:`max_threads`); the
        setting then stays as it was.
    """
    count = _thread_count(n)
    effective = count
    if _setting["forked"] and count != 1:
        warnings.warn("arpy: this process was forked from one that had started OpenMP threads; the core "
                      "runs on one thread here (use the 'spawn' or 'forkserver' start method for more)",
                      RuntimeWarning, stacklevel=2)
        effective = 1
    _bridge.set_threads(effective)
    _setting["requested"] = count


def get_num_threads() -> int:
    """The number of threads the core's next parallel loop will use."""
    return _bridge.get_threads()


def set_huge_pages(on: bool) -> bool:
    """Whether the core asks for transparent huge pages for its large arrays (default: yes).

    It is advice to the kernel (``madvise(MADV_HUGEPAGE)`` on arrays of 4 MiB or more, Linux
    only): results are the same either way, only the time to fault fresh memory in changes.  The
    kernel follows it when ``/sys/kernel/mm/transparent_hugepage/enabled`` is ``madvise`` or
    ``always``; turn it off where the kernel's compaction for huge pages stalls the process.

    Parameters
    ----------
    on : bool
        True: advise huge pages; False: leave the kernel's default.

    Returns
    -------
    bool
        The setting before the call.
    """
    if not isinstance(on, (bool, np.bool_)):
        raise TypeError(f"set_huge_pages: on must be True or False, got {on!r}")
    return _bridge.set_huge_pages(bool(on))


@contextmanager
def num_threads(n: int | None) -> Iterator[None]:
    """A ``with`` block in which the core uses ``n`` threads (see :func:`set_num_threads`); the count
    is process-wide, so concurrent Python threads see it too.  A count :func:`set_num_threads` refuses
    raises before the block, and the setting stays as it was."""
    before = _setting["requested"]
    set_num_threads(n)
    try:
        yield
    finally:
        set_num_threads(before)


def one_thread_per_rank(ranks: int) -> bool:
    """One thread in the core's loops, for a process that is one of ``ranks`` MPI ranks, unless the
    user chose the count: ``OMP_NUM_THREADS`` is set, or :func:`set_num_threads` was called with a
    count (called after this, it still overrides).  Called by :class:`arpy.distributed.MPIComm`.

    Every rank would otherwise start OpenMP's default, a thread per core, and P ranks on a machine
    would run P threads per core: 2 ranks of 2 threads on 2 cores took 9.8 s where 2 ranks of one
    thread took 4.75 s (issue 54).  For ranks that each have cores of their own (a rank per node or
    per socket), give ``OMP_NUM_THREADS`` to ``mpiexec``.

    Returns
    -------
    bool
        Whether it set one thread (False: one rank, or the user's count stands).
    """
    if ranks <= 1 or "OMP_NUM_THREADS" in os.environ or _setting["requested"]:
        return False
    _bridge.set_threads(1)
    _setting["requested"] = 1
    return True


#: The count last set by :func:`set_num_threads` or :func:`one_thread_per_rank` (0: OpenMP's default);
#: whether this process is a fork of one that had loaded the core.
_setting = {"requested": 0, "forked": False}


def _after_fork_in_child() -> None:
    """One thread in a forked child (see the module docstring)."""
    _setting["forked"] = True
    _bridge.set_threads(1)


os.register_at_fork(after_in_child=_after_fork_in_child)
