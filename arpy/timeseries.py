"""A simulation's particles over time: VTU frames and the ``.pvd`` collection naming them with their
times, which ParaView opens as one animation (:class:`TimeSeries`).

A run of ``arpy run CASE --output-every K`` writes one (``OUT/<case>/<case>_series.pvd``); from Python,
give a series to :meth:`arpy.Simulation.run` as its callback::

    series = TimeSeries("run/pulse.pvd", every=10)
    series.start(sim)                       # the frame at the current time
    sim.run(1.0, callback=series)           # a frame every 10 steps
    series.finish(sim)                      # and the last one, at t = 1
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np

from .io import replace_atomically, write_vtu

if TYPE_CHECKING:
    from .simulation import Simulation

__all__ = ["TimeSeries"]


class TimeSeries:
    """Frames of a simulation's particles every ``every`` time steps (and at the start and the end of a
    run: :meth:`start`, :meth:`finish`), and the ``.pvd`` collection that lists them with their
    simulation times (the ``timestep`` of each data set): ParaView opens the ``.pvd`` as one animation
    whose time is the simulation's.

    Each frame holds the particles' positions and, as point data, ``D`` (the resolution D_p, a length)
    and every field by name (``f`` for a simulation of one field).  One process writes a ``.vtu`` per
    frame (:func:`arpy.io.write_vtu`); a distributed run (the simulation's communicator has more than
    one rank) a ``.pvtu`` per frame with one piece per rank (:func:`arpy.distributed.write_pvtu`),
    every rank calling.  The ``.pvd`` is rewritten after each frame (by rank 0, as one unit), so that
    it names every frame written so far, also when a run stops early.

    Parameters
    ----------
    path : str or Path
        The collection (``.pvd``).  The frames go into the folder of the same name without the suffix,
        named by the step: ``run.pvd`` lists ``run/run_000000.vtu``, ``run/run_000010.vtu``, ...
    every : int
        Time steps between frames (a frame when the step count is a multiple of it); 0: no frames.
    """

    def __init__(self, path: str | Path, every: int = 1) -> None:
        if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 0:
            raise ValueError(f"every must be an integer >= 0, got {every!r}")
        self.path = Path(path)
        self.every = int(every)
        #: The frames so far: (simulation time, file relative to the ``.pvd``'s folder).
        self.frames: list[tuple[float, str]] = []

    @property
    def folder(self) -> Path:
        """The folder of the frames."""
        return self.path.with_suffix("")

    def start(self, sim: Simulation, resume: bool = False) -> None:
        """Begin the series at the simulation's current state: its frame is the first (with ``every``
        > 0); or, with ``resume``, go on with the frames of the existing ``.pvd`` up to the current time
        (those of a run interrupted later are left out; the resumed run writes them again).
        Collective."""
        self.frames = []
        if resume and self.path.exists():
            self.frames = [(t, name) for t, name in _read_pvd(self.path) if t <= sim.t]
            return
        if self.every:
            self.write_state(sim)

    def finish(self, sim: Simulation) -> None:
        """End the series at the simulation's current state: its frame, unless the last frame is of this
        time already (with ``every`` > 0).  Collective."""
        if self.every and (not self.frames or self.frames[-1][0] < sim.t):
            self.write_state(sim)

    def __call__(self, sim: Simulation) -> None:
        """The callback of :meth:`arpy.Simulation.run`: a frame when the step count is a multiple of
        ``every``.  Collective."""
        if self.every and sim.steps % self.every == 0:
            self.write_state(sim)

    def write_state(self, sim: Simulation) -> Path:
        """A frame of the simulation's particles now (positions, ``D`` and its fields) at its time and
        step count; returns the frame's file.  Collective."""
        return self.write(sim.t, sim.steps, sim.x, {"D": sim.D, **sim.fields}, comm=sim.particles.comm)

    def write(self, t: float, step: int, x: np.ndarray, point_data: Mapping[str, np.ndarray], comm: Any = None
              ) -> Path:
        """A frame at time ``t`` (the ``.pvd``'s timestep) named by ``step``: the positions ``x`` (n, d)
        and the arrays ``point_data`` (each (n,) or (n, k)); with ``comm`` of more than one rank, each
        rank's own particles (one piece each of a ``.pvtu``).  Returns the frame's file.  Collective."""
        distributed = comm is not None and comm.size > 1
        name = f"{self.folder.name}_{int(step):06d}.{'pvtu' if distributed else 'vtu'}"
        frame = self.folder / name
        if distributed:
            from .distributed.pvtu import write_pvtu

            write_pvtu(comm, frame, x, **point_data)
        elif comm is None or comm.rank == 0:
            self.folder.mkdir(parents=True, exist_ok=True)
            write_vtu(frame, x, **point_data)
        self.frames = [(tt, f) for tt, f in self.frames if tt < t] + [(float(t), f"{self.folder.name}/{name}")]
        if comm is None or comm.rank == 0:
            text = _pvd_text(self.frames)
            replace_atomically({self.path: lambda f: f.write(text.encode())})
        return frame


def _pvd_text(frames: list[tuple[float, str]]) -> str:
    """The ``.pvd`` collection of the frames (time, file), one data set each."""
    rows = "".join(f'    <DataSet timestep="{t!r}" group="" part="0" file="{name}"/>\n' for t, name in frames)
    return ('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
            f"  <Collection>\n{rows}  </Collection>\n</VTKFile>\n")


def _read_pvd(path: Path) -> list[tuple[float, str]]:
    """The frames (time, file) a ``.pvd`` of :class:`TimeSeries` lists."""
    from xml.etree import ElementTree as ET

    return [(float(d.attrib["timestep"]), d.attrib["file"]) for d in ET.parse(path).getroot().iter("DataSet")]
