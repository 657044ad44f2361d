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

import glob
import secrets
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, NamedTuple, Sequence

import numpy as np

from .distributed import (Comm, Decomposition, GhostLayer, SerialComm, agree, bisect, exchange_ghosts, gather, h_min,
                          migrate, scatter)
from .distributed.reductions import Reductions, key_places
from .domain import Domain, as_domain
from .io import Entry, StateFileError, load_results, npz_path, open_results, save_results, unreadable
from .lists.neighborlist import NeighborList
from .lists.search import cache_order, neighbor_list
from ._validate import resolve_full

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from .distributed.balance import CostBalance

__all__ = ["PARTICLE_FILE", "PIECES", "Particles", "SavedSet", "block", "log_arrays", "of_particles", "piece_path",
           "read_piece", "read_pieces", "remove_pieces", "sampled", "save_pieces", "saved_rows", "saved_set",
           "set_arrays"]


def log_arrays(log: list[dict], empty: Mapping[str, type] | None = None) -> dict[str, np.ndarray]:
    """A list of per-iteration (or per-step) dicts as arrays, one per key present in every entry; with no
    entries, one empty array per key of ``empty`` (of its type)."""
    if not log:
        return {k: np.empty(0, t) for k, t in (empty or {}).items()}
    return {k: np.array([e[k] for e in log]) for k in log[0] if all(k in e for e in log)}


class Particles(Reductions):
    """This rank's particles of a set spread over the ranks of ``comm`` (one process: all of them).

    :func:`arpy.self_organize` returns one (with ``n_star``, ``log`` and ``converged`` of the
    adaptation); :class:`arpy.Simulation` keeps its state in one (``sim.particles``, with the fields).

    Attributes
    ----------
    x : float64 array (n, d)
        Positions of this rank's particles.
    D : float64 array (n,)
        Their resolution D_p (length unit of x); the core sizes (= cutoff radii) are ``rstar * D``.
    rstar : float
        Core size over D.
    n_star : int or None
        The wanted number of neighbours N* of an adapted set (None: not adapted).
    domain : Domain
        Where the particles live (a box, or free space; default free space).
    log : list of dict
        Of an adapted set, one dict per iteration of the adaptation: ``iteration, n, fused,
        inserted, removed, energy_before, energy, gamma, trials, min_neighbors, max_ratio``, timings
        ``t_fuse_insert, t_resolution, t_lists, t_forces, t_total`` in seconds, and ``moved``
        (whether a step was accepted); see :meth:`history`.
    converged : bool
        Of an adapted set: whether the stopping rule was met (else max_iter ran out or the descent
        stalled).
    keys : int64 array (n,)
        The particles' global keys, distinct over the ranks (default ``0 .. n - 1``).
    F : float64 array (n, k)
        Their fields, one column per name in ``names`` (default none: (n, 0)).
    names : tuple of str
        The fields' names.
    decomposition : Decomposition
        The ranks' boxes; this rank owns the particles in ``decomposition.box(comm.rank)`` (default,
        one process: one box around every particle).
    comm : Comm
        The ranks (default :class:`arpy.distributed.SerialComm`: one process, P = 1).

    Examples
    --------
    >>> import numpy as np
    >>> import arpy
    >>> def wavy(p):
    ...     return 0.06 * (1 + 0.5 * np.sin(2 * np.pi * p[:, 0]))
    >>> box = arpy.Domain([1.0, 1.0], periodic=True)
    >>> ps = arpy.self_organize(np.random.default_rng(2).random((200, 2)), wavy, domain=box, seed=2)
    >>> ps.d, ps.n_star, ps.converged
    (2, 10, True)
    >>> ps.x.shape == (ps.n, 2) and ps.D.shape == ps.rc.shape == (ps.n,)
    True
    >>> len(ps.history()["n"]) == len(ps.log)
    True

    ``ps.save(path)`` and ``arpy.Particles.load(path)`` write and read it; ``ps.plot()`` draws
    it (with matplotlib).
    """

    x: np.ndarray
    D: np.ndarray
    rstar: float
    n_star: int | None
    domain: Domain
    log: list[dict]
    converged: bool
    keys: np.ndarray
    F: np.ndarray
    names: tuple[str, ...]
    decomposition: Decomposition
    comm: Comm

    def __init__(self, x: np.ndarray, D: np.ndarray, rstar: float, n_star: int | None = None,
                 domain: Domain | None = None, log: list[dict] | None = None, converged: bool = False, *,
                 keys: np.ndarray | None = None, F: np.ndarray | None = None, names: Sequence[str] = (),
                 decomposition: Decomposition | None = None, comm: Comm | None = None) -> None:
        self.x, self.D = np.asarray(x, dtype=np.float64), np.asarray(D, dtype=np.float64)
        if self.x.ndim != 2 or self.D.shape != (self.x.shape[0],):
            raise ValueError(f"x must have shape (n, d) and D shape (n,), got {self.x.shape} and {self.D.shape}")
        n = self.x.shape[0]
        self.rstar, self.n_star = float(rstar), None if n_star is None else int(n_star)
        self.domain = as_domain(domain)
        self.log, self.converged = list(log or []), bool(converged)
        self.names, self.comm = tuple(names), comm or SerialComm()
        self.keys = np.arange(n, dtype=np.int64) if keys is None else np.asarray(keys)
        self.F = np.zeros((n, len(self.names))) if F is None else np.asarray(F)
        if self.keys.shape != (n,) or self.F.shape != (n, len(self.names)):
            raise ValueError(f"keys must have shape ({n},) and F ({n}, {len(self.names)}) for the fields "
                             f"{list(self.names)}, got {self.keys.shape} and {self.F.shape}")
        if decomposition is None:
            if self.comm.size > 1:
                raise ValueError("a share of a set on several ranks needs its decomposition")
            decomposition = bisect(self.x, 1, domain=self.domain)[0]
        self.decomposition = decomposition

    @classmethod
    def dealt(cls, x: np.ndarray, D: np.ndarray, F: np.ndarray, names: Sequence[str], *, domain: Domain,
              rstar: float, comm: Comm | None = None, deal: np.ndarray | None = None) -> "Particles":
        """The same whole set (x (n, d), D (n,), F (n, k)) given on every rank -> this rank's share,
        keyed by index: the ranks take the particles ``deal`` gives them (the rank of each particle,
        int (n,), the same on every rank; default every P-th from the rank's number), bisect the
        domain and migrate to the boxes.  Collective."""
        comm = comm or SerialComm()
        dec, xs, keys, got = scatter(comm, x, {"D": D, "F": F}, domain=domain, deal=deal,
                                     same={"field names": tuple(names), "rstar": rstar})
        return cls._owned(xs, keys, got, names, domain=domain, rstar=rstar, dec=dec, comm=comm)

    @classmethod
    def from_shares(cls, x: np.ndarray, D: np.ndarray, F: np.ndarray, names: Sequence[str], keys: np.ndarray, *,
                    domain: Domain, rstar: float, comm: Comm) -> "Particles":
        """A set given in shares (each rank some of its particles: x (n, d), D (n,), F (n, k) with their
        ``keys``, distinct over the ranks) -> this rank's particles as :meth:`dealt` deals the whole set
        gathered in key order: keyed by their places in key order (0 .. N - 1,
        :func:`~arpy.distributed.reductions.key_places`), in the boxes of the domain bisected over every
        rank's particles, with no rank holding more than its share and the keys.  First checks that the
        ranks were given the same field names, ``rstar`` and domain, in one collective
        (:func:`~arpy.distributed.inputs.agree`: ValueError on every rank, naming what differs).  Collective."""
        agree(comm, "Particles.from_shares", **{"field names": tuple(names), "rstar": rstar, "domain": domain})
        return cls._bisected(x, key_places(comm, keys), {"D": D, "F": F}, names, domain=domain, rstar=rstar,
                             comm=comm)

    @classmethod
    def _bisected(cls, x: np.ndarray, keys: np.ndarray, got: dict[str, np.ndarray], names: Sequence[str], *,
                  domain: Domain, rstar: float, comm: Comm) -> "Particles":
        """Some particles of a set on each rank (x, keys, ``got`` D and F; each particle on one rank) ->
        this rank's particles: those in its box of the domain bisected over every rank's particles,
        migrated there (in key order), then in cache order (on several ranks).  Collective."""
        dec, _ = bisect(x, comm.size, domain=domain, comm=comm)
        xs, ks, fields = migrate(comm, dec, x, keys, got)                          # (in key order)
        return cls._owned(xs, ks, fields, names, domain=domain, rstar=rstar, dec=dec, comm=comm)

    @classmethod
    def _owned(cls, x: np.ndarray, keys: np.ndarray, got: dict[str, np.ndarray], names: Sequence[str], *,
               domain: Domain, rstar: float, dec: Decomposition, comm: Comm) -> "Particles":
        """The particles a rank owns after a deal or a migration (x, keys, ``got`` D and F), each rank's
        in cache order."""
        out = cls(x, got["D"], rstar, domain=domain, keys=keys, F=got["F"], names=tuple(names), decomposition=dec,
                  comm=comm)
        if out.parallel:
            out.reorder(cache_order(out.x, domain=out.domain))
        return out

    # ------------------------------------------------------------------ sizes
    @property
    def n(self) -> int:
        """The number of this rank's particles."""
        return int(self.x.shape[0])

    @property
    def d(self) -> int:
        """The dimension."""
        return int(self.x.shape[1])

    @property
    def eps(self) -> np.ndarray:
        """Core sizes = cutoff radii ``rstar * D``, (n,)."""
        return self.rstar * self.D

    @property
    def rc(self) -> np.ndarray:
        """Cutoff radii r_c,p = r* D_p (the core sizes :attr:`eps`), (n,)."""
        return self.eps

    def __repr__(self) -> str:
        parts = [f"n={self.n}", f"d={self.d}"]
        if self.n:
            parts.append(f"D in [{self.D.min():.3g}, {self.D.max():.3g}]")
        parts.append(f"r*={self.rstar:.3g}")
        if self.n_star is not None:
            parts.append(f"N*={self.n_star}")
        if self.names:
            parts.append(f"fields={list(self.names)}")
        parts.append(repr(self.domain))
        if self.log:
            parts.append(f"{len(self.log)} iterations, {'converged' if self.converged else 'not converged'}")
        if self.parallel:
            parts.append(f"rank {self.comm.rank} of {self.comm.size}")
        return f"Particles({', '.join(parts)})"

    def neighbor_list(self, *, full: bool = False, symmetric: bool | None = None) -> NeighborList:
        """Neighbour lists of this rank's particles under the min rule (minimum image along periodic
        axes; on several ranks, among this rank's particles only): a half list, or with ``full`` a full
        one (``symmetric``: the deprecated name of ``not full``)."""
        full = resolve_full(full, symmetric, "Particles.neighbor_list")
        return neighbor_list(self.x, self.rc, method="auto", full=full, domain=self.domain)

    def history(self) -> dict[str, np.ndarray]:
        """The adaptation's log as arrays, one per key."""
        return log_arrays(self.log)

    def plot(self, ax: "Axes | None" = None, **kwargs: Any) -> "Axes":
        """Draw the particles (see :func:`arpy.plotting.plot_particles`)."""
        from .plotting import plot_particles

        return plot_particles(self, ax=ax, **kwargs)

    @property
    def parallel(self) -> bool:
        """Whether the set is spread over more than one rank."""
        return self.comm.size > 1

    def h_min(self) -> float:
        """The smallest distance between two particles of the whole set (minimum image along periodic
        axes).  Collective."""
        return h_min(self.comm, self.decomposition, self.x, self.eps, self.keys, self.domain)

    # ------------------------------------------------------------------ moving particles
    def migrate(self, balance: "CostBalance | None" = None) -> None:
        """Each particle (with D and fields) to the rank whose box holds it, then in cache order (the
        order in memory changes no result: rows and sums go by key).  With ``balance`` (every rank
        gives one), the boxes are first cut anew by the particles' costs when its survey finds the
        work uneven (:class:`arpy.distributed.balance.CostBalance`).  One process keeps its order.
        Collective."""
        if self.parallel:               # (one rank owns everything in its box, in the order it has)
            if balance is not None:
                dest = self.decomposition.locate(self.x)
                balance.survey(np.bincount(dest[dest >= 0], minlength=self.comm.size))
                if balance.due():
                    self.decomposition = bisect(self.x, self.comm.size, weights=balance.weights(self.n),
                                                domain=self.domain, comm=self.comm)[0]
                    balance.cut()
            self.x, self.keys, got = migrate(self.comm, self.decomposition, self.x, self.keys, {"D": self.D, "F": self.F})
            self.D, self.F = got["D"], got["F"]
            self.reorder(cache_order(self.x, domain=self.domain))

    def reorder(self, perm: np.ndarray) -> None:
        """This rank's particles put in the order ``perm`` (nothing else changes)."""
        self.x, self.keys, self.D, self.F = self.x[perm], self.keys[perm], self.D[perm], self.F[perm]

    def ghosts(self, reach: np.ndarray, skin: float = 0.0) -> GhostLayer:
        """The ghosts of this rank: the particles of other ranks (and periodic images) within their own
        ``reach`` (+ skin) of this rank's box, in (shift, key) order.  Collective."""
        return exchange_ghosts(self.comm, self.decomposition, self.x, reach, self.keys, skin=skin, domain=self.domain)

    def gather(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The whole set on every rank, in key order: (keys, x (N, d), D (N,), F (N, k)).  Collective;
        output at small scale (one process: its own arrays)."""
        if not self.parallel:
            return self.ordered()
        keys, x, D, F = gather(self.comm, self.keys, self.x, self.D, self.F)
        return keys, x, D, F

    def ordered(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """This rank's particles in key order, with no communication: (keys, x (n, d), D (n,), F (n, k));
        one process: the whole set, as :meth:`gather` gives it (its own arrays if already in order)."""
        if np.all(self.keys[1:] > self.keys[:-1]):
            return self.keys, self.x, self.D, self.F
        order = np.argsort(self.keys, kind="stable")
        return self.keys[order], self.x[order], self.D[order], self.F[order]

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path, meta: dict[str, Any] | None = None, single: bool = False, *,
             sets: Mapping[str, Mapping[str, np.ndarray]] | None = None, **extra: np.ndarray) -> Path:
        """Write the set to a .npz (with a .json sidecar, both written as one unit by
        :func:`arpy.io.save_results`; ``.npz`` appended to a path without it).  One process: the
        file holds ``keys``, ``x``, ``D``, the fields as ``f`` ((N,) if ``single``, else (N, k); none
        without fields) in key order.  On P > 1 ranks no rank gathers the set: each writes its own
        particles, in key order, to a piece beside the file (``<name>.part<r>-of-<P>.npz``, the same
        arrays), and the file is the index of the pieces (their names, counts and a token that ties
        them to it), written by rank 0 once every piece is.  Either way the file holds the ``extra``
        arrays and as meta r*, N*, the domain, the field names, the log and ``converged``, updated
        with ``meta`` (JSON-able).  ``sets``: more sets of rows of this rank, each with its own ``keys``
        (e.g. the particles at an earlier time): one process writes them to the file as
        ``<set>_<name>`` in key order without the keys (:func:`set_arrays`), P > 1 ranks each its own to
        its piece (:func:`save_pieces`).  Collective; returns the path of the file written (on every rank)."""
        clash = sorted(set(meta or {}) & {"rstar", "n_star", "converged", "domain", "fields", "log", PIECES})
        if clash:
            raise ValueError(f"meta must not set the container's own entries {clash}")
        own = {"rstar": self.rstar, "n_star": self.n_star, "converged": self.converged,
               "domain": self.domain.state(), "fields": list(self.names), "log": self.log}
        if not self.parallel:
            keys, x, D, F = self.ordered()
            return save_results(path, {**own, **(meta or {})}, **self._arrays(keys, x, D, F, single), **extra,
                                **set_arrays(sets))
        out = npz_path(path)
        return save_pieces(self.comm, out, self._arrays(self.keys, self.x, self.D, self.F, single),
                           lambda index: save_results(out, {**own, **(meta or {}), PIECES: {**index, "d": self.d}},
                                                      **extra), sets)

    def _arrays(self, keys: np.ndarray, x: np.ndarray, D: np.ndarray, F: np.ndarray, single: bool
                ) -> dict[str, np.ndarray]:
        arrays = dict(x=x, D=D, keys=keys)
        if self.names:
            arrays["f"] = F[:, 0] if single else F
        return arrays

    @classmethod
    def load(cls, path: str | Path, *, comm: Comm | None = None) -> "Particles":
        """A set written by :meth:`save`, dealt to the ranks of ``comm`` (each keeps the particles its
        box owns, having read only a share of the file's: :meth:`from_saved`; one process: all of them,
        in key order).  Collective."""
        return cls.read(path, comm=comm)[0]

    @classmethod
    def read(cls, path: str | Path, *, comm: Comm | None = None) -> tuple["Particles", dict[str, Any]]:
        """As :meth:`load`, with the file's meta: (this rank's particles, meta).  A file without keys
        numbers its particles 0 .. N - 1.  A file that is not such a set raises
        :class:`arpy.io.StateFileError` naming it.  Collective."""
        meta, arrays = open_results(path, what=PARTICLE_FILE)
        return cls.from_saved(saved_set(path, meta, arrays), comm=comm), meta

    @classmethod
    def from_saved(cls, saved: "SavedSet", *, comm: Comm | None = None) -> "Particles":
        """The set of a file of :meth:`save` (read by :func:`saved_set`), dealt to the ranks of
        ``comm``; no rank reads the whole set unless P = 1.  A file of pieces: each rank reads every
        P-th piece; one file on P ranks: rank r reads its block of rows, N r / P .. N (r + 1) / P - 1
        (:func:`block`, :func:`saved_rows`; memory: those rows).  Either way the ranks then bisect the
        domain over what they read, migrate to the boxes (in key order) and put their particles in cache
        order, the same bits for any P.  One file on one process: the whole set, read and dealt as
        :meth:`dealt` deals it.  Collective."""
        comm = comm or SerialComm()
        if not saved.pieces and comm.size == 1:
            x, D, F, keys = saved_rows(saved, 0, saved.n)
            out = cls.dealt(x, D, F, saved.names, domain=saved.domain, rstar=saved.rstar, comm=comm)
            out.keys = keys[out.keys]
        else:
            if saved.pieces:
                got = [read_piece(p, saved) for p in saved.pieces[comm.rank::comm.size]]
                got = got or [saved_rows(saved, 0, 0)]                      # (no piece for this rank)
            else:
                got = [saved_rows(saved, *block(saved.n, comm.rank, comm.size))]
            x, D, F, keys = (np.concatenate([g[i] for g in got]) for i in range(4))
            out = cls._bisected(x, keys, {"D": D, "F": F}, saved.names, domain=saved.domain, rstar=saved.rstar,
                                comm=comm)
        out.n_star, out.converged, out.log = saved.n_star, saved.converged, list(saved.log)
        return out


#: What :meth:`Particles.read` calls a file it reads (in the message of a file that is not one).
PARTICLE_FILE = "arpy particle file"


class SavedSet(NamedTuple):
    """A whole particle set as a file of :meth:`Particles.save` holds it, in key order: its arrays as the
    file has them, read by :func:`saved_rows` (one process the whole set, each of P ranks a block)."""

    rows: Mapping[str, "np.ndarray | Entry"]
    """The per-particle arrays by their names in the file: ``x`` (N, d), ``D`` (N,), of a set with
    fields ``f`` ((N,) or (N, k)), and ``keys`` (N,) if the file has them; in memory, or
    :class:`arpy.io.Entry` of the file, read when asked.  A file of pieces: the arrays without rows."""
    n: int
    """The number of particles N (0 for a file of pieces)."""
    d: int
    """The dimension."""
    names: tuple[str, ...]
    """Field names."""
    domain: Domain
    """The domain."""
    rstar: float
    """Core size over D."""
    n_star: int | None
    """N* of an adapted set."""
    converged: bool
    """Whether the adaptation converged."""
    log: list[dict]
    """The adaptation's log."""
    path: Path
    """The file (named by the errors of :func:`saved_rows`)."""
    what: str = PARTICLE_FILE
    """What the file is called in those errors."""
    pieces: tuple[Path, ...] = ()
    """A file of pieces (written on several ranks): their paths, in rank order (each rank reads its
    pieces, :meth:`Particles.from_saved`)."""
    counts: tuple[int, ...] = ()
    """The pieces' particle counts."""
    token: str = ""
    """The token that ties the pieces to their index."""


def saved_set(path: str | Path, meta: dict[str, Any], arrays: Mapping[str, "np.ndarray | Entry"],
              what: str = PARTICLE_FILE) -> SavedSet:
    """The particle set in the contents (meta, arrays or their :class:`arpy.io.Entry`) of a file of
    :meth:`Particles.save`, checked as far as the arrays' shapes go (the keys' order when their rows are
    read, :func:`saved_rows`): :class:`arpy.io.StateFileError` naming ``path`` (as not a readable
    ``what``) if an entry is missing or does not fit the others.  A file of pieces gives their paths, not
    the particles."""
    try:
        names = tuple(str(name) for name in meta.get("fields", ["f"] if "f" in arrays else []))
        n_star = meta.get("n_star")
        domain = Domain.from_state(meta.get("domain", {}))
        common: dict[str, Any] = dict(names=names, domain=domain, rstar=float(meta["rstar"]),
                                      n_star=None if n_star is None else int(n_star),
                                      converged=bool(meta.get("converged", False)), log=list(meta.get("log", [])),
                                      path=Path(path), what=what)
        if PIECES in meta:
            index = meta[PIECES]
            files, counts, token = list(index["files"]), [int(c) for c in index["counts"]], str(index["token"])
            if not files or len(counts) != len(files) or min(counts) < 0 or not token:
                raise ValueError("its index of pieces is not one count per piece with a token")
            d = int(index["d"])
            none = {"x": np.zeros((0, d)), "D": np.zeros(0), "f": np.zeros((0, len(names))), "keys": np.zeros(0, np.int64)}
            return SavedSet(none, 0, d, **common, pieces=tuple(Path(path).parent / str(f) for f in files),
                            counts=tuple(counts), token=token)
        x, D = arrays["x"], arrays["D"]
        if len(x.shape) != 2 or D.shape != (x.shape[0],):
            raise ValueError(f"its positions x {x.shape} and resolutions D {D.shape} are not (N, d) and (N,)")
        n = x.shape[0]
        rows = {"x": x, "D": D}
        if names:
            f = arrays["f"]
            columns = int(np.prod(f.shape[1:])) if f.shape[:1] == (n,) else -1
            if columns != len(names):
                raise ValueError(f"its fields {list(names)} do not match its f {f.shape}")
            rows["f"] = f
        if "keys" in arrays:
            if arrays["keys"].dtype.kind not in "iu" or arrays["keys"].shape != (n,):
                raise ValueError("its particle keys are not one increasing integer key per particle")
            rows["keys"] = arrays["keys"]
        return SavedSet(rows, n, x.shape[1], **common)
    except (KeyError, ValueError, TypeError, AttributeError) as exc:
        raise unreadable(path, what, exc) from exc


def block(n: int, rank: int, size: int) -> tuple[int, int]:
    """The rows (lo, hi) of ``n`` that rank ``rank`` of ``size`` reads of one file: lo = n rank / size,
    hi = n (rank + 1) / size (rounded down), contiguous and together each row once."""
    return n * rank // size, n * (rank + 1) // size


def saved_rows(saved: SavedSet, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rows lo .. hi - 1 of a saved set (0 <= lo <= hi <= N): (x (m, d), D (m,), F (m, k), keys (m,)),
    read from the file if not in memory (those rows only, and the key before them: the keys must
    increase); a file without keys numbers its particles 0 .. N - 1.  :class:`arpy.io.StateFileError`
    naming the file if they do not fit."""
    def take(a: "np.ndarray | Entry", first: int = lo) -> np.ndarray:
        return a.rows(first, hi) if isinstance(a, Entry) else np.asarray(a)[first:hi]

    m = hi - lo
    try:
        x = take(saved.rows["x"]).astype(np.float64, copy=False)
        D = take(saved.rows["D"]).astype(np.float64, copy=False)
        F = take(saved.rows["f"]).astype(np.float64, copy=False).reshape(m, len(saved.names)) if saved.names \
            else np.zeros((m, 0))
        if "keys" not in saved.rows:
            return x, D, F, np.arange(lo, hi, dtype=np.int64)
        keys = take(saved.rows["keys"], max(lo - 1, 0))
        if np.any(np.diff(keys) <= 0):
            raise ValueError("its particle keys are not one increasing integer key per particle")
    except StateFileError:
        raise
    except (ValueError, TypeError) as exc:
        raise unreadable(saved.path, saved.what, exc) from exc
    return x, D, F, keys[keys.size - m:].astype(np.int64)


#: The meta entry of a particle file that is the index of pieces written on several ranks.
PIECES = "pieces"


def piece_path(path: Path, rank: int, parts: int) -> Path:
    """The piece of rank ``rank`` of ``parts`` beside the file ``path`` (``run.npz`` ->
    ``run.part00001-of-00004.npz``)."""
    return path.with_name(f"{path.stem}.part{rank:05d}-of-{parts:05d}.npz")


def remove_pieces(path: Path, keep: Sequence[str] = ()) -> None:
    """Delete the pieces beside the file ``path`` (and their sidecars), but those named in ``keep``."""
    for piece in path.parent.glob(glob.escape(path.stem) + ".part*-of-*.npz"):
        if piece.name not in keep:
            piece.unlink(missing_ok=True)
            piece.with_suffix(".json").unlink(missing_ok=True)


def save_pieces(comm: Comm, path: Path, rows: dict[str, np.ndarray], write_index: Callable[[dict[str, Any]], Path],
                sets: Mapping[str, Mapping[str, np.ndarray]] | None = None) -> Path:
    """Write arrays with one row per particle of every rank with no rank holding more than its own
    (output at large scale): each rank writes its rows, in the order of their ``keys`` (a row of
    ``rows``, int (n,)), to its piece beside ``path`` (:func:`piece_path`, by
    :func:`arpy.io.save_results`), and once every piece is written rank 0 calls ``write_index(index)``,
    which writes the file ``path`` with the ``index`` of the pieces in it (``files``: their names in
    rank order, ``counts``: their rows, ``token``: a token the pieces hold too), and removes the
    pieces of an earlier write of ``path`` on another rank count.  ``sets``: more sets of rows of this
    rank, each with its own ``keys`` (e.g. the particles at an earlier time; the same names on every
    rank), written to the piece too, each in the order of its keys, as ``<set>.<name>``; the index then
    gives their rows per piece (``sets``: {set: counts}; read back by :func:`read_pieces` with ``of=``).
    Collective; returns ``path``."""
    token = comm.allgather(secrets.token_hex(16) if comm.rank == 0 else None)[0]
    keys = np.asarray(rows["keys"])
    more = {f"{name}.{k}": a for name, got in (sets or {}).items() for k, a in _in_key_order(got).items()}
    save_results(piece_path(path, comm.rank, comm.size), {"piece": comm.rank, "of": comm.size, "token": token},
                 **_in_key_order(rows), **more)
    counts = comm.allgather([int(keys.size), *(int(np.size(got["keys"])) for got in (sets or {}).values())])
    if comm.rank == 0:
        index: dict[str, Any] = {"files": [piece_path(path, r, comm.size).name for r in range(comm.size)],
                                 "counts": [c[0] for c in counts], "token": token}
        if sets:
            index["sets"] = {name: [c[1 + i] for c in counts] for i, name in enumerate(sets)}
        write_index(index)
        remove_pieces(path, keep=index["files"])             # (an earlier write's on another rank count)
    comm.allgather(None)                                     # (written before any rank goes on)
    return path


def _in_key_order(rows: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rows with their ``keys`` (int (n,)) put in the order of the keys."""
    order = np.argsort(np.asarray(rows["keys"]), kind="stable")
    return {name: np.asarray(a)[order] for name, a in rows.items()}


def set_arrays(sets: Mapping[str, Mapping[str, np.ndarray]] | None) -> dict[str, np.ndarray]:
    """Sets of rows (each with its ``keys``) of one process as the arrays of its file: ``<set>_<name>`` in
    key order, without the keys (as one process writes its particles' rows)."""
    return {f"{name}_{k}": a for name, got in (sets or {}).items() for k, a in _in_key_order(got).items()
            if k != "keys"}


def _piece(path: Path, count: int, token: str, what: str) -> dict[str, np.ndarray]:
    """The arrays of a piece written by :func:`save_pieces`, checked against its index (its ``count`` of
    rows and ``token``): :class:`arpy.io.StateFileError` naming the piece (as not a readable ``what``)
    if it is not one of that index's."""
    meta, arrays = load_results(path, what=what)
    try:
        if meta.get("token") != token:
            raise ValueError("it belongs to another save than its index (a save of the same name that did not "
                             "complete, or pieces copied from elsewhere)")
        n = len(arrays["keys"]) if "keys" in arrays else len(arrays["x"])
        if n != count:
            raise ValueError(f"it holds {n} particles, its index says {count}")
    except (KeyError, ValueError) as exc:
        raise unreadable(path, what, exc) from exc
    return arrays


def sampled(keys: np.ndarray, fraction: float) -> np.ndarray:
    """Which of the particles with these ``keys`` (integers (n,)) are in the sample of about ``fraction``
    of them (bool (n,)): those whose key's hash (splitmix64's finaliser) falls below ``fraction`` of its
    range.  The choice of a particle depends on its key alone, so that a sample drawn from every rank's
    rows, or from pieces read one at a time, is the one-process sample; with ``fraction >= 1``, all."""
    if fraction >= 1.0:
        return np.ones(len(keys), bool)
    z = np.asarray(keys).astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    with np.errstate(over="ignore"):
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z ^= z >> np.uint64(31)
    return z < np.uint64(max(fraction, 0.0) * 2.0 ** 64)


def read_pieces(path: str | Path, index: dict[str, Any], what: str = "piece of an arpy results file", *,
                of: str | None = None, share: tuple[int, int] | None = None,
                fraction: float = 1.0) -> dict[str, np.ndarray]:
    """The rows of every piece named by ``index`` (of the file ``path``, :func:`save_pieces`), read back
    and put in the order of their keys: the arrays the one-process run writes, with ``keys``; with
    ``of``, those of that set of rows (by their names in the set, with ``keys``).  It holds the whole
    set: output at small scale (a test); ``fraction`` < 1: only the rows of the sample of about that
    fraction of them (:func:`sampled`; each piece read, then cut to its sample, in turn: what a figure of
    any size needs); ``share`` = (r, P): only every P-th piece from the r-th (rank r's share of them when
    P ranks read; none when r is beyond the pieces: the arrays without rows).
    :class:`arpy.io.StateFileError` names a piece that is missing or not of this index."""
    folder = Path(path).parent
    every = list(zip(index["files"], index["counts"], index.get("sets", {}).get(of, index["counts"])))
    files = every if share is None else every[share[0]::share[1]]
    sets = index.get("sets", {})
    pieces = []
    for f, c, c_of in files or every[:1]:
        got = _piece(folder / str(f), int(c), str(index["token"]), what)
        if of is None:
            got = {k: a for k, a in got.items() if k.split(".")[0] not in sets}
        else:
            got = {k[len(of) + 1:]: a for k, a in got.items() if k.startswith(f"{of}.")}
            if "keys" not in got or len(got["keys"]) != int(c_of):
                raise unreadable(folder / str(f), what, ValueError(f"its set {of!r} is not the {c_of} rows of its index"))
        if fraction < 1.0:
            keep = sampled(got["keys"], fraction)
            got = {k: a[keep] for k, a in got.items()}
        pieces.append(got)
    if not pieces:
        return {}
    keys = np.concatenate([p["keys"] for p in pieces])
    order = np.argsort(keys, kind="stable")[:keys.size if files else 0]      # (no piece of this share: no rows)
    return {name: np.concatenate([p[name] for p in pieces])[order] for name in pieces[0]}


def read_piece(path: Path, saved: SavedSet) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One piece of a file of pieces, checked against its index ``saved``: (x, D, F, keys);
    :class:`arpy.io.StateFileError` naming the piece if it is not one of that file's."""
    what = "piece of an arpy particle file"
    try:
        rank = saved.pieces.index(path)
    except ValueError as exc:
        raise unreadable(path, what, exc) from exc
    arrays = _piece(path, saved.counts[rank], saved.token, what)
    one = saved_set(path, {"rstar": saved.rstar, "fields": list(saved.names)}, arrays, what)
    return saved_rows(one, 0, one.n)


def of_particles(name: str, doc: str) -> property:
    """A property of an object holding its particles as ``particles`` (e.g. :class:`arpy.Simulation`)
    that reads and writes their attribute ``name``."""

    def get(sim: Any) -> np.ndarray:
        return getattr(sim.particles, name)

    def put(sim: Any, value: np.ndarray) -> None:
        setattr(sim.particles, name, value)

    return property(get, put, doc=doc)
