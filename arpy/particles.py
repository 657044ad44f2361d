"""One particle container for one process and for many: :class:`Particles`.

A :class:`Particles` holds this rank's share of a particle set: positions, core-size scales D (the
core sizes are ``rstar * D``), global keys, named fields, the :class:`arpy.Domain`, a communicator
and the boxes of the decomposition.  One process is simply P = 1 (:class:`arpy.distributed.SerialComm`,
the default): its one box holds every particle, its exchanges send nothing, its reductions are the
values themselves.  Migration, ghost layers, reductions (exact sums, minima and maxima, the smallest
spacing) and gathering are the container's methods, so a simulation step is written once and runs
unchanged at every rank count.

Keys number the particles of the whole set; rows, sums and tie-breaks follow key order, so results
do not depend on how the particles are dealt to the ranks, nor on their order in memory.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .distributed import (Comm, Decomposition, GhostLayer, SerialComm, exact_sum, exchange_ghosts, gather, h_min,
                          migrate, scatter)
from .domain import Domain
from .io import load_results, save_results
from .lists.search import cache_order

__all__ = ["Particles"]


@dataclass
class Particles:
    """This rank's particles of a set spread over the ranks of ``comm`` (one process: all of them).

    Attributes
    ----------
    x : float64 array (n, d)
        Positions of this rank's particles.
    D : float64 array (n,)
        Their resolution D_p (core sizes ``rstar * D``).
    keys : int64 array (n,)
        Their global keys (distinct over the ranks).
    F : float64 array (n, k)
        Their fields, one column per name in ``names``.
    names : tuple of str
        The fields' names.
    domain : Domain
        Where the particles live (a box, or free space).
    rstar : float
        Core size over D.
    dec : Decomposition
        The ranks' boxes; this rank owns the particles in ``dec.box(comm.rank)``.
    comm : Comm
        The ranks (default :class:`arpy.distributed.SerialComm`: one process, P = 1).
    """

    x: np.ndarray
    D: np.ndarray
    keys: np.ndarray
    F: np.ndarray
    names: tuple[str, ...]
    domain: Domain
    rstar: float
    dec: Decomposition
    comm: Comm = field(default_factory=SerialComm)

    @classmethod
    def dealt(cls, x: np.ndarray, D: np.ndarray, F: np.ndarray, names: Sequence[str], *, domain: Domain,
              rstar: float, comm: Comm | None = None, deal: np.ndarray | None = None) -> "Particles":
        """The same whole set (x (n, d), D (n,), F (n, k)) given on every rank -> this rank's share,
        keyed by index: the ranks take the particles ``deal`` gives them (the rank of each particle,
        int (n,), the same on every rank; default every P-th from the rank's number), bisect the
        domain and migrate to the boxes.  Collective."""
        comm = comm or SerialComm()
        dec, xs, keys, got = scatter(comm, x, {"D": D, "F": F}, domain=domain, deal=deal)
        out = cls(xs, got["D"], keys, got["F"], tuple(names), domain, float(rstar), dec, comm)
        if out.parallel:                                   # (each rank keeps its own in cache order)
            out.reorder(cache_order(out.x, domain=out.domain))
        return out

    # ------------------------------------------------------------------ figures
    @property
    def n(self) -> int:
        """The number of this rank's particles."""
        return int(self.x.shape[0])

    @property
    def eps(self) -> np.ndarray:
        """Core sizes ``rstar * D``, (n,)."""
        return self.rstar * self.D

    @property
    def parallel(self) -> bool:
        """Whether the set is spread over more than one rank."""
        return self.comm.size > 1

    def total(self, count: int) -> int:
        """An integer summed over the ranks (exact).  Collective."""
        return int(self.comm.sum(int(count)))

    def gmin(self, value: float) -> float:
        """The smallest of the ranks' values.  Collective."""
        return float(self.comm.min(np.array([value], dtype=np.float64))[0])

    def gmax(self, value: float) -> float:
        """The largest of the ranks' values.  Collective."""
        return float(self.comm.max(np.array([value], dtype=np.float64))[0])

    def fsum(self, values: np.ndarray) -> float:
        """The exact, once-rounded sum of every rank's values (the same bits for any rank count).
        Collective."""
        return exact_sum(self.comm, values)

    def h_min(self) -> float:
        """The smallest distance between two particles of the whole set (minimum image along periodic
        axes).  Collective."""
        return h_min(self.comm, self.dec, self.x, self.eps, self.keys, self.domain)

    # ------------------------------------------------------------------ moving particles
    def migrate(self) -> None:
        """Each particle (with D and fields) to the rank whose box holds it, then in cache order (the
        order in memory changes no result: rows and sums go by key).  One process keeps its order.
        Collective."""
        if self.parallel:               # (one rank owns everything in its box, in the order it has)
            self.x, self.keys, got = migrate(self.comm, self.dec, self.x, self.keys, {"D": self.D, "F": self.F})
            self.D, self.F = got["D"], got["F"]
            self.reorder(cache_order(self.x, domain=self.domain))

    def reorder(self, perm: np.ndarray) -> None:
        """This rank's particles put in the order ``perm`` (nothing else changes)."""
        self.x, self.keys, self.D, self.F = self.x[perm], self.keys[perm], self.D[perm], self.F[perm]

    def ghosts(self, reach: np.ndarray, skin: float = 0.0) -> GhostLayer:
        """The ghosts of this rank: the particles of other ranks (and periodic images) within their own
        ``reach`` (+ skin) of this rank's box, in (shift, key) order.  Collective."""
        return exchange_ghosts(self.comm, self.dec, self.x, reach, self.keys, skin=skin, domain=self.domain)

    def gather(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The whole set on every rank, in key order: (keys, x (N, d), D (N,), F (N, k)).  Collective;
        output at small scale (one process: its own arrays)."""
        if not self.parallel and np.all(self.keys[1:] > self.keys[:-1]):
            return self.keys, self.x, self.D, self.F
        keys, x, D, F = gather(self.comm, self.keys, self.x, self.D, self.F)
        return keys, x, D, F

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path, meta: dict[str, Any], single: bool = False, **extra: np.ndarray) -> Path:
        """Write the whole set, gathered in key order, to a .npz with ``meta`` (JSON-able) and the
        ``extra`` arrays: ``keys``, ``x``, ``D`` and the fields as ``f`` ((N,) if ``single``, else
        (N, k)).  Rank 0 writes, the others wait for it.  Collective; returns the path written."""
        keys, x, D, F = self.gather()
        out = Path(path)
        if self.comm.rank == 0:
            out = save_results(path, meta, x=x, D=D, f=F[:, 0] if single else F, keys=keys, **extra)
        self.comm.allgather(None)                              # (written before any rank goes on)
        return out

    @classmethod
    def load(cls, path: str | Path, names: Sequence[str], *, domain: Domain, rstar: float,
             comm: Comm | None = None) -> tuple["Particles", dict[str, Any]]:
        """A set written by :meth:`save`, dealt to the ranks of ``comm`` (each rank reads the file and
        keeps the particles its box owns): (this rank's particles, the file's meta).  A file without
        keys numbers its particles 0 .. N - 1.  Collective."""
        meta, arrays = load_results(path)
        x, D = arrays["x"], arrays["D"]
        F = arrays["f"].reshape(x.shape[0], -1)
        keys = arrays["keys"] if "keys" in arrays else np.arange(x.shape[0], dtype=np.int64)
        if keys.shape != (x.shape[0],) or np.any(np.diff(keys) <= 0):
            raise ValueError(f"{path}: its particle keys are not one increasing key per particle")
        out = cls.dealt(x, D, F, names, domain=domain, rstar=rstar, comm=comm)
        out.keys = keys[out.keys]
        return out, meta
