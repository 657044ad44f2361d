"""Command-line interface: ``arpy <command> [options]`` (also ``python -m arpy``)."""

from __future__ import annotations

import argparse
import sys

import numpy as np

__all__ = ["main"]


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

            ParticleSet(sim.x, sim.D, sim.rstar, 10, sim.box).plot(ax=axes[1], title="D_p", circles=8)
            axes[2].semilogy(r["error_history"][:, 0], r["error_history"][:, 1], label="L-inf error")
            axes[2].semilogy(r["mass_t"], np.abs(r["mass_loss"]) + 1e-16, "o-", label="|relative mass loss|")
            axes[2].set_xlabel("t")
            axes[2].legend()
            save_figure(fig, out / "pulse.png")
    elif args.case == "advection":
        D0 = args.D0 or (0.25 if args.monitor == "fourth" else 0.2)
        r = cases.advection(D0=D0, T=args.T, reorganize_every=args.k, seed=args.seed, reach=args.reach,
                            monitor=args.monitor, progress=not args.quiet)
        sim = r["sim"]
        print(f"arpy run advection: a blob in the reversing vortex (Reboux et al. 2012, Sec. 4.2), RK4, dt = 0.025, "
              f"D0 = {D0:g}, monitor {args.monitor}")
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
        r = cases.burgers(Re=args.re, D0=args.D0 or 0.1, T=args.T, reorganize_every=args.k, seed=args.seed,
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
        r = cases.five_spot(mu=args.mu, nu=args.nu, D0=args.D0 or 0.1, T=args.T, reorganize_every=args.k,
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

        Ls = args.L or [0.40]
        print(f"arpy run bud-surface: curvature-driven surface refinement (Reboux et al. 2012, Sec. 4.6), "
              f"D0 = {args.D0 or 0.1:g}, V1, band |phi| <= 4 D~")
        results = []
        for L in Ls:
            Dmin = cases.BUD_DMIN.get(round(L, 2))
            if Dmin is not None:
                print(f"  L = {L:g}: the neck is nearly pinched off; D~ is bounded below by Dmin = {Dmin:g}")
            r = cases.bud_surface(L, D0=args.D0 or 0.1, Dmin=Dmin, seed=args.seed, progress=not args.quiet)
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
        r = cases.consistency(d0_start=0.4 if args.field == "tanh" else 0.25, d0_end=args.D0 or 0.2,
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
    demo.set_defaults(func=_demo)
    run = sub.add_parser("run", help="a test case of the JCP paper: pulse (default), advection, burgers, "
                                     "five-spot, consistency, bud-surface")
    run.add_argument("case", nargs="?", default="pulse",
                     choices=("pulse", "advection", "burgers", "five-spot", "consistency", "bud-surface"),
                     help="pulse: Sec. 4.3 rotation + diffusion; advection: Sec. 4.2 vortex; burgers: Sec. 4.4 "
                          "2D Burgers equation; five-spot: Sec. 4.5 Buckley-Leverett; consistency: Sec. 4.1 "
                          "convergence of interpolation and Laplacian; bud-surface: Sec. 4.6 particles refining "
                          "a curved surface (Figs. 4.10, 4.11)")
    run.add_argument("--d", type=int, default=2, choices=(2, 3), help="pulse: dimension (default 2)")
    run.add_argument("--pe", type=float, default=None, help="pulse: Peclet number (default 1000 in 2D, 100 in 3D)")
    run.add_argument("--D0", type=float, default=None,
                     help="coarsest resolution (pulse: 0.08 in 2D, 0.5 in 3D, with --monitor fourth 0.2 and "
                          "1.0; advection: 0.2, with --monitor fourth 0.25; "
                          "burgers, five-spot and bud-surface: 0.1); "
                          "consistency: the last D0 (default 0.2; the paper goes to 0.006)")
    run.add_argument("--L", type=float, nargs="+", default=None,
                     help="bud-surface: distances between the sphere and bud centres (default 0.40; the paper "
                          "shows 0.40 0.45 0.50 0.56)")
    run.add_argument("--re", type=float, default=100.0, help="burgers: Reynolds number (default 100)")
    run.add_argument("--mu", type=float, default=0.5, help="five-spot: viscosity ratio in Eq. 4.13 (default 0.5)")
    run.add_argument("--nu", type=float, default=0.01, help="five-spot: diffusion coefficient (default 0.01)")
    run.add_argument("--T", type=float, default=None,
                     help="final time (pulse: 1; advection: 2.5; burgers: 0.1; five-spot: 0.09)")
    run.add_argument("--k", type=int, default=None,
                     help="steps between re-organizations (pulse and burgers 10, advection 4)")
    run.add_argument("--remeshed", type=int, default=128,
                     help="pulse, burgers: also run the remeshed baseline with this many cells per edge (0: skip)")
    run.add_argument("--mass-every", type=int, default=10, help="pulse: steps between mass evaluations")
    run.add_argument("--reach", type=float, default=1.0,
                     help="factor on the ball of Eq. 2.9 (1: the paper's; 2 grades D_p more slowly near fine "
                          "features: 2D pulse order 1.8 instead of 1.5 with Eq. 2.8; --monitor fourth: 2.2)")
    run.add_argument("--field", choices=("tanh", "blob"), default="tanh",
                     help="consistency: the tanh front of Eq. 4.1 (default) or the blob of Eq. 4.3 (Sec. 4.2)")
    run.add_argument("--monitor", choices=("gradient", "fourth"), default="gradient",
                     help="pulse, advection and consistency: the monitor, Eq. 2.8 (default) or Appendix B's "
                          "Eq. B.13 from fourth derivatives (pulse and advection: DC-PSE estimates at every "
                          "re-organization; consistency: exact)")
    run.add_argument("--seed", type=int, default=1)
    run.add_argument("--out", default="arpy-output", help="output folder (default ./arpy-output)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.set_defaults(func=_run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``arpy`` command; returns the process exit code."""
    args = build_parser().parse_args(argv)
    if getattr(args, "case", None) is not None:
        if args.k is None:
            args.k = 4 if args.case == "advection" else 10
        if args.T is None:
            args.T = {"advection": 2.5, "burgers": 0.1, "five-spot": 0.09}.get(args.case, 1.0)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
