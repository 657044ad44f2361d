"""The case registry: what ``arpy run <case>`` takes and runs, declared once per case.

Each section module (:mod:`arpy.cases.pulse`, ...) declares its case as a :class:`Case`: the
parameters (:class:`Param`: option, type, default, meaning and unit, checks), the context of the
checks (the case's domain, :func:`domain`) and the runner, which runs the case and prints and writes
its outputs.  :data:`arpy.cases.CASES` collects them; :mod:`arpy.cli` builds one ``arpy run``
subcommand per case from it.

A parameter that sets a keyword of a case function is made by :func:`option`, which takes the
function's default: the defaults live in the functions' signatures only.  Where the default
depends on other parameters (the pulse's D0 on the dimension and the monitor, ...), the function
takes None and resolves it with a rule of its module, which the parameter names as ``default_for``.

A :data:`Check` is a pair (predicate of the value and the context, message).  The context holds
the parsed values and the case's domain; the message is formatted with it and ``value``.  A
predicate may raise ValueError, whose text then completes the message.
"""

from __future__ import annotations

import argparse
import inspect
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, cast

import numpy as np

from ..adapt.organize import MAX_PARTICLES
from ..adapt.resolution import r_star
from ..io import load_run, npz_path, run_record, save_run, write_vtu
from ..particles import PIECES, read_pieces, sampled, save_pieces, set_arrays
from ..timeseries import TimeSeries
from .checkpoint import Checkpoint

__all__ = ["CHECKPOINT", "COMMON", "Case", "Check", "EVERY", "FEW_ENOUGH", "FIGURE_POINTS", "NATURAL", "OUTPUT_EVERY",
           "PERIODIC", "POSITIVE", "Param", "REACH", "REMESHED", "RESOLUTION", "RUN_TIME_MACHINE", "TIME", "at_least",
           "checkpoint_path", "domain", "figure_rows", "option", "reach_option", "seed_option", "steps_option",
           "time_option", "writable"]

#: A check of one value: (predicate of the value and the context, message).
Check = tuple[Callable[[Any, dict[str, Any]], bool], str]


def at_least(lo: float, *, strict: bool = False, kind: str = "a finite number", what: str = "") -> Check:
    """A finite value >= lo (> lo if strict); ``what`` says what the option is."""
    return (lambda v, _: math.isfinite(v) and (v > lo if strict else v >= lo),
            f"must be {kind} {'>' if strict else '>='} {lo:g}{what}")


def writable(out: str, context: dict[str, Any]) -> bool:
    """Whether the folder out/<case> exists, or can be created, and can be written: a folder is made
    and removed again in the nearest folder on the path that exists (``os.access`` alone would pass
    where the permissions do not bind, e.g. for root, and on read-only or pseudo file systems).
    Raises ValueError with the system's reason when that fails."""
    path = Path(out, context["case"]).absolute()
    try:
        while not path.exists():
            path = path.parent
        if not path.is_dir():
            return False
        os.rmdir(tempfile.mkdtemp(prefix=".arpy-probe-", dir=path))
    except OSError as exc:
        raise ValueError(f"{exc.strerror or exc}: {path}") from None
    return True


def domain(edge: float, dim: int, *, periodic: bool = False, coarsest: float | None = None, reach: float = 1.0,
           max_particles: int = MAX_PARTICLES) -> dict[str, Any]:
    """The context of the checks that depend on a case's domain.

    Parameters
    ----------
    edge : float
        Edge of the domain, a cube in ``dim`` dimensions (domain units).
    dim : int
        Dimension, 2 or 3.
    periodic : bool
        Whether the cube is a periodic box.
    coarsest : float, optional
        In a periodic box: the coarsest resolution D0 (domain units).
    reach : float
        The factor on the ball of Eq. 2.9.
    max_particles : int
        The particle number at which the case's self-organization stops.

    Returns
    -------
    dict
        ``d0_min``: the D0 below which (edge / D0)^dim, about the particles at resolution D0
        before any refinement, exceeds ``max_particles``; ``cells_max``: the most remeshing cells
        per edge within it; in a periodic box ``cutoff``, the reach r* D0 of its coarsest
        particles, which must stay below half the edge.
    """
    context = dict(edge=edge, dim=dim, periodic=periodic, max_particles=max_particles, r_star=r_star(dim),
                   d0_min=edge / max_particles ** (1 / dim), cells_max=math.floor(max_particles ** (1 / dim)))
    if periodic:
        assert coarsest is not None, "a periodic box needs its coarsest resolution"
        context.update(coarsest=coarsest, cutoff=reach * r_star(dim) * coarsest)
    return context


POSITIVE = at_least(0, strict=True)
NATURAL = at_least(0, kind="an integer")
PERIODIC: Check = (lambda v, c: not c["periodic"] or c["cutoff"] < c["edge"] / 2,
                   "the periodic box of edge {edge:g} needs the cutoffs reach r* D0 (r* = {r_star:.3g}) below half "
                   "its edge, but --reach {reach:g} and the coarsest D0 = {coarsest:g} give {cutoff:.3g}")
FEW_ENOUGH: Check = (lambda v, c: v >= c["d0_min"],
                     "asks for more than {max_particles:.0e} particles, about (edge / D0)^{dim} on the {dim}D domain "
                     "of edge {edge:g}, where self-organization stops: use D0 >= {d0_min:.3g}")
#: The checks of a coarsest resolution D0.
RESOLUTION = (POSITIVE, FEW_ENOUGH, PERIODIC)
REACH = at_least(1, what=" (the factor on the ball of Eq. 2.9; 1 is the paper's)")
#: The most time steps a diffusion option may ask for (see :func:`few_steps`).
MAX_STEPS = 10_000_000


def few_steps(diffusivity: Callable[[float], float]) -> Check:
    """A check of an option that sets the diffusivity nu = ``diffusivity(value)``: the run to --T may
    not need more than :data:`MAX_STEPS` steps of the diffusive bound h^2 / (4 nu).  Every spacing h
    is at most about D0, so a run takes at least 4 T nu / D0^2 steps; above MAX_STEPS it is refused
    before any work (a --T or --D0 their own checks refuse is left to them)."""
    def ok(v: float, c: dict[str, Any]) -> bool:
        T, D0 = c["T"], c["D0"]
        if not (math.isfinite(T) and T > 0 and math.isfinite(D0) and D0 >= c["d0_min"] and D0 > 0):
            return True
        return 4.0 * T * diffusivity(v) / D0 ** 2 <= MAX_STEPS

    return (ok,
            f"with --T {{T:g}} and --D0 {{D0:g}} asks for more than {MAX_STEPS:.0e} time steps (the diffusive step "
            "h^2 / (4 nu), spacings h <= D0, gives at least 4 T nu / D0^2 of them)")
TIME = at_least(0, strict=True, what=" (the final time)")
EVERY = at_least(0, kind="an integer", what=" (0: never re-organize)")
REMESHED: tuple[Check, ...] = (
    at_least(0, kind="an integer", what=" (0: skip the remeshed baseline)"),
    (lambda v, c: v <= c["cells_max"], "makes more than {max_particles:.0e} mesh particles ({value}^{dim}): "
                                       "use at most {cells_max} cells per edge"))


@dataclass(frozen=True)
class Param:
    """One parameter of a case: the option ``flag`` of ``arpy run <case>``.

    ``help`` states its meaning and unit; ``checks`` are tried in order on the value (on each
    element of a list), None (a default the case function resolves itself) is not checked.
    ``function`` and ``keyword`` name the case function's argument it sets (None: the runner uses
    it otherwise).  ``default_for``, given the parsed values, returns the default where it depends
    on other parameters (then ``default`` is None and ``shown`` says what --help prints).
    """

    flag: str
    help: str
    type: Callable[[str], Any] | None = float
    default: Any = None
    checks: tuple[Check, ...] = ()
    choices: tuple | None = None
    nargs: str | None = None
    function: str | None = None
    keyword: str | None = None
    default_for: Callable[[argparse.Namespace], Any] | None = None
    shown: str | None = None

    @property
    def dest(self) -> str:
        """The namespace attribute of the option."""
        return self.flag[2:].replace("-", "_")

    def add_to(self, parser: argparse.ArgumentParser) -> None:
        """Declares the option on ``parser``, its help ending with the default."""
        shown = self.shown if self.shown is not None else (
            " ".join(f"{v:g}" for v in self.default) if isinstance(self.default, list) else
            f"{self.default:g}" if isinstance(self.default, float) else str(self.default))
        text = f"{self.help} (default: {shown})".replace("%", "%%")
        if self.type is None:
            parser.add_argument(self.flag, action="store_true", help=self.help.replace("%", "%%"))
            return
        extra: dict[str, Any] = {"metavar": self.dest.upper()} if self.choices is None else {"choices": self.choices}
        if self.nargs is not None:
            extra["nargs"] = self.nargs
        parser.add_argument(self.flag, type=self.type, default=self.default, help=text, **extra)


def option(function: Callable[..., Any], keyword: str, flag: str, help: str, *checks: Check, **more: Any) -> Param:
    """A :class:`Param` that sets ``keyword`` of the case ``function``, with the function's default
    (a list of it if ``nargs`` is given)."""
    default = inspect.signature(function).parameters[keyword].default
    if default is inspect.Parameter.empty:
        raise TypeError(f"{function.__name__}({keyword}) has no default")
    if more.get("nargs") is not None:
        default = [default]
    return Param(flag, help, default=default, checks=checks, function=function.__name__, keyword=keyword, **more)


#: A case's figure draws about this many particles of each set at most: beyond, the sample of its keys
#: (:func:`arpy.particles.sampled`), the same on any number of ranks (:meth:`Case.figure`).
FIGURE_POINTS = 200_000


def figure_rows(rows: dict[str, np.ndarray], points: int | None = None) -> dict[str, Any]:
    """The rows of one process's set (arrays with one row per particle, its ``keys`` among them) that a
    figure draws: all of them if they are at most ``points`` (default :data:`FIGURE_POINTS`), else those
    of the sample of about ``points`` by their keys (:func:`arpy.particles.sampled`); with the set's
    count as ``N``."""
    count = len(rows["keys"])
    keep = sampled(rows["keys"], (FIGURE_POINTS if points is None else points) / max(count, 1))
    return {**({k: v[keep] for k, v in rows.items()} if not keep.all() else dict(rows)), "N": count}


#: Where the run times of :attr:`Case.seconds` were measured: CPU seconds of one run on one core thread
#: (OMP_NUM_THREADS=1), which on an idle machine is its wall time; the core's default of every core
#: shortens only its parallel loops.
RUN_TIME_MACHINE = "one thread of a 2-core AMD EPYC virtual machine"


@dataclass(frozen=True)
class Case:
    """A case of ``arpy run``: ``name`` (the subcommand), ``title`` (one line for ``arpy run --help``),
    ``params`` in the order they are checked, ``context`` (the parsed values -> the checks' context:
    the case's domain), and ``run`` (the parsed values and the output folder -> prints and writes
    the case's outputs, and returns its summary: the figures it printed, as JSON values).  Every case
    runs across the MPI ranks it is started on, with every option: ``run`` finds the communicator in
    ``args.comm``."""

    name: str
    title: str
    params: tuple[Param, ...]
    context: Callable[[argparse.Namespace], dict[str, Any]]
    run: Callable[[argparse.Namespace, Path], dict[str, Any]]
    #: The names of the columns of the two-dimensional arrays of its results, by array.
    columns: dict[str, tuple[str, ...]] = field(default_factory=dict)
    #: The typical run time at the defaults, in seconds: measured on :data:`RUN_TIME_MACHINE` (0: not
    #: measured); ``arpy run CASE --help`` states it.
    seconds: float = 0.0

    def run_time(self) -> str:
        """The typical run time at the defaults, as ``--help`` says it (empty if not measured)."""
        if not self.seconds:
            return ""
        shown = f"{self.seconds:.0f} s" if self.seconds < 120 else f"{self.seconds / 60:.0f} min"
        return f"At the defaults it takes about {shown} ({RUN_TIME_MACHINE})."

    def parameters(self, args: argparse.Namespace) -> dict[str, Any]:
        """The case and the value of each of its options in ``args`` (what a result file records)."""
        return {"case": self.name, **{p.dest: getattr(args, p.dest) for p in self.params}}

    def kwargs(self, args: argparse.Namespace, function: str) -> dict[str, Any]:
        """The keyword arguments of the case function named ``function`` set by the parsed ``args``."""
        return {cast(str, p.keyword): getattr(args, p.dest) for p in self.params if p.function == function}

    def checkpoint(self, args: argparse.Namespace) -> Checkpoint | None:
        """The checkpoint of a case that steps in time (None for the others), from --checkpoint-every,
        --resume and --out, with the run's time series (:meth:`series`).  One per parsed command and
        set of ranks (kept in ``args``): the checks before the run and a run on one process use the
        same, so a resumed state is read once (:meth:`Checkpoint.resumed`); the ranks of a run under
        mpiexec, known only when it starts, get their own."""
        if not any(p.dest == "resume" for p in self.params):
            return None
        kept = getattr(args, "_checkpoint", None)
        if isinstance(kept, Checkpoint) and kept.comm is getattr(args, "comm", None):
            return kept
        made = Checkpoint(checkpoint_path(vars(args)), every=args.checkpoint_every, resume=args.resume,
                          parameters=self.parameters(args), free=("T", "checkpoint_every", "resume", "output_every"),
                          comm=getattr(args, "comm", None), series=self.series(args))
        args._checkpoint = made
        return made

    def series(self, args: argparse.Namespace, tag: str = "") -> TimeSeries | None:
        """The time series of --output-every (None when it is 0 or the case takes no such option):
        ``OUT/<case>/<name>_series<tag>.pvd`` and its frames (<name>: the case's name with ``_`` for
        ``-``; ``tag`` tells the runs of one case apart)."""
        every = getattr(args, "output_every", 0) if any(p.dest == "output_every" for p in self.params) else 0
        if not every:
            return None
        return TimeSeries(Path(args.out, self.name, f"{self.name.replace('-', '_')}_series{tag}.pvd"), every)

    def record(self, args: argparse.Namespace, summary: dict[str, Any]) -> dict[str, Any]:
        """The record of a run of the case (:func:`arpy.io.run_record`): its options in ``args``, its
        ``summary``, the ranks (``args.comm``), threads and versions, and the :attr:`columns` of its arrays."""
        return run_record(self.parameters(args), summary, comm=getattr(args, "comm", None), columns=self.columns)

    def save(self, args: argparse.Namespace, path: Path, summary: dict[str, Any], *,
             rows: dict[str, np.ndarray] | None = None, sets: dict[str, dict[str, np.ndarray]] | None = None,
             **arrays: Any) -> Path:
        """Write the ``arrays`` of a run to the NumPy archive ``path`` with the run's :meth:`record` in it
        and in its JSON sidecar (:func:`arpy.io.save_run`): the one writer of every case's results.

        ``rows`` are arrays with one row per particle of this rank, in key order, their keys as ``keys``
        (int (n,)).  One process writes them into the archive (without the keys).  On P > 1 ranks
        (``args.comm``) no rank gathers them: each writes its rows to a piece beside the archive
        (:func:`arpy.particles.save_pieces`: ``<name>.part<r>-of-<P>.npz``, with the keys), and the
        archive, written by rank 0, holds ``arrays`` and the record with the index of the pieces
        (``pieces``; :meth:`figure` reads them back).  ``sets``: more sets of rows of this rank, each with
        its own ``keys`` (the particles at an earlier time), written as ``rows`` are: by one process into
        the archive as ``<set>_<name>`` (:func:`arpy.particles.set_arrays`), on P > 1 ranks to the pieces.
        Collective with ``rows``; without, the archive is written by the rank that calls (a case whose
        results every rank holds calls on rank 0 only)."""
        comm = getattr(args, "comm", None)
        record = self.record(args, summary)
        if comm is None or comm.size == 1 or rows is None:
            return save_run(path, record, **{k: v for k, v in (rows or {}).items() if k != "keys"}, **arrays,
                            **set_arrays(sets))
        out = npz_path(path)
        return save_pieces(comm, out, rows, lambda index: save_run(out, {**record, PIECES: index}, **arrays), sets)

    def figure(self, args: argparse.Namespace, path: Path, archive: Path, rows: dict[str, np.ndarray],
               draw: Callable[[dict[str, Any], Path], None], points: int | None = None,
               sets: dict[str, dict[str, np.ndarray]] | None = None) -> bool:
        """Draw the figure ``path`` of the whole set, ``draw(whole, path)`` (with matplotlib,
        :func:`arpy.plotting.write_figure`), ``whole`` the rows written by :meth:`save` to ``archive``, in
        key order, and as ``whole[set]`` the rows of each of its ``sets``, each with its count of particles
        as ``N`` (for the titles).  Of a set of more than ``points`` particles (default
        :data:`FIGURE_POINTS`), only the sample of about ``points`` of them by their keys
        (:func:`figure_rows`): the same rows on any number of ranks.  One process: those of ``rows`` and
        ``sets`` themselves.  On P > 1 ranks (``args.comm``) rank 0 reads them from the pieces
        (:meth:`read_back`) and the other ranks draw nothing; with ``--no-figure`` no rank draws.  Not
        collective; returns whether the figure was drawn."""
        whole = self.drawn_rows(args, archive, rows, points, sets)
        if whole is None:
            return False
        from ..plotting import write_figure

        return write_figure(path, lambda p: draw(whole, p))

    def drawn_rows(self, args: argparse.Namespace, archive: Path, rows: dict[str, np.ndarray],
                   points: int | None = None, sets: dict[str, dict[str, np.ndarray]] | None = None
                   ) -> dict[str, Any] | None:
        """The ``whole`` that :meth:`figure` draws (its arguments), on the rank that draws: one process's
        own rows (:func:`figure_rows`), or on P > 1 ranks rank 0's read back (:meth:`read_back`); None on
        the other ranks and with ``--no-figure``.  Not collective."""
        comm = getattr(args, "comm", None)
        if args.no_figure or (comm is not None and comm.size > 1 and comm.rank != 0):
            return None
        if comm is not None and comm.size > 1:
            return self.read_back(archive, points)
        whole: dict[str, Any] = figure_rows(rows, points)
        whole.update({name: figure_rows(got, points) for name, got in (sets or {}).items()})
        return whole

    @staticmethod
    def read_back(archive: Path, points: int | None = None) -> dict[str, Any]:
        """The rows :meth:`save` wrote in pieces beside ``archive`` on P > 1 ranks, read back in key order
        (:func:`arpy.particles.read_pieces`), with those of each of its sets as ``whole[set]``, for a
        figure: each set's count as ``N``, and of a set of more than ``points`` particles (default
        :data:`FIGURE_POINTS`), only the rows of its sample (:func:`figure_rows`), each piece cut to
        them as it is read.  Not collective."""
        record, _ = load_run(archive)
        index = record[PIECES]
        limit = FIGURE_POINTS if points is None else points

        def rows_of(of: str | None) -> dict[str, Any]:
            count = sum(index["counts"] if of is None else index["sets"][of])
            return {**read_pieces(archive, index, of=of, fraction=limit / max(count, 1)), "N": count}
        whole = rows_of(None)
        whole.update({name: rows_of(name) for name in index.get("sets", {})})
        return whole

    def vtu(self, args: argparse.Namespace, path: Path, x: np.ndarray, **point_data: np.ndarray) -> Path:
        """Write this rank's particles (x (n, d), point data (n,) or (n, k)) for ParaView: one process,
        the ``.vtu`` ``path`` (:func:`arpy.io.write_vtu`); on P > 1 ranks (``args.comm``), with no rank
        gathering them, ``path`` with ``.pvtu`` and one piece per rank (:func:`arpy.distributed.write_pvtu`,
        with the array ``rank``).  Collective; returns the file written."""
        comm = getattr(args, "comm", None)
        if comm is None or comm.size == 1:
            return write_vtu(path, x, **point_data)
        from ..distributed import write_pvtu

        return write_pvtu(comm, path.with_suffix(".pvtu"), x, **point_data)


#: The options of ``arpy run`` that every case takes, after its own.
COMMON: tuple[Param, ...] = (
    Param("--out", "output folder; the case writes into OUT/<case>", type=str, default="arpy-output",
          checks=((writable, "must be a folder that exists, or can be created, and can be written"),)),
    Param("--quiet", "no progress bar", type=None, default=False),
    Param("--json", "print a machine-readable summary (JSON) instead of the text", type=None, default=False),
    Param("--no-figure", "draw no figure (matplotlib is not needed): the results file, the particles and the "
          "summary only, e.g. for runs on a cluster or many runs in a sweep", type=None, default=False),
)


def checkpoint_path(context: dict[str, Any]) -> Path:
    """The state file of a run of the case in ``context["case"]`` with ``--out`` ``context["out"]``."""
    return Path(context["out"], context["case"], "checkpoint.npz")


#: The option of the cases that step a simulation in time: their particles over time (:meth:`Case.series`).
OUTPUT_EVERY = Param("--output-every", "write the particles (positions, D_p and the fields) every K time steps, at "
                     "the start and at the end as a VTU time series: OUT/<case>/<case>_series.pvd, which ParaView opens "
                     "as one animation in simulation time, and its frames in OUT/<case>/<case>_series/ (0: none)",
                     type=int, default=0, checks=(NATURAL,))

#: The options of the cases that step a simulation in time: checkpoint and restart.
CHECKPOINT: tuple[Param, ...] = (
    Param("--checkpoint-every", "write the simulation's state to OUT/<case>/checkpoint.npz every K time steps "
          "(0: never; an earlier run's checkpoint there is replaced); --resume continues from it", type=int, default=0,
          checks=(NATURAL,)),
    Param("--resume", "continue the run whose state is in OUT/<case>/checkpoint.npz (the same options, else "
          "refused, naming those that differ; --T may be larger); its results equal those of an uninterrupted run",
          type=None, default=False,
          checks=((lambda v, c: not v or checkpoint_path(c).exists(),
                   "nothing to resume: {out}/{case}/checkpoint.npz does not exist"),)),
)


def seed_option(function: Callable[..., Any]) -> Param:
    """--seed: the seed of ``function``'s random initial particles and insertions."""
    return option(function, "seed", "--seed", "seed of the random initial particles and insertions", NATURAL,
                  type=int)


def reach_option(function: Callable[..., Any], *checks: Check) -> Param:
    """--reach: the factor on the ball of Eq. 2.9 (dimensionless), checked by REACH and ``checks``."""
    return option(function, "reach", "--reach",
                  "factor on the ball of Eq. 2.9, dimensionless (1: the paper's; 2 grades D_p more slowly near "
                  "fine features)", REACH, *checks)


def time_option(function: Callable[..., Any]) -> Param:
    """--T: the final time of ``function``'s simulation."""
    return option(function, "T", "--T", "final time T (time units of the case)", TIME)


def steps_option(function: Callable[..., Any]) -> Param:
    """--k: the time steps between re-organizations of ``function``'s simulation."""
    return option(function, "reorganize_every", "--k", "time steps between re-organizations (0: never)", EVERY,
                  type=int)

