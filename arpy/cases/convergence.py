"""§4.1 of Reboux et al. (2012): the consistency of DC-PSE interpolation and Laplacian between
successive adaptations, on the tanh front (Eq. 4.1) or on the blob of §4.2 (Eq. 4.3), while D0
shrinks by a factor per adaptation.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from .. import fields
from ..distributed import Comm, DistributedDCPSE, SerialComm, migrate
from ..distributed.reductions import exact_median, exact_quantile, key_places
from ..domain import Domain
from ..adapt.organize import DEFAULT_SEED, displace_set, self_organize, start_share
from ..particles import Particles
from ..plotting import save_figure, slope_lines, write_figure
from ..adapt.resolution import MONITORS, check_monitor, monitor_fourth
from ..dcpse.displace import repair_for
from ..dcpse.domain import LEBESGUE_MAX, REPAIR, Repair
from .analysis import slope
from .registry import (FEW_ENOUGH, PERIODIC, POSITIVE, Case, Check, domain, option, reach_option,
                       seed_option)
from .reversing_vortex import blob, blob_fourth_derivatives, blob_gradient, blob_laplacian

__all__ = ["CASE", "COLUMNS", "CONSISTENCY_FACTOR", "CONSISTENCY_START", "TWO_REFINEMENTS", "consistency",
           "consistency_levels", "consistency_start"]

#: The names of the columns of :func:`consistency`'s two-dimensional results.
COLUMNS: dict[str, tuple[str, ...]] = {"x_at_max": ("x", "y")}
#: The factor by which :func:`consistency` refines D0 from one adaptation to the next.
CONSISTENCY_FACTOR = 0.95
#: The first D0 of :func:`consistency` per field when none is given.
CONSISTENCY_START = {"tanh": 0.4, "blob": 0.25}


def consistency_levels(d0_start: float, d0_end: float, factor: float = CONSISTENCY_FACTOR) -> np.ndarray:
    """The D0 of each refinement of :func:`consistency`: d0_start factor^k for k = 1, 2, ... down to d0_end."""
    return d0_start * factor ** np.arange(1, int(np.floor(np.log(d0_end / d0_start) / np.log(factor))) + 1)


def consistency_start(field: str, d0_start: float | None = None) -> float:
    """The first D0 of :func:`consistency`: ``d0_start``, or :data:`CONSISTENCY_START` of the field if None."""
    if field not in CONSISTENCY_START:
        raise ValueError(f"field must be 'tanh' or 'blob', got {field!r}")
    return CONSISTENCY_START[field] if d0_start is None else d0_start


class _Field(NamedTuple):
    """A field of §4.1 on its domain: f, its gradient, Laplacian and fourth derivatives (x (n, 2) ->
    (n,), (n, 2), (n,), (n, 5)), its domain, its area, ``max |f|`` (the errors' scale) and the range
    [lo, hi] of the initial random particles."""

    f: Callable
    grad: Callable
    laplacian: Callable
    fourth: Callable
    domain: Domain
    area: float
    scale: float
    lo: float
    hi: float


def _field(field: str, width: float) -> _Field:
    """The tanh front of Eq. 4.1 on [-1, 1]^2 with walls, or the blob of Eq. 4.3 in the periodic unit square."""
    if field == "tanh":
        return _Field(lambda p: fields.tanh_front(p, width), lambda p: fields.tanh_front_gradient(p, width),
                      lambda p: fields.tanh_front_laplacian(p, width),
                      lambda p: fields.tanh_front_fourth_derivatives(p, width),
                      Domain(([-1.0, -1.0], [1.0, 1.0])), 4.0, 1.0, -1.0, 1.0)
    if field == "blob":
        return _Field(blob, blob_gradient, blob_laplacian, blob_fourth_derivatives,
                      Domain([1.0, 1.0], periodic=True), 1.0, np.sqrt(2), 0.0, 1.0)
    raise ValueError(f"field must be 'tanh' or 'blob', got {field!r}")


def _laplacian_scale(fld: _Field, points: int = 1000) -> float:
    """``max |lap f| / max |f|`` of the field at the centres of a ``points`` x ``points`` grid of cells over
    its box (the scale of the Laplacian's errors, which are relative to ``max |f|``); no centre falls on the
    blob's centre, where its Laplacian has a weak 1/r singularity."""
    axis = fld.lo + (np.arange(points) + 0.5) * ((fld.hi - fld.lo) / points)
    grid = np.stack(np.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
    return float(np.abs(fld.laplacian(grid)).max()) / fld.scale


class _Errors(NamedTuple):
    """The errors of one step of §4.1 (:func:`_transfer_errors`) at this rank's new particles, with the
    counts over every rank."""

    rows: np.ndarray
    """This rank's new particles: their indices into the new set, increasing, int (m,)."""
    x: np.ndarray
    """Their positions, (m, d)."""
    D: np.ndarray
    """Their resolutions D_p, (m,)."""
    interp: np.ndarray
    """Their interpolation errors, (m,)."""
    laplacian: np.ndarray
    """The Laplacian's errors at those of them with a stencil."""
    failed: int
    """The new particles of every rank without a stencil even after the repair."""
    unrepaired: int
    """The new particles of every rank without a stencil of their own (before the repair)."""


def _transfer_errors(old: Particles, new: Particles, fld: _Field, repair: Repair = REPAIR) -> _Errors:
    """One step of §4.1: the old values interpolated to the new particles and the Laplacian applied
    with the old particles as sources (one DC-PSE factorisation), against the exact field.  The sets
    are each rank's shares (one process: the whole sets) on the ranks of ``old.comm``: each rank takes
    its old particles, in their boxes, and the new ones those boxes own, moved there
    (:class:`arpy.distributed.DistributedDCPSE`, both numbered by their places in key order: bitwise
    the same for every rank count) and keeps their errors; only the counts are summed over the ranks.
    The particles without a stencil take the nearest old value, as in a simulation, and are left out
    of the Laplacian's errors.  Collective."""
    comm, dec = old.comm, old.decomposition
    ko = key_places(comm, old.keys)
    xn, kn, got = migrate(comm, dec, new.x, key_places(comm, new.keys), {"eps": new.eps, "D": new.D})
    # (the Lebesgue limit of REPAIR under either rule: this case's rows as it has always built them;
    # a Simulation under "displace" builds its old -> new rows without it)
    dop = DistributedDCPSE(comm, dec, old.x, old.eps, ko, xn, got["eps"], domain=fld.domain,
                           order=4, strict=False, operators=["interpolation", "laplacian"], widen=repair["widen"],
                           max_lebesgue=LEBESGUE_MAX)
    fo = fld.f(old.x)
    fi, lap = dop.interpolate(fo), dop.laplacian() @ dop.extend(fo)
    ok = np.ones(kn.size, bool)
    ok[dop.failed] = False
    return _Errors(kn, xn, got["D"], np.abs(fi - fld.f(xn)) / fld.scale,
                   (np.abs(lap - fld.laplacian(xn)) / fld.scale)[ok],
                   comm.sum(int(np.size(dop.failed))), comm.sum(int(np.size(dop.unrepaired))))


def _largest(comm: Comm, e: _Errors) -> tuple[float, float, np.ndarray, float]:
    """The largest interpolation and Laplacian errors over every rank's new particles (NumPy's max: NaN
    if any is NaN) and the position (d,) and D_p of the first new particle with the largest
    interpolation error (as ``argmax`` of the errors of the whole set in index order finds it; sent by
    the rank that holds it).  Collective."""
    top_i, top_l = comm.max(np.array([e.interp.max(initial=-np.inf), e.laplacian.max(initial=-np.inf)]))
    at = e.rows[np.isnan(e.interp) if np.isnan(top_i) else e.interp == top_i]
    k = int(comm.min(np.array([at.min(initial=np.iinfo(np.int64).max)]))[0])
    hit = np.flatnonzero(e.rows == k)
    x_at, D_at = next(g for g in comm.allgather((e.x[hit[0]], e.D[hit[0]]) if hit.size else None) if g is not None)
    return float(top_i), float(top_l), x_at, float(D_at)


def consistency(d0_start: float | None = None, d0_end: float = 0.1, factor: float = CONSISTENCY_FACTOR,
                seed: int = DEFAULT_SEED, width: float = 0.01, reach: float = 1.0, field: str = "tanh",
                monitor: str = "gradient", stencil_rule: str = "repair", progress: bool = False,
                comm: Comm | None = None) -> dict:
    """§4.1: adapt particles to a field, refine D0 <- factor D0, interpolate the old values to the
    new particles and apply the Laplacian with the old particles as sources (one factorisation);
    errors against the exact field.

    Parameters
    ----------
    d0_start : float, optional
        The D0 of the first adaptation (length); None: :data:`CONSISTENCY_START` of the field
        (0.4 for tanh, 0.25 for the blob).
    d0_end : float
        The last D0 (length): the refinements are :func:`consistency_levels` (the paper goes to 0.006).
    factor : float
        D0 <- factor D0 from one adaptation to the next, 0 < factor < 1.
    seed : int
        Seed of the random initial particles and insertions.
    width : float
        W of the tanh front (the paper's: 0.01).
    reach : float
        The factor on the ball of Eq. 2.9 (1: the paper's; see :func:`arpy.self_organize`).
    field : str
        "tanh" -- the front of Eq. 4.1 on [-1, 1]^2 with walls (the paper's §4.1); "blob" -- the
        blob of Eq. 4.3 in the periodic unit square (the initial field of §4.2): one interpolation
        between successive adaptations, the building block of every re-organization of Fig. 4.2.
    monitor : str
        "gradient" -- the paper's Eq. 2.8, ``D~ = D0 / sqrt(1 + |grad f|^2)``; "fourth" -- Eq. B.13 of
        its Appendix B, the resolution that equidistributes the error of m = 4 interpolation,
        regularised like Eq. 2.8: ``D~ = D0 (1 + max over |beta| = 4 of |d^beta f|)^(-1/4)``, from the
        exact fourth derivatives (a simulation estimates them from the particles:
        ``Simulation(monitor="fourth")``).
    stencil_rule : {"repair", "displace"}
        Stencils the moment conditions cannot use: repaired (arpy's rules) or, on each new set,
        removed by displacing and inserting particles (the paper's §2.2,
        :func:`arpy.dcpse.displace.displace_until_valid`) before the operators are built without repair.
    progress : bool
        Show a progress bar.
    comm : Comm, optional
        Run over the ranks of a communicator (every rank calls this function with the same
        arguments): each adaptation on the ranks (:func:`arpy.self_organize` with ``comm``; the first
        from each rank's share of the random start, each next one from each rank's share of the set
        before: no rank holds a whole set), the operators old -> new on them (:func:`_transfer_errors`),
        bitwise the one-process results on every rank (under either stencil rule).  Each rank keeps
        the errors of the new particles its box owns: the maxima, medians, percentiles and counts are
        reductions over the ranks (:func:`~arpy.distributed.reductions.exact_median`,
        :func:`~arpy.distributed.reductions.exact_quantile`), no rank gathers the errors.

    Returns
    -------
    dict
        Errors are relative to ``max |f|`` (1 for the tanh front, sqrt(2) for the blob, as in Eq. 4.5).
        Arrays (k,) over the refinements: ``D0``, ``N``, ``h`` = ``sqrt(|Omega| / N)``, ``err_interp``
        and ``err_laplacian`` (maxima over the new particles), ``median_interp``,
        ``median_laplacian``, ``p99_interp`` (99th percentile of the interpolation error),
        ``x_at_max`` (k, 2) and ``D_at_max``: the position and D_p of the new particle with the
        largest interpolation error, ``failed``: the new particles without a DC-PSE stencil even
        after the repair (they take the nearest old value and are left out of the Laplacian's
        errors); ``slope_interp`` and ``slope_laplacian``: the fitted slopes of the maxima (the
        paper: 4 and 2; the maximum is the error at one particle of each new set, and scatters from set
        to set by up to 7x), ``slope_p99``: that of the 99th percentiles of the interpolation error
        (the trend without that scatter); ``laplacian_scale``: ``max |lap f| / max |f|`` on a 1000^2
        grid (``err_laplacian / laplacian_scale`` is the Laplacian's error relative to ``max |lap f|``);
        ``last``: the finest set's particles, their indices ``keys`` (n,) into it, positions x (n, 2),
        D_p (n,) and interpolation errors (n,), in index order (with ``comm``: this rank's); ``failed_before``,
        ``displaced``, ``inserted``: per refinement, the rows without a valid stencil before the rule
        acts and what the "displace" rule did (zeros under "repair"); ``wall_s``: the run's wall time
        (seconds); ``columns``: the names of the columns of ``x_at_max``.
    """
    fld = _field(field, width)
    check_monitor(monitor, 4)
    repair = repair_for(stencil_rule)
    d0_start = consistency_start(field, d0_start)

    def adapt(start: dict, d0):
        """The set adapted to D0 = d0 from ``start`` (:func:`self_organize`'s x, keys and boxes): on
        several ranks each rank's share, none gathered."""
        if monitor == "gradient":
            return self_organize(**start, grad_f=fld.grad, D0=d0, domain=fld.domain, seed=seed, reach=reach, comm=comm)
        return self_organize(**start, resolution=lambda p: monitor_fourth(fld.fourth(p), d0), domain=fld.domain,
                             seed=seed, reach=reach, comm=comm)

    def again(ps: Particles) -> dict:
        """The start of the next adaptation from the set ``ps``: its particles numbered by their places
        in key order (the indices of the whole set), on several ranks each rank's in its boxes."""
        if not ps.parallel:
            return {"x": ps.x}
        return {"x": ps.x, "keys": key_places(ps.comm, ps.keys), "decomposition": ps.decomposition}

    if not (0 < factor < 1 and 0 < d0_end < d0_start):
        raise ValueError("need 0 < factor < 1 and 0 < d0_end < d0_start")
    t0 = time.perf_counter()
    x = np.random.default_rng(seed).uniform(fld.lo, fld.hi, (800, 2))
    ps = adapt(start_share(x, comm), d0_start)
    whole = comm or SerialComm()
    rows = []
    d0s = consistency_levels(d0_start, d0_end, factor)
    it = d0s
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(d0s, desc="consistency", unit="D0", disable=None)
    for d0 in it:
        new = adapt(again(ps), float(d0))
        counts = None                               # failed before the rule, displaced, inserted
        if stencil_rule == "displace":
            new, done = displace_set(new, old=ps, rng=seed)
            counts = (done["failed"], done["displaced"], done["inserted"])
        e = _transfer_errors(ps, new, fld, repair)
        top_i, top_l, x_at, D_at = _largest(whole, e)
        rows.append((d0, new.total(new.n), top_i, top_l, exact_median(whole, e.interp),
                     exact_median(whole, e.laplacian), exact_quantile(whole, e.interp, 0.99), x_at, D_at, e.failed,
                     *(counts or (e.unrepaired, 0, 0))))
        ps, last = new, e
    d0, n, ei, el, mi, ml, qi, xm, dm, nf, fb, nd, ni = (np.array(c) for c in zip(*rows))
    h = np.sqrt(fld.area / n)
    return dict(D0=d0, N=n, h=h, err_interp=ei, err_laplacian=el, median_interp=mi, median_laplacian=ml,
                p99_interp=qi, x_at_max=xm, D_at_max=dm, failed=nf, failed_before=fb, displaced=nd, inserted=ni,
                slope_interp=slope(h, ei), slope_p99=slope(h, qi),
                slope_laplacian=slope(h, el), laplacian_scale=_laplacian_scale(fld),
                last=dict(keys=last.rows, x=last.x, D=last.D, err_interp=last.interp),
                wall_s=time.perf_counter() - t0, columns=COLUMNS)


# ---------------------------------------------------------------- arpy run consistency
def _plot(r: dict, path: Path, title: str) -> None:
    """(a) The interpolation errors relative to max |f| against h: the maxima, 99th percentiles and
    medians over the new particles, with slope 4; (b) the Laplacian's relative to max |lap f|: maxima and
    medians, with slope 2."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 5.2), sharex=True)
    h, lap = r["h"], r["laplacian_scale"]
    ax = axes[0]
    ax.loglog(h, r["err_interp"], "o", label=f"maximum (slope {r['slope_interp']:.2f})")
    ax.loglog(h, r["p99_interp"], "s-", ms=4, label=f"99th percentile (slope {r['slope_p99']:.2f})")
    ax.loglog(h, r["median_interp"], "^-", ms=4, label=f"median (slope {slope(h, r['median_interp']):.2f})")
    slope_lines(ax, h, r["p99_interp"], [4])
    ax.set_ylabel("|f_h - f| / max |f| at the new particles")
    ax.set_title("(a) interpolation old -> new")
    ax = axes[1]
    ax.loglog(h, r["err_laplacian"] / lap, "o", label=f"maximum (slope {r['slope_laplacian']:.2f})")
    ax.loglog(h, r["median_laplacian"] / lap, "^-", color="C2", ms=4,
              label=f"median (slope {slope(h, r['median_laplacian']):.2f})")
    slope_lines(ax, h, r["median_laplacian"] / lap, [2])
    ax.set_ylabel("|lap_h f - lap f| / max |lap f|")
    ax.set_title("(b) Laplacian from the old particles")
    for ax in axes:
        ax.set_xlabel("h = sqrt(|Omega| / N)")
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, frameon=False)   # (below)
    fig.suptitle(title, fontsize=10)
    save_figure(fig, path)


def run(args: argparse.Namespace, out: Path) -> dict:
    """``arpy run consistency``: prints the errors per refinement and their fitted slopes; writes
    consistency.npz, consistency_particles.vtu (the finest set and its interpolation errors) and
    consistency.png; returns the summary.  Under mpiexec rank 0 writes consistency.npz and the figure
    (the summaries every rank holds), and consistency_particles.pvtu has one piece per rank
    (:meth:`~arpy.cases.registry.Case.vtu`)."""
    comm = getattr(args, "comm", None)
    r = consistency(d0_start=consistency_start(args.field), **CASE.kwargs(args, "consistency"),
                    progress=not args.quiet, comm=comm)
    what = ("the tanh front (Reboux et al. 2012, Sec. 4.1)" if args.field == "tanh" else
            "the blob of Sec. 4.2 at rest (Reboux et al. 2012)") + f", monitor {args.monitor}"
    print(f"arpy run consistency: interpolation and Laplacian on {what}; errors / max f")
    print(f"  {'D0':>7s} {'N':>7s} {'h':>8s} {'interp err':>11s} {'99th pct':>10s} {'Laplacian err':>14s}")
    for row in zip(r["D0"], r["N"], r["h"], r["err_interp"], r["p99_interp"], r["err_laplacian"]):
        print(f"  {row[0]:7.4f} {row[1]:7d} {row[2]:8.4f} {row[3]:11.3e} {row[4]:10.3e} {row[5]:14.3e}")
    print(f"  fitted slopes: interpolation {r['slope_interp']:.2f} (99th percentile {r['slope_p99']:.2f}; "
          "the paper: 4, "
          f"{'which Eq. 2.8 caps near 2' if args.monitor == 'gradient' else 'reached with Eq. B.13'}), "
          f"Laplacian {r['slope_laplacian']:.2f} (the paper: 2)" + (f"; on {comm.size} MPI ranks" if comm else ""))
    summary = {k: r[k] for k in ("D0", "N", "h", "err_interp", "p99_interp", "err_laplacian", "failed", "slope_interp",
                                 "slope_p99", "slope_laplacian", "laplacian_scale", "wall_s")}
    last = r["last"]
    CASE.vtu(args, out / "consistency_particles.vtu", last["x"], D=last["D"], err_interp=last["err_interp"])
    if comm is not None and comm.rank != 0:                  # (rank 0 writes the summaries)
        return summary
    CASE.save(args, out / "consistency.npz", summary, **{k: v for k, v in r.items() if k not in ("last", "columns")})
    if not args.no_figure:
        write_figure(out / "consistency.png", lambda path: _plot(r, path, f"consistency: {what}"))
    return summary


def _context(args: argparse.Namespace) -> dict:
    """The domain of --field (tanh: [-1, 1]^2 with walls; blob: the periodic unit square) and the first D0."""
    start = consistency_start(args.field)
    box = domain(2.0, 2) if args.field == "tanh" else domain(1.0, 2, periodic=True, coarsest=start, reach=args.reach)
    return dict(box, d0_start=start, d0_last=start * CONSISTENCY_FACTOR ** 2, factor=CONSISTENCY_FACTOR)


#: The last D0 must leave two refinements from the first: the fitted slopes need two points.
TWO_REFINEMENTS: Check = (lambda v, c: len(consistency_levels(c["d0_start"], v)) >= 2,
                          "must be <= {d0_last:.3g}: the fitted slopes need two refinements (by {factor:g}) from "
                          "the first D0 = {d0_start:g}")

#: ``arpy run consistency``.  --reach comes before --D0-end: the periodic box's check of it uses the first D0.
CASE = Case(
    "consistency", "Sec. 4.1: convergence of interpolation and Laplacian while D0 shrinks (tanh front or blob)",
    (option(consistency, "field", "--field", "the field: the tanh front of Eq. 4.1 on [-1, 1]^2 or the blob of "
            "Eq. 4.3 (Sec. 4.2) in the periodic unit square", type=str, choices=tuple(CONSISTENCY_START)),
     option(consistency, "monitor", "--monitor",
            "the monitor: Eq. 2.8 (gradient) or Appendix B's Eq. B.13 from the exact fourth derivatives",
            type=str, choices=MONITORS),
     reach_option(consistency, PERIODIC),
     option(consistency, "d0_end", "--D0-end",
            "the last (finest) D0, a length: D0 starts at "
            + " or ".join(f"{v:g} ({k})" for k, v in CONSISTENCY_START.items())
            + f" and shrinks by {CONSISTENCY_FACTOR:g} per adaptation (the paper goes to 0.006)",
            POSITIVE, FEW_ENOUGH, TWO_REFINEMENTS),
     seed_option(consistency)),
    _context, run, columns=COLUMNS, seconds=27.0)
