"""Checkpoint and restart of a case's simulation (``arpy run CASE --checkpoint-every K --resume``).

A :class:`Checkpoint` names a state file.  Every ``every`` steps the case's simulation writes its
state there (:meth:`arpy.Simulation.save_state`) together with the case's own records (error or
mass histories, snapshots), and the initial particle set beside it once.  A run started with
``resume=True`` loads them instead of self-organizing the initial set and continues from the
state: its results equal those of an uninterrupted run bit for bit.  A distributed run (the case's
``comm``) writes the same files from rank 0, and resumes on any number of ranks, or on one process.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..particles import Particles
from ..simulation import Simulation, state_records

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
    """

    path: Path
    every: int = 0
    resume: bool = False
    parameters: dict[str, Any] = field(default_factory=dict)
    free: tuple[str, ...] = ("T",)
    comm: Any = None

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

    def check(self) -> None:
        """On resume: the files exist and hold a run of the same parameters (else ValueError)."""
        if not self.resume:
            return
        missing = [p.name for p in (self.path, self.initial, self.case_file) if not p.exists()]
        if missing:
            raise ValueError(f"nothing to resume in {self.path.parent}: {', '.join(missing)} missing "
                             "(a run writes them with a checkpoint interval > 0)")
        stored = json.loads(self.case_file.read_text())
        differ = sorted(k for k in set(stored) | set(self.parameters)
                        if k not in self.free and stored.get(k) != self.parameters.get(k))
        if differ:
            raise ValueError("the checkpoint in " f"{self.path.parent} was written with other parameters: "
                             + ", ".join(f"{k} = {stored.get(k)!r} (now {self.parameters.get(k)!r})" for k in differ))

    def particles(self, make: Callable[[], Particles]) -> Particles:
        """The initial particle set: ``make()`` (saved for a later resume when ``every`` > 0), or on
        resume the saved one."""
        self.check()
        if self.resume:
            return Particles.load(self.initial)
        ps = make()
        if self.every and self.writer:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            ps.save(self.initial)
            self.case_file.write_text(json.dumps(self.parameters, indent=1, sort_keys=True) + "\n")
        return ps

    def run(self, sim: Simulation, T: float, *, progress: bool = False,
            callback: Callable[[Simulation], None] | None = None,
            records: Callable[[], dict[str, np.ndarray]] | None = None,
            restore: Callable[[dict[str, np.ndarray]], None] | None = None) -> Simulation:
        """``sim.run(T)`` with the state written every ``every`` steps (after ``callback``), and on
        resume the state and the case's records (``restore``) loaded first.

        ``records()`` gives the case's records as arrays when a state is written; ``restore`` puts
        them back on resume."""
        if self.resume:
            sim.load_state(self.path)
            if restore is not None:
                restore(state_records(self.path))

        def step(s: Simulation) -> None:
            if callback is not None:
                callback(s)
            if self.every and s.steps % self.every == 0:        # written beside it, then moved in place
                tmp = self.path.with_name(self.path.stem + "_writing.npz")
                s.save_state(tmp, records() if records is not None else None)      # (collective)
                if self.writer:
                    os.replace(tmp.with_suffix(".json"), self.path.with_suffix(".json"))
                    os.replace(tmp, self.path)

        return sim.run(T, progress=progress, callback=step)


#: No checkpoint: the run starts from the beginning and writes no state.
NO_CHECKPOINT = Checkpoint(Path("checkpoint.npz"))
