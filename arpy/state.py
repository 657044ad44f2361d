"""The state of a simulation in a file, tied to the run it belongs to: what
:meth:`arpy.Simulation.save_state` writes and :meth:`arpy.Simulation.load_state` reads.

A state file is a NumPy archive of :func:`arpy.io.save_results`, written with its JSON sidecar as one
unit (temporary files moved in place; a path without ``.npz`` gets it, and the path returned is the
file written).  It holds the whole particle set in key order (:meth:`arpy.Particles.save`: ``keys``,
``x``, ``D``, the fields ``f``), the caller's records as ``record_<name>`` (arrays of numbers,
booleans or strings; anything that would need pickling is refused when saving), and as meta:

* ``format``: :data:`FORMAT`, the layout of the file;
* ``t`` and ``steps``: the time and the number of steps taken;
* ``rng``: the state of the simulation's random generator (the insertions of later re-organizations);
* ``step_log``: the per-step log;
* ``records``: the names of the caller's records;
* ``identity``: the identity of the run (:func:`run_identity`): every constructor option that shapes
  the results as a short text (:func:`arpy.distributed.inputs.fingerprint`: numbers exactly, callables
  by their qualified name only, so two closures of one factory with other parameters look the same),
  the initial particle set as its count and a SHA-256 digest of its positions, resolutions and
  initial fields, the random generator and the arpy version;
* ``run``: the caller's own identity of the run (JSON values; for ``arpy run``, the case and its
  options), or None.

The caller's shares (:func:`write_state`'s ``shares``: sets of rows of a rank, each with its keys, e.g.
the particles at an earlier time) are records too: one process writes them as the records
``<set>_<name>`` in key order, without the keys; on P > 1 ranks each rank writes its rows to its piece
(:meth:`arpy.Particles.save` with ``sets``), none gathered, and :meth:`State.shares` gives each rank of
the resuming run its part of them.

A Simulation built with the same arguments and initial particles continues the run from its state
exactly as the run would have gone on, on any number of ranks (with ``verlet_skin`` > 0 the reused
lists start anew, which moves the results by rounding in free space only).

Reading (:func:`read_state`) checks the file: one :class:`arpy.io.StateFileError` naming it if it is
missing, empty, truncated, corrupted or not a state.  It reads no array whole: a record when it is
looked up, the particles when they are dealt (:meth:`State.particles`) and the shares by rows
(:meth:`State.shares`); resumed on P > 1 ranks, a state in one file is read by each rank in its block
of rows (the particles' and the shares'), so that no rank reads the whole set.  :meth:`State.check` then compares identities: a
state of another run (any option, the initial set, the caller's ``run``) is refused with
:class:`StateMismatchError`, which names each difference, e.g. ``nu = 0.01 (now 0.02)``.  Another arpy
version only warns (:class:`StateWarning`): the layout has its own number (``format``, checked), so
the state loads as written, but the continued run may differ by rounding from an uninterrupted run
of either version.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Collection, Mapping, Sequence

import numpy as np

from ._version import __version__
from .distributed.comm import Comm
from .distributed.inputs import fingerprint
from .distributed.reductions import key_chunks
from .domain import Domain
from .io import StateFileError, Stored, json_default, open_results, storable, unreadable
from .particles import PIECES, Particles, SavedSet, block, read_pieces, saved_set, set_arrays

__all__ = ["FORMAT", "IDENTITY_ROWS", "INITIAL", "STATE_FILE", "VERSION", "Records", "Run", "Shares", "State",
           "StateMismatchError", "StateWarning", "as_json", "differences", "read_state", "run_identity", "state_records",
           "write_state"]

#: The caller's identity of a run (JSON values, e.g. the case and options of ``arpy run``).
Run = Mapping[str, Any]
#: The caller's records stored with a state: arrays of numbers, booleans or strings by name.
Records = Mapping[str, Any]
#: The caller's shares stored with a state: sets of rows of this rank by name, each a mapping of arrays with
#: one row per key of its ``keys`` (int (n,)).
Shares = Mapping[str, Mapping[str, np.ndarray]]

#: The layout of a state file (its ``format`` entry); a file of another layout is not read.
FORMAT = 1
#: What a file that is not a readable state is called in the message of its :class:`StateFileError`.
STATE_FILE = "arpy state file"
#: The entry of an identity for the initial particle set.
INITIAL = "initial particles"
#: The entry of an identity for the arpy version (a difference warns, see :class:`StateWarning`).
VERSION = "arpy version"


class StateMismatchError(ValueError):
    """A state file that belongs to another run than the one it is loaded into; ``differences`` lists
    each difference as ``"name = stored (now given)"``, and the message names the file and them."""

    def __init__(self, message: str, differences: list[str]) -> None:
        super().__init__(message)
        self.differences = differences


class StateWarning(UserWarning):
    """A state written by another arpy version: it loads, but the continued run may differ by rounding
    from an uninterrupted run (of either version)."""


#: The rows a rank's share of the initial particles is hashed in at a time (:func:`run_identity` with ``comm``).
IDENTITY_ROWS = 65536


def run_identity(options: Mapping[str, Any], x: np.ndarray, D: np.ndarray, F: np.ndarray,
                 rng: np.random.Generator, *, comm: Comm | None = None, keys: np.ndarray | None = None
                 ) -> dict[str, str]:
    """The identity of a run: ``{option: its fingerprint}`` for each of ``options`` (the values that
    shape the results), :data:`INITIAL`: the number of initial particles and a SHA-256 digest of
    their positions x (N, d), resolutions D (N,) and initial fields F (N, k), the kind of the random
    generator ``rng`` and :data:`VERSION`.  Computed once, when the run is set up (hashing the
    arrays costs about as much as copying them).  With ``comm`` on several ranks, x, D and F are this
    rank's particles with ``keys`` (0 .. N - 1 over the ranks): the digest is that of the whole set in
    key order, hashed :data:`IDENTITY_ROWS` rows at a time (:func:`~arpy.distributed.reductions.key_chunks`;
    collective)."""
    spread = comm if comm is not None and comm.size > 1 else None      # (several ranks)
    if spread is not None and keys is None:
        raise ValueError("run_identity on several ranks needs the particles' keys")
    n = int(np.shape(x)[0]) if spread is None else int(spread.sum(int(np.shape(x)[0])))
    digest = hashlib.sha256()
    for array in (x, D, F):
        a = np.asarray(array, dtype=np.float64)
        digest.update(repr((n, *a.shape[1:])).encode())
        for chunk in (a,) if spread is None or keys is None else key_chunks(spread, keys, a, IDENTITY_ROWS):
            digest.update(np.ascontiguousarray(chunk).reshape(-1).view(np.uint8).data)
    return {**{name: fingerprint(value) for name, value in options.items()},
            INITIAL: f"{n} particles, sha256 {digest.hexdigest()[:16]}",
            "random generator": type(rng.bit_generator).__name__, VERSION: __version__}


def as_json(value: Any) -> Any:
    """``value`` as it comes back from a file's JSON (tuples as lists, NumPy numbers as Python's), to
    compare it with what a file holds."""
    return json.loads(json.dumps(value, default=json_default))


_MISSING = object()


def differences(stored: Mapping[str, Any], now: Mapping[str, Any], *, show: Callable[[Any], str] = str,
                skip: Collection[str] = ()) -> list[str]:
    """``"name = stored (now value)"`` for every name (of either mapping, not in ``skip``) whose values
    differ, the values written by ``show`` ("(not given)" where one mapping lacks the name)."""
    out = []
    for name in dict.fromkeys([*stored, *now]):
        old, new = stored.get(name, _MISSING), now.get(name, _MISSING)
        if name not in skip and old != new:
            text = [("(not given)" if v is _MISSING else show(v)) for v in (old, new)]
            out.append(f"{name} = {text[0]} (now {text[1]})")
    return out


@dataclass(frozen=True)
class State:
    """The contents of a state file (:func:`read_state`), checked to be whole and consistent."""

    path: Path
    """The file."""
    t: float
    """The time."""
    steps: int
    """The number of steps taken."""
    rng: dict[str, Any]
    """The state of the random generator (``bit_generator.state``)."""
    log: list[dict]
    """The per-step log."""
    identity: dict[str, str]
    """The identity of the run (:func:`run_identity`)."""
    run: dict[str, Any] | None
    """The caller's identity of the run (JSON values), or None."""
    records: Stored
    """The caller's records by name (a mapping; each read from the file when looked up)."""
    whole: SavedSet
    """The whole particle set, in key order, as the file holds it (read when dealt: :meth:`particles`)."""
    index: dict[str, Any] | None = None
    """The index of the pieces of a state written on several ranks (None: one file)."""

    def check(self, identity: Mapping[str, str], *, run: Run | None = None, allow: Collection[str] = ()) -> "State":
        """This state, if it belongs to the run with ``identity`` (:func:`run_identity`) and, if given,
        the caller's ``run``; else :class:`StateMismatchError` naming each difference.  Names in
        ``allow`` (entries of the identity, or "run") may differ, e.g. ``allow=("dt",)`` to continue
        on purpose with another step (then not the uninterrupted run).  Another arpy version warns
        (:class:`StateWarning`); the options compared are then those both versions have."""
        unknown = sorted(set(allow) - set(identity) - {"run"})
        if unknown:
            raise ValueError(f"allow names {unknown}, which are not entries of the identity: {sorted(identity)}")
        stored, now = self.identity, dict(identity)
        other_version = stored.get(VERSION) != now.get(VERSION)
        if other_version:
            stored, now = ({k: v for k, v in d.items() if k in stored and k in now} for d in (stored, now))
        differ = differences(stored, now, skip={VERSION, *allow})
        if run is not None and "run" not in allow:
            differ += differences(self.run or {}, as_json(run), show=repr)
        if differ:
            raise StateMismatchError(f"{self.path} holds the state of another run: {'; '.join(differ)}.  A state "
                                     "continues the run of a Simulation built with the same arguments and initial "
                                     "particles (load_state(path, allow=names) accepts named differences)", differ)
        if other_version and VERSION not in allow:
            warnings.warn(f"{self.path} was written by arpy {self.identity.get(VERSION, '(not given)')}, this is "
                          f"arpy {identity.get(VERSION)}: the state loads, but the continued run may differ by "
                          "rounding from an uninterrupted run", StateWarning, stacklevel=3)
        return self

    def particles(self, comm: Comm | None = None, domain: Domain | None = None) -> Particles:
        """The particle set dealt to the ranks of ``comm`` (:meth:`arpy.Particles.from_saved`), in
        ``domain`` if given (the loading simulation's, equal to the file's), without a log.  No rank
        reads the whole set unless P = 1: a state of pieces, each rank every P-th piece; a state in one
        file, rank r its block of rows N r / P .. N (r + 1) / P - 1 of ``x``, ``D``, ``f`` and ``keys``.
        Collective."""
        out = Particles.from_saved(self.whole, comm=comm)
        out.domain, out.log = out.domain if domain is None else domain, []
        return out

    def shares(self, names: Sequence[str], comm: Comm | None = None) -> dict[str, dict[str, np.ndarray]]:
        """This rank's part of the caller's shares ``names`` (:func:`write_state`), each a set of rows with
        their ``keys`` in key order; a name the state does not hold is left out.  A state of pieces: the
        rows of every P-th piece (P the ranks of ``comm``), none gathered; a state in one file (written
        by one process): the records ``<set>_<name>``, rank r of P reads only its block of their rows,
        M r / P .. M (r + 1) / P - 1 (:func:`arpy.particles.block`; all of them on one process), keyed by
        their places.  Not collective."""
        rank, size = (0, 1) if comm is None else (comm.rank, comm.size)
        out = {}
        for name in names:
            if self.index is not None and name in self.index.get("sets", {}):
                out[name] = read_pieces(self.path, self.index, STATE_FILE, of=name, share=(rank, size))
                continue
            columns = {k[len(name) + 1:]: e for k, e in self.records.entries.items() if k.startswith(f"{name}_")}
            if columns:
                lo, hi = block(next(iter(columns.values())).shape[0], rank, size)
                out[name] = {"keys": np.arange(lo, hi, dtype=np.int64), **{k: e.rows(lo, hi) for k, e in columns.items()}}
        return out


def read_state(path: str | Path) -> State:
    """The checked contents of a state file of :func:`write_state`; one :class:`arpy.io.StateFileError`
    naming the file if it is missing, empty, truncated, corrupted (every entry's checksum is checked,
    streaming), of another format or not a state.  Its arrays are not read here: the records when looked
    up, the particles when dealt (:meth:`State.particles`), the shares by rows (:meth:`State.shares`)."""
    path = Path(path)
    meta, arrays = open_results(path, what=STATE_FILE)
    try:
        if meta.get("format") != FORMAT:
            raise ValueError(f"its format is {meta.get('format', '(not given)')}, this arpy reads format {FORMAT} "
                             "(a state of an earlier arpy, or not a state)")
        rng = dict(meta["rng"])
        kind = getattr(np.random, str(rng["bit_generator"]), None)
        if not (isinstance(kind, type) and issubclass(kind, np.random.BitGenerator)):
            raise ValueError(f"its random generator {rng['bit_generator']!r} is not one of NumPy's")
        kind().state = rng                                          # (a state the generator takes)
        identity, run = meta["identity"], meta["run"]
        if not (isinstance(identity, dict) and all(isinstance(v, str) for v in identity.values())):
            raise ValueError("its identity is not a mapping of names to texts")
        if not (run is None or isinstance(run, dict)):
            raise ValueError("its run is not a mapping")
        records = Stored({str(name): arrays[f"record_{name}"] for name in meta["records"]})
        state = State(path, float(meta["t"]), int(meta["steps"]), rng, list(meta["step_log"]), identity, run,
                      records, saved_set(path, meta, arrays, STATE_FILE), meta.get(PIECES))
    except StateFileError:
        raise
    except (KeyError, ValueError, TypeError, AttributeError) as exc:
        raise unreadable(path, STATE_FILE, exc) from exc
    return state


def write_state(path: str | Path, particles: Particles, *, t: float, steps: int, rng: np.random.Generator,
                log: list[dict], identity: Mapping[str, str], single: bool, records: Records | None = None,
                shares: Shares | None = None, run: Run | None = None) -> Path:
    """Write a state file (see the module's docstring for what it holds): ``particles`` (each rank its
    own, in pieces on P > 1 ranks; the fields as ``f`` (N,) if ``single``), the time ``t``, ``steps``,
    the state of ``rng``, the per-step ``log``, the run's ``identity``, the caller's ``records`` (rank
    0's are written), ``shares`` (each rank's own) and ``run``.  A record or share that a state file
    could not load back (an array of Python objects: dicts, ragged rows) raises TypeError naming it, on
    the rank given it, before anything is written.  Collective (rank 0 writes the file, each rank its
    piece); returns the path of the file written."""
    records = dict(records or {})
    sets = {name: {k: storable(f"shares[{name!r}][{k!r}]", v) for k, v in rows.items()}
            for name, rows in (shares or {}).items()}
    if not particles.parallel:                     # (one process: the shares are records, in one file)
        records.update(set_arrays(sets))
        sets = {}
    bad = [name for name in [*records, *sets] if not isinstance(name, str) or not name]
    if bad:
        raise TypeError(f"record and share names must be non-empty strings, got {bad}")
    arrays = {f"record_{name}": storable(f"records[{name!r}]", value) for name, value in records.items()}
    meta = {"format": FORMAT, "t": float(t), "steps": int(steps), "rng": rng.bit_generator.state, "step_log": log,
            "records": sorted(records), "identity": dict(identity), "run": None if run is None else dict(run)}
    return particles.save(path, meta, single, sets=sets, **arrays)


def state_records(path: str | Path) -> dict[str, np.ndarray]:
    """The ``records`` stored with a state by :meth:`arpy.Simulation.save_state` (each read whole)."""
    return dict(read_state(path).records)
