"""Command-line interface: ``arpy <command> [options]`` (also ``python -m arpy``).

Every option is checked before any work starts: :data:`CASES` declares the options
each case of ``arpy run`` takes, with their checks, and :data:`DEMO` those of
``arpy demo``.  A bad value, or an option the case does not take, ends the command
with argparse's one-line error and exit code 2.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .cases import BUD_MAX_PARTICLES, CONSISTENCY_FACTOR, consistency_levels, pulse_setup
from .organize import MAX_PARTICLES
from .resolution import r_star
from .surface import Bud

__all__ = ["CASES", "COMMON", "DEMO", "Case", "build_parser", "main"]


def _demo(args: argparse.Namespace) -> int:
    """Neighbour lists for the AR benchmark distribution with every available method."""
    from ._bench import best_time, kdtree_pairs
    from .distributions import ar_benchmark
    from .neighbors import neighbor_list

    x, rc = ar_benchmark(args.n, args.lam, d=args.d)
    n = x.shape[0]
    print(f"arpy demo: AR benchmark distribution (Awile et al. 2012, Sec. 3.1), d = {args.d}")
    print(f"  {n} particles: {10 ** args.d} large (rc = {rc.max():g}) + {args.n} small (rc = {rc.min():g}),"
          f" resolution span lambda = {args.lam:g}")
    methods = {
        "ar (adaptive-resolution cells)": lambda: neighbor_list(x, rc, method="ar").pairs(),
        "cell (uniform cell list)": lambda: neighbor_list(x, rc, method="cell").pairs(),
        "cKDTree.query_pairs + min rule": lambda: _sorted(*kdtree_pairs(x, rc)),
    }
    if n <= args.brute_max:
        methods["brute (all pairs)"] = lambda: neighbor_list(x, rc, method="brute").pairs()
    rows, reference = [], None
    for name, fn in methods.items():
        t, (i, j) = best_time(fn, repeat=args.repeat)
        if reference is None:
            reference = (i, j)
        same = np.array_equal(i, reference[0]) and np.array_equal(j, reference[1])
        rows.append((name, i.size, t, same))
    print(f"\n  {'method':34s} {'pairs':>10s} {'time [ms]':>10s} {'ns/particle':>12s}  same pairs")
    for name, npairs, t, same in rows:
        print(f"  {name:34s} {npairs:10d} {1e3 * t:10.2f} {1e9 * t / n:12.1f}  {'yes' if same else 'NO'}")
    if n > args.brute_max:
        print(f"\n  (brute force skipped above {args.brute_max} particles; raise --brute-max to include it)")
    return 0 if all(r[3] for r in rows) else 1


def _sorted(i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order = np.lexsort((j, i))
    return i[order], j[order]


def _run(args: argparse.Namespace) -> int:
    """The test cases of §4.1-4.3 (see arpy.cases); writes plots and data into --out."""
    from pathlib import Path

    from . import cases
    from .io import write_vtk
    from .plotting import plot_burgers, plot_five_spot, save_figure, slope_lines

    out = Path(args.out) / args.case
    out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if args.case == "pulse":
        r = cases.gaussian_pulse(d=args.d, Pe=args.pe, D0=args.D0, T=args.T, reorganize_every=args.k,
                                 seed=args.seed, mass_every=args.mass_every, reach=args.reach,
                                 monitor=args.monitor, progress=not args.quiet)
        sim = r["sim"]
        print(f"arpy run pulse: Gaussian pulse rotated and diffused (Reboux et al. 2012, Sec. 4.3), d = {r['d']}, "
              f"Pe = {r['Pe']:g}, D0 = {r['D0']:g}, T = {args.T:g}, monitor {args.monitor}")
        print(f"  particles: {r['N_initial']} at t = 0, {r['N']} at t = T (largest {r['N_max']}), "
              f"h = {r['h']:.4g}; {r['steps']} steps in {r['wall_s']:.1f} s")
        print(f"  L-infinity error at T against Eq. 4.8: {r['error']:.3e}")
        print(f"  relative mass loss (Eq. 4.9) at T: {r['mass_loss'][-1]:.3e}")
        if r["degenerate_max"]:
            print(f"  note: up to {r['degenerate_max']} particles per step had no valid DC-PSE stencil")
        f_exact = r["exact"](sim.x, sim.t)
        base = None
        if args.remeshed:
            base = cases.remeshed_pulse(d=r["d"], Pe=r["Pe"], n_cells=args.remeshed, T=args.T)
            print(f"  remeshed particle method, {base['N']} particles (h = {base['h']:.4g}): error {base['error']:.3e}, "
                  f"{base['steps']} steps in {base['wall_s']:.1f} s")
        np.savez(out / "pulse.npz", x=sim.x, f=sim.f, D=sim.D, f_exact=f_exact, t=sim.t,
                 error_history=r["error_history"], mass_t=r["mass_t"], mass_loss=r["mass_loss"],
                 n_history=sim.history()["n"])
        write_vtk(out / "pulse_particles.vtk", sim.x, f=sim.f, D=sim.D, error=sim.f - f_exact)
        if r["d"] == 2:
            fig, axes = plt.subplots(1, 3, figsize=(16, 5))
            sc = axes[0].scatter(sim.x[:, 0], sim.x[:, 1], c=sim.f, s=2, cmap="viridis")
            fig.colorbar(sc, ax=axes[0], label="f")
            axes[0].set_aspect("equal")
            axes[0].set_title(f"f at t = {sim.t:g} (N = {sim.n})")
            from .organize import ParticleSet

            ParticleSet(sim.x, sim.D, sim.rstar, 10, sim.domain).plot(ax=axes[1], title="D_p", circles=8)
            axes[2].semilogy(r["error_history"][:, 0], r["error_history"][:, 1], label="L-inf error")
            axes[2].semilogy(r["mass_t"], np.abs(r["mass_loss"]) + 1e-16, "o-", label="|relative mass loss|")
            axes[2].set_xlabel("t")
            axes[2].legend()
            save_figure(fig, out / "pulse.png")
    elif args.case == "advection":
        r = cases.advection(D0=args.D0, T=args.T, reorganize_every=args.k, seed=args.seed, reach=args.reach,
                            monitor=args.monitor, progress=not args.quiet)
        sim = r["sim"]
        print(f"arpy run advection: a blob in the reversing vortex (Reboux et al. 2012, Sec. 4.2), RK4, dt = 0.025, "
              f"D0 = {args.D0:g}, monitor {args.monitor}")
        print(f"  particles: {r['N']} at T (largest {r['N_max']}), h = 1/sqrt(N_max) = {r['h']:.4g}; "
              f"{r['steps']} steps in {r['wall_s']:.1f} s")
        print(f"  L-infinity error of Eq. 4.5 at T: {r['error']:.3e}")
        np.savez(out / "advection.npz", x=sim.x, f=sim.f, D=sim.D, **{f"half_{k}": v for k, v in r["half"].items()})
        write_vtk(out / "advection_particles.vtk", sim.x, f=sim.f, D=sim.D)
        fig, axes = plt.subplots(1, 2, figsize=(11, 5))
        for ax, (x, f, title) in zip(axes, [(r["half"]["x"], r["half"]["f"], "t = T/2"), (sim.x, sim.f, "t = T")]):
            sc = ax.scatter(x[:, 0], x[:, 1], c=f, s=1, cmap="viridis")
            ax.set_aspect("equal")
            ax.set_title(f"{title}, N = {len(x)}")
        fig.colorbar(sc, ax=axes, label="f")
        fig.savefig(out / "advection.png", dpi=110)
        plt.close(fig)
    elif args.case == "burgers":
        r = cases.burgers(Re=args.re, D0=args.D0, T=args.T, reorganize_every=args.k, seed=args.seed,
                          reach=args.reach, progress=not args.quiet)
        sim, ref = r["sim"], r["reference"]
        print(f"arpy run burgers: 2D Burgers equation, u = (f, f) (Reboux et al. 2012, Sec. 4.4), Re = {args.re:g}, "
              f"D0 = {r['D0']:g}, T = {args.T:g}")
        print(f"  particles: {r['N_initial']} at t = 0, {r['N']} at t = T (largest {r['N_max']}), "
              f"h = 1/sqrt(N_max) = {r['h']:.4g}; {r['steps']} steps in {r['wall_s']:.1f} s")
        print(f"  fine/coarse scale ratio max D_p / min D_p at T: {r['scale_ratio']:.1f}")
        print(f"  L-infinity error at T against a {ref.n}^2 pseudo-spectral solution: {r['error']:.3e}"
              + ("" if args.re <= 100 else f" (indicative only: {ref.n}^2 is converged for Re <= 100)"))
        if args.remeshed:
            b = cases.remeshed_burgers(Re=args.re, n_cells=args.remeshed, T=args.T, reference=ref)
            print(f"  remeshed particle method (conservative form), {b['N']} particles (h = {b['h']:.4g}): "
                  f"error {b['error']:.3e}, {b['steps']} steps in {b['wall_s']:.1f} s")
        f_ref = ref(sim.x)
        np.savez(out / "burgers.npz", x=sim.x, f=sim.f, D=sim.D, f_reference=f_ref,
                 **{f"history_{k}": v for k, v in sim.history().items()})
        write_vtk(out / "burgers_particles.vtk", sim.x, f=sim.f, D=sim.D, error=sim.f - f_ref)
        plot_burgers(sim, out / "burgers.png", f"Re = {args.re:g}, T = {args.T:g} (Fig. 4.6)")
    elif args.case == "five-spot":
        r = cases.five_spot(mu=args.mu, nu=args.nu, D0=args.D0, T=args.T, reorganize_every=args.k,
                            seed=args.seed, reach=args.reach, progress=not args.quiet)
        sim = r["sim"]
        print(f"arpy run five-spot: viscous Buckley-Leverett, five-spot wells (Reboux et al. 2012, Sec. 4.5), "
              f"mu = {args.mu:g}, nu = {args.nu:g}, D0 = {r['D0']:g}, T = {args.T:g}")
        print(f"  particles: {r['N_initial']} at t = 0, {r['N']} at t = T (largest {int(r['n'].max())}); "
              f"{r['steps']} steps in {r['wall_s']:.1f} s")
        print(f"  saturation range at T: [{r['f_min']:.4f}, {r['f_max']:.4f}]")
        np.savez(out / "five_spot.npz", x=sim.x, f=sim.f, D=sim.D, t=r["t"], n=r["n"])
        write_vtk(out / "five_spot_particles.vtk", sim.x, f=sim.f, D=sim.D)
        plot_five_spot(r, out / "five_spot.png")
    elif args.case == "bud-surface":
        from .plotting import plot_bud_surface

        print(f"arpy run bud-surface: curvature-driven surface refinement (Reboux et al. 2012, Sec. 4.6), "
              f"D0 = {args.D0:g}, V1, band |phi| <= 4 D~")
        results = []
        for L in args.L:
            Dmin = cases.BUD_DMIN.get(round(L, 2))
            if Dmin is not None:
                print(f"  L = {L:g}: the neck is nearly pinched off; D~ is bounded below by Dmin = {Dmin:g}")
            r = cases.bud_surface(L, D0=args.D0, Dmin=Dmin, seed=args.seed, progress=not args.quiet)
            ps = r["particles"]
            cnt = ps.neighbor_list(symmetric=False).counts()
            print(f"  L = {L:g} (neck radius {r['neck_radius']:.3g}): N = {r['N']} (from {r['N_initial']}), "
                  f"D_p in [{r['D_min']:.3g}, {r['D_max']:.3g}], {r['iterations']} iterations "
                  f"({'converged' if r['converged'] else 'NOT converged'}), {r['wall_s']:.1f} s; "
                  f"neighbours >= {ps.n_star}: {np.mean(cnt[r['interior']] >= ps.n_star):.1%} of the "
                  f"{int(r['interior'].sum())} particles away from the band's edges, "
                  f"{np.mean(cnt >= ps.n_star):.1%} of all")
            np.savez(out / f"bud_L{L:g}.npz", x=ps.x, D=ps.D, phi=r["bud"].phi(ps.x))
            write_vtk(out / f"bud_L{L:g}_particles.vtk", ps.x, D=ps.D, phi=r["bud"].phi(ps.x))
            results.append(r)
        plot_bud_surface(results, out / "bud_surface.png", cases.BUD_PAPER_N)
    else:
        r = cases.consistency(d0_start=CONSISTENCY_START[args.field], d0_end=args.D0,
                              seed=args.seed, reach=args.reach, field=args.field, monitor=args.monitor,
                              progress=not args.quiet)
        what = ("the tanh front (Reboux et al. 2012, Sec. 4.1)" if args.field == "tanh" else
                "the blob of Sec. 4.2 at rest (Reboux et al. 2012)") + f", monitor {args.monitor}"
        print(f"arpy run consistency: interpolation and Laplacian on {what}; errors / max f")
        print(f"  {'D0':>7s} {'N':>7s} {'h':>8s} {'interp err':>11s} {'99th pct':>10s} {'Laplacian err':>14s}")
        for row in zip(r["D0"], r["N"], r["h"], r["err_interp"], r["p99_interp"], r["err_laplacian"]):
            print(f"  {row[0]:7.4f} {row[1]:7d} {row[2]:8.4f} {row[3]:11.3e} {row[4]:10.3e} {row[5]:14.3e}")
        print(f"  fitted slopes: interpolation {r['slope_interp']:.2f} (expected 4), "
              f"Laplacian {r['slope_laplacian']:.2f} (expected 2)")
        np.savez(out / "consistency.npz", **{k: v for k, v in r.items() if k != "last"})
        fig, ax = plt.subplots(figsize=(6, 4.5))
        ax.loglog(r["h"], r["err_interp"], "o", label="interpolation")
        ax.loglog(r["h"], r["err_laplacian"], "s", label="Laplacian")
        slope_lines(ax, r["h"], r["err_interp"], [4])
        slope_lines(ax, r["h"], r["err_laplacian"], [2])
        ax.set_xlabel("h = sqrt(|Omega| / N)")
        ax.set_ylabel("max error")
        ax.legend()
        save_figure(fig, out / "consistency.png")
    print(f"  wrote {out}/")
    return 0


#: A check of one option's value: (predicate of the value and the context, message).  The context
#: holds the namespace's values and the case's domain (:func:`_domain`); the message is formatted
#: with it and ``value``.  A predicate may raise ValueError, whose text then completes the message.
Check = tuple[Callable[[Any, dict[str, Any]], bool], str]


def _at_least(lo: float, *, strict: bool = False, kind: str = "a finite number", what: str = "") -> Check:
    """A finite value >= lo (> lo if strict); ``what`` says what the option is."""
    return (lambda v, _: math.isfinite(v) and (v > lo if strict else v >= lo),
            f"must be {kind} {'>' if strict else '>='} {lo:g}{what}")


def _closed_bud(L: float, _: dict[str, Any]) -> bool:
    """Whether the sphere and the bud at centre distance L join into a closed surface (else ValueError)."""
    Bud(L)
    return True


def _writable(out: str, context: dict[str, Any]) -> bool:
    """Whether the folder out/<case> exists, or can be created, and can be written."""
    path = Path(out, context["case"]).absolute()
    while not path.exists():
        path = path.parent
    return path.is_dir() and os.access(path, os.W_OK)


def _domain(edge: float, dim: int, *, periodic: bool = False, coarsest: float | None = None, reach: float = 1.0,
            max_particles: int = MAX_PARTICLES) -> dict[str, Any]:
    """The context of the checks that depend on a case's domain, a cube of edge ``edge`` in ``dim``
    dimensions: ``d0_min``, the D0 below which (edge / D0)^dim, about the particles at resolution D0
    before any refinement, exceeds ``max_particles``, where the case's self-organization stops;
    ``cells_max``, the most remeshing cells per edge within it; in a periodic box, ``cutoff``:
    reach r* D0 of its coarsest particles (D0 = ``coarsest``), which must stay below half the edge."""
    context = dict(edge=edge, dim=dim, periodic=periodic, max_particles=max_particles, r_star=r_star(dim),
                   d0_min=edge / max_particles ** (1 / dim), cells_max=math.floor(max_particles ** (1 / dim)))
    if periodic:
        context.update(coarsest=coarsest, cutoff=reach * r_star(dim) * coarsest)
    return context


POSITIVE = _at_least(0, strict=True)
NATURAL = _at_least(0, kind="an integer")
PERIODIC: Check = (lambda v, c: not c["periodic"] or c["cutoff"] < c["edge"] / 2,
                   "the periodic box of edge {edge:g} needs the cutoffs reach r* D0 (r* = {r_star:.3g}) below half "
                   "its edge, but --reach {reach:g} and the coarsest D0 = {coarsest:g} give {cutoff:.3g}")
FEW_ENOUGH: Check = (lambda v, c: v >= c["d0_min"],
                     "asks for more than {max_particles:.0e} particles, about (edge / D0)^{dim} on the {dim}D domain "
                     "of edge {edge:g}, where self-organization stops: use D0 >= {d0_min:.3g}")
RESOLUTION = (POSITIVE, FEW_ENOUGH, PERIODIC)
TWO_REFINEMENTS: Check = (lambda v, c: len(consistency_levels(c["d0_start"], v)) >= 2,
                          "must be <= {d0_last:.3g}: the fitted slopes need two refinements (by {factor:g}) from "
                          "the first D0 = {d0_start:g}")
REACH = _at_least(1, what=" (the factor on the ball of Eq. 2.9; 1 is the paper's)")
TIME = _at_least(0, strict=True, what=" (the final time)")
EVERY = _at_least(0, kind="an integer", what=" (0: never re-organize)")
REMESHED: tuple[Check, ...] = (
    _at_least(0, kind="an integer", what=" (0: skip the remeshed baseline)"),
    (lambda v, c: v <= c["cells_max"], "makes more than {max_particles:.0e} mesh particles ({value}^{dim}): "
                                       "use at most {cells_max} cells per edge"))


def _pulse_context(args: argparse.Namespace) -> dict[str, Any]:
    """The pulse's box (:func:`arpy.cases.pulse_setup`): a cube of edge 2 in 2D, 3 in 3D."""
    lo, hi = pulse_setup(args.d, 1.0)["box"]
    return _domain(float(hi[0] - lo[0]), args.d)


#: Where ``arpy run consistency`` starts refining, per --field.
CONSISTENCY_START = {"tanh": 0.4, "blob": 0.25}


def _consistency_context(args: argparse.Namespace) -> dict[str, Any]:
    """The domain of --field (tanh: [-1, 1]^2 with walls; blob: the periodic unit square) and the first D0."""
    start = CONSISTENCY_START[args.field]
    domain = _domain(2.0, 2) if args.field == "tanh" else _domain(1.0, 2, periodic=True, coarsest=start,
                                                                  reach=args.reach)
    return dict(domain, d0_start=start, d0_last=start * CONSISTENCY_FACTOR ** 2, factor=CONSISTENCY_FACTOR)


@dataclass(frozen=True)
class Case:
    """What ``arpy run <case>`` takes: its options, in the order they are checked, each with its
    checks; the context of the checks (its domain); and the defaults that depend on the case
    (values, or functions of the namespace), filled in for the options not given."""

    options: dict[str, tuple[Check, ...]]
    context: Callable[[argparse.Namespace], dict[str, Any]]
    defaults: dict[str, Any] = field(default_factory=dict)


#: The options of ``arpy run``, per case.  --reach comes before --D0: the box's check of D0 uses it.
CASES: dict[str, Case] = {
    "pulse": Case(
        {"--d": (), "--pe": (_at_least(0, strict=True, what=" (the Peclet number; the diffusivity is 1 / Pe)"),),
         "--reach": (REACH,), "--D0": RESOLUTION, "--T": (TIME,), "--k": (EVERY,), "--remeshed": REMESHED,
         "--mass-every": (_at_least(0, kind="an integer", what=" (0: at the start and the end)"),),
         "--monitor": ()},
        _pulse_context,
        {"--T": 1.0, "--k": 10}),
    "advection": Case(
        {"--reach": (REACH,), "--D0": RESOLUTION, "--T": (TIME,), "--k": (EVERY,), "--monitor": ()},
        lambda a: _domain(1.0, 2, periodic=True, coarsest=a.D0, reach=a.reach),
        {"--T": 2.5, "--k": 4, "--D0": lambda a: 0.25 if a.monitor == "fourth" else 0.2}),
    "burgers": Case(
        {"--re": (_at_least(0, strict=True, what=" (the Reynolds number; the viscosity is 1 / Re)"),),
         "--reach": (REACH,), "--D0": RESOLUTION, "--T": (TIME,), "--k": (EVERY,), "--remeshed": REMESHED},
        lambda a: _domain(1.0, 2, periodic=True, coarsest=a.D0, reach=a.reach),
        {"--T": 0.1, "--k": 10, "--D0": 0.1}),
    "five-spot": Case(
        {"--mu": (_at_least(0, strict=True, what=" (the viscosity ratio of Eq. 4.13: g(f) = f^2 / (f^2 + mu "
                                                  "(1 - f)^2))"),),
         "--nu": (_at_least(0, what=" (the diffusion coefficient)"),),
         "--reach": (REACH,), "--D0": RESOLUTION, "--T": (TIME,), "--k": (EVERY,)},
        lambda a: _domain(1.0, 2),
        {"--T": 0.09, "--k": 10, "--D0": 0.1}),
    "consistency": Case(
        {"--field": (), "--monitor": (), "--reach": (REACH, PERIODIC), "--D0": (POSITIVE, FEW_ENOUGH, TWO_REFINEMENTS)},
        _consistency_context,
        {"--D0": 0.2}),
    "bud-surface": Case(
        {"--L": ((_closed_bud, "must join the sphere and the bud into a closed surface"),), "--D0": RESOLUTION},
        lambda a: _domain(1.0, 3, max_particles=BUD_MAX_PARTICLES),
        {"--D0": 0.1, "--L": [0.40]}),
}
#: The options of ``arpy run`` that every case takes.
COMMON: dict[str, tuple[Check, ...]] = {
    "--seed": (NATURAL,),
    "--out": ((_writable, "must be a folder that exists, or can be created, and can be written"),),
    "--quiet": (),
}
#: The options of ``arpy demo``.
DEMO: dict[str, tuple[Check, ...]] = {
    "--n": (_at_least(1, kind="an integer"),),
    "--lam": (_at_least(1, what=" (the resolution span, the largest cutoff over the smallest)"),),
    "--d": (),
    "--repeat": (_at_least(1, kind="an integer"),),
    "--brute-max": (NATURAL,),
}


def _dest(flag: str) -> str:
    """The namespace attribute of an option."""
    return flag[2:].replace("-", "_")


def _failure(value: Any, checks: tuple[Check, ...], context: dict[str, Any]) -> str | None:
    """The message of the first check the value fails, or None."""
    for ok, message in checks:
        try:
            if ok(value, context):
                continue
            reason = ""
        except ValueError as exc:
            reason = f" ({exc})"
        return message.format(value=value, **context) + reason
    return None


def _check(args: argparse.Namespace, options: dict[str, tuple[Check, ...]], context: dict[str, Any]) -> None:
    """Ends the command with its parser's error at the first value (of a list: element) that fails its
    option's checks; None, the case function's own default, is not checked."""
    for flag, checks in options.items():
        value = getattr(args, _dest(flag))
        for v in value if isinstance(value, list) else [value]:
            failure = None if v is None else _failure(v, checks, context)
            if failure:
                args.parser.error(f"argument {flag}: {v}: {failure}")


def _settle(args: argparse.Namespace) -> None:
    """Checks the options of ``args.command`` before any work; for ``run``, refuses the options its case
    does not take and fills in the defaults that depend on the case."""
    if args.command == "demo":
        _check(args, DEMO, vars(args))
        return
    case = CASES[args.case]
    foreign = [flag for flag in dict.fromkeys(args.given) if flag not in case.options and flag not in COMMON]
    if foreign:
        args.parser.error(f"{', '.join(foreign)} {'does' if len(foreign) == 1 else 'do'} not apply to case "
                          f"{args.case}; it takes {' '.join(case.options)} (and {' '.join(COMMON)})")
    for flag, default in case.defaults.items():
        if getattr(args, _dest(flag)) is None:
            setattr(args, _dest(flag), default(args) if callable(default) else default)
    _check(args, {**case.options, **COMMON}, {**vars(args), **case.context(args)})


def _cases_help() -> str:
    """The options each case of ``arpy run`` takes, from :data:`CASES`."""
    width = max(map(len, CASES)) + 1
    return "\n".join(["options by case:", *(f"  {name + ':':{width}s} {' '.join(case.options)}"
                                           for name, case in CASES.items()),
                      f"  {'all:':{width}s} {' '.join(COMMON)}"])


class _Given(argparse.Action):
    """argparse's default action, storing the value, that also records the option in ``namespace.given``."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        setattr(namespace, self.dest, values)
        namespace.given = (*namespace.given, self.option_strings[0])


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``arpy`` command."""
    parser = argparse.ArgumentParser(prog="arpy", description="Adaptive-resolution particle methods.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="command")
    demo = sub.add_parser("demo", help="neighbour lists of the AR benchmark distribution, every method timed")
    demo.add_argument("--n", type=int, default=20000, help="number of small particles (default 20000)")
    demo.add_argument("--lam", type=float, default=10.0, help="resolution span lambda (default 10)")
    demo.add_argument("--d", type=int, default=2, choices=(2, 3), help="dimension (default 2)")
    demo.add_argument("--repeat", type=int, default=3, help="timing repeats, best is shown (default 3)")
    demo.add_argument("--brute-max", type=int, default=30000, help="largest n for brute force (default 30000)")
    demo.set_defaults(func=_demo, parser=demo)
    run = sub.add_parser("run", help="a test case of the JCP paper: pulse (default), advection, burgers, "
                                     "five-spot, consistency, bud-surface",
                         epilog=_cases_help(), formatter_class=argparse.RawDescriptionHelpFormatter)
    option = partial(run.add_argument, action=_Given)
    run.add_argument("case", nargs="?", default="pulse",
                     choices=("pulse", "advection", "burgers", "five-spot", "consistency", "bud-surface"),
                     help="pulse: Sec. 4.3 rotation + diffusion; advection: Sec. 4.2 vortex; burgers: Sec. 4.4 "
                          "2D Burgers equation; five-spot: Sec. 4.5 Buckley-Leverett; consistency: Sec. 4.1 "
                          "convergence of interpolation and Laplacian; bud-surface: Sec. 4.6 particles refining "
                          "a curved surface (Figs. 4.10, 4.11)")
    option("--d", type=int, default=2, choices=(2, 3), help="pulse: dimension (default 2)")
    option("--pe", type=float, default=None, help="pulse: Peclet number (default 1000 in 2D, 100 in 3D)")
    option("--D0", type=float, default=None,
           help="coarsest resolution (pulse: 0.08 in 2D, 0.5 in 3D, with --monitor fourth 0.2 and "
                "1.0; advection: 0.2, with --monitor fourth 0.25; "
                "burgers, five-spot and bud-surface: 0.1); "
                "consistency: the last D0 (default 0.2; the paper goes to 0.006)")
    option("--L", type=float, nargs="+", default=None,
           help="bud-surface: distances between the sphere and bud centres (default 0.40; the paper "
                "shows 0.40 0.45 0.50 0.56)")
    option("--re", type=float, default=100.0, help="burgers: Reynolds number (default 100)")
    option("--mu", type=float, default=0.5, help="five-spot: viscosity ratio in Eq. 4.13 (default 0.5)")
    option("--nu", type=float, default=0.01, help="five-spot: diffusion coefficient (default 0.01)")
    option("--T", type=float, default=None,
           help="final time (pulse: 1; advection: 2.5; burgers: 0.1; five-spot: 0.09)")
    option("--k", type=int, default=None,
           help="steps between re-organizations (pulse and burgers 10, advection 4)")
    option("--remeshed", type=int, default=128,
           help="pulse, burgers: also run the remeshed baseline with this many cells per edge (0: skip)")
    option("--mass-every", type=int, default=10, help="pulse: steps between mass evaluations")
    option("--reach", type=float, default=1.0,
           help="factor on the ball of Eq. 2.9 (1: the paper's; 2 grades D_p more slowly near fine "
                "features: 2D pulse order 1.8 instead of 1.5 with Eq. 2.8; --monitor fourth: 2.2)")
    option("--field", choices=("tanh", "blob"), default="tanh",
           help="consistency: the tanh front of Eq. 4.1 (default) or the blob of Eq. 4.3 (Sec. 4.2)")
    option("--monitor", choices=("gradient", "fourth"), default="gradient",
           help="pulse, advection and consistency: the monitor, Eq. 2.8 (default) or Appendix B's "
                "Eq. B.13 from fourth derivatives (pulse and advection: DC-PSE estimates at every "
                "re-organization; consistency: exact)")
    option("--seed", type=int, default=1, help="seed of the random initial particles and insertions (default 1)")
    option("--out", default="arpy-output", help="output folder (default ./arpy-output)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.set_defaults(func=_run, parser=run, given=())
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``arpy`` command; returns the process exit code."""
    args = build_parser().parse_args(argv)
    _settle(args)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
