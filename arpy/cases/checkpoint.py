"""Checkpoint and restart of a case's simulation (``arpy run CASE --checkpoint-every K --resume``).

A :class:`Checkpoint` names a state file.  Every ``every`` steps the case's simulation writes its
state there (:meth:`arpy.Simulation.save_state`, data and sidecar as one unit) together with the
case's own records (error or mass histories, snapshots), and the initial particle set and the case's
parameters beside it once.  A run started with ``resume=True`` loads them instead of self-organizing
the initial set and continues from the state: its results equal those of an uninterrupted run bit
for bit.  A distributed run (the case's ``comm``) writes the state and the initial set in pieces (each
rank its particles and its rows of the case's snapshots, rank 0 the index with the records; nothing
is gathered), and resumes on any number of ranks, or on one process.

The three files belong to one run: each holds the run's parameters (:attr:`Checkpoint.identity`, the case
and its options but those a resumed run may change), and the state also the simulation's identity
(:mod:`arpy.state`).  A resume refuses files of another run, naming each difference (``D0 = 0.25 (now
0.24)``): a checkpoint copied from another run, or left by an earlier run with other options.  A
run started afresh that writes checkpoints replaces an earlier run's files in its folder (and says
so on stderr); one that writes none leaves them.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..io import StateFileError, open_results, replace_atomically, unreadable
from ..particles import PARTICLE_FILE, Particles, remove_pieces
from ..simulation import Simulation
from ..state import Shares, State, StateMismatchError, as_json, differences, read_state
from ..timeseries import TimeSeries

__all__ = ["Checkpoint"]


@dataclass(frozen=True)
class Checkpoint:
    """Where a case's simulation keeps its state, how often, and whether it starts from it.

    Parameters
    ----------
    path : Path
        The state file (.npz); the initial particle set goes to ``<stem>_initial.npz`` and the
        case's parameters to ``<stem>_case.json`` beside it.
    every : int
        Time steps between writes of the state (0: never).
    resume : bool
        Start from the files instead of from the beginning.
    parameters : dict
        What the run was started with (JSON values).  On resume they must equal those stored,
        except the keys in ``free`` (e.g. the final time, which a resumed run may extend).
    free : tuple of str
        Parameters a resumed run may change.
    comm : Comm, optional
        The ranks of a distributed run: every rank calls the methods, rank 0 writes the files.
    series : TimeSeries, optional
        The run's particles over time (:class:`arpy.timeseries.TimeSeries`): its first frame when the
        run starts (on resume its frames up to the state's time kept), its last when the run ends.
    """

    path: Path
    every: int = 0
    resume: bool = False
    parameters: dict[str, Any] = field(default_factory=dict)
    free: tuple[str, ...] = ("T",)
    comm: Any = None
    series: TimeSeries | None = None
    #: On resume, the state once read (:meth:`resumed`), until :meth:`run` has restored it.
    _read: dict[str, State] = field(default_factory=dict, init=False, repr=False, compare=False)

    def resumed(self) -> State:
        """The state to resume from, read once: :func:`arpy.state.read_state` streams the whole file
        through its checksums, and a resume needs it in :meth:`check`, :meth:`shares` and :meth:`run`.
        Kept until :meth:`run` has restored it (the run then writes the file anew)."""
        if "state" not in self._read:
            self._read["state"] = read_state(self.path)
        return self._read["state"]

    @property
    def writer(self) -> bool:
        """Whether this process writes the files (one process, or rank 0)."""
        return self.comm is None or self.comm.rank == 0

    @property
    def initial(self) -> Path:
        """The file of the initial particle set."""
        return self.path.with_name(self.path.stem + "_initial.npz")

    @property
    def case_file(self) -> Path:
        """The file of the parameters the run was started with."""
        return self.path.with_name(self.path.stem + "_case.json")

    @property
    def identity(self) -> dict[str, Any]:
        """The run's identity in its files: the parameters but the ``free`` ones."""
        return {k: v for k, v in self.parameters.items() if k not in self.free}

    def check(self) -> float | None:
        """On resume: the files exist, hold a run of the same parameters and are readable (else
        ValueError: :class:`arpy.io.StateFileError` for a file that is not what it should be,
        :class:`arpy.state.StateMismatchError` for another run's), and the time of the state is
        returned; else None."""
        if not self.resume:
            return None
        missing = [p.name for p in (self.path, self.initial, self.case_file) if not p.exists()]
        if missing:
            raise ValueError(f"nothing to resume in {self.path.parent}: {', '.join(missing)} missing "
                             "(a run writes them with a checkpoint interval > 0)")
        differ = differences(self._stored(), as_json(self.parameters), show=repr, skip=self.free)
        if differ:
            raise ValueError(f"the checkpoint in {self.path.parent} was written with other parameters: "
                             + ", ".join(differ))
        state = self.resumed()
        for path, run in ((self.initial, open_results(self.initial, PARTICLE_FILE)[0].get("run")),
                          (self.path, state.run)):
            if not isinstance(run, dict):
                raise StateMismatchError(f"{path} holds no run parameters: it was not written by a checkpoint of "
                                         f"the run in {self.case_file.name}", [])
            differ = differences(run, as_json(self.identity), show=repr)
            if differ:
                raise StateMismatchError(f"{path} belongs to another run than {self.case_file.name}: "
                                         f"{', '.join(differ)} (start the run afresh, without --resume)", differ)
        return state.t

    def _stored(self) -> dict[str, Any]:
        """The parameters in :attr:`case_file`."""
        try:
            stored = json.loads(self.case_file.read_text())
            if not isinstance(stored, dict):
                raise ValueError("it is not a JSON object")
        except (OSError, ValueError) as exc:
            raise unreadable(self.case_file, "parameter file of a checkpoint", exc) from exc
        return stored

    def particles(self, make: Callable[[], Particles]) -> Particles:
        """The initial particle set: ``make()`` (saved for a later resume when ``every`` > 0, replacing
        an earlier run's checkpoint files; a set spread over the ranks is saved in pieces, collectively),
        or on resume the saved one, dealt to the ranks of :attr:`comm` (:meth:`arpy.Particles.load`; each
        rank reads its share: every P-th piece of a file of pieces, its block of rows of one file; one
        process: the whole set)."""
        self.check()
        if self.resume:
            return Particles.load(self.initial, comm=self.comm)
        ps = make()
        if self.every:
            if self.writer:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._replace_earlier()
            if ps.parallel:
                ps.comm.allgather(None)                  # (the folder made, the earlier files gone)
                ps.save(self.initial, {"run": self.identity})
            elif self.writer:
                ps.save(self.initial, {"run": self.identity})
            if self.writer:
                text = json.dumps(self.parameters, indent=1, sort_keys=True) + "\n"
                replace_atomically({self.case_file: lambda f: f.write(text.encode())})
        return ps

    def _replace_earlier(self) -> None:
        """Remove the state of an earlier run (saying so on stderr, with the parameters that differ),
        so that no state of it is left beside this run's files."""
        if not (self.path.exists() or self.path.is_symlink()):
            return
        try:
            differ = ", ".join(differences(self._stored(), as_json(self.parameters), show=repr, skip=self.free))
        except StateFileError:
            differ = ""
        self.path.unlink()
        self.path.with_suffix(".json").unlink(missing_ok=True)
        remove_pieces(self.path)
        print(f"arpy: starting afresh: the checkpoint of an earlier run in {self.path.parent} is replaced"
              + (f" (it had {differ})" if differ else ""), file=sys.stderr)

    def shares(self, names: Sequence[str]) -> dict[str, dict[str, np.ndarray]]:
        """On resume: this rank's part of the shares ``names`` stored with the state (:meth:`run`'s
        ``shares``; :meth:`arpy.state.State.shares`): each a set of rows with their keys, in key order
        (on one process all of them).  Not collective."""
        return self.resumed().shares(names, self.comm)

    def run(self, sim: Simulation, T: float, *, progress: bool = False,
            callback: Callable[[Simulation], None] | None = None,
            records: Callable[[], dict[str, np.ndarray]] | None = None,
            restore: Callable[[Mapping[str, np.ndarray]], None] | None = None,
            shares: Callable[[], Shares] | None = None) -> Simulation:
        """``sim.run(T)`` with the state written every ``every`` steps (after ``callback`` and the
        :attr:`series`' frame), and on resume the state and the case's records (``restore``) loaded first
        (refused if of another run).

        ``records()`` gives the case's records as arrays when a state is written (rank 0's are kept);
        ``shares()`` its sets of rows of this rank, each with its keys (the particles at an earlier time:
        in each rank's piece, none gathered); ``restore`` puts the records back on resume (and takes
        the shares from :meth:`shares`)."""
        if self.resume:
            state = self.resumed()
            sim.load_state(state, run=self.identity)
            if restore is not None:
                restore(state.records)
            self._read.clear()
        if self.series is not None:
            self.series.start(sim, resume=self.resume)

        def step(s: Simulation) -> None:
            if callback is not None:
                callback(s)
            if self.series is not None:
                self.series(s)
            if self.every and s.steps % self.every == 0:          # (collective; rank 0 writes)
                s.save_state(self.path, records() if records is not None else None,
                             shares=shares() if shares is not None else None, run=self.identity)

        sim.run(T, progress=progress, callback=step)
        if self.series is not None:
            self.series.finish(sim)
        return sim


#: No checkpoint: the run starts from the beginning and writes no state.
NO_CHECKPOINT = Checkpoint(Path("checkpoint.npz"))


def case_checkpoint(checkpoint: Checkpoint | None, T: float) -> Checkpoint:
    """The checkpoint a case that steps in time to ``T`` runs with (``checkpoint``, else
    :data:`NO_CHECKPOINT`), once T is checked: ValueError unless it is a finite number > 0 (a case
    steps at least once; checked before the self-organization of its start, which can take long)."""
    if not (isinstance(T, (int, float, np.floating, np.integer)) and np.isfinite(T) and T > 0):
        raise ValueError(f"T must be a finite number > 0 (the final time), got {T!r}")
    return checkpoint or NO_CHECKPOINT
