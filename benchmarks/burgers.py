"""Benchmark: the 2D Burgers equation of Reboux et al. (2012), §4.4 and §4.7.

  fig46   Re = 1000 to T = 0.17 with D0 = 0.15: the solution and the particle
          distribution; the fine/coarse scale ratio max D_p / min D_p (the
          paper: about 12).
  fig47   Re = 100 to T = 0.1: L-infinity error vs h = 1 / sqrt(N) against a
          pseudo-spectral reference (its own convergence is tested), for the
          adaptive method and the remeshed baseline in conservative form
          (Eq. 4.11); fitted orders (the paper: 2 and 2) and the particle
          ratio at equal error (the paper: about 8).
  fig412  the cost of the fig47 adaptive runs: wall time per step split into
          the monitor (DC-PSE gradient + Eq. 2.9), self-organization (its
          neighbour lists, the rest), DC-PSE old -> new at re-organizations and
          the right-hand side at the other steps; gradient-descent iterations
          per adaptation over the run; the net speed-up against the remeshed
          baseline at equal error (the paper: 36 % self-organization, 64 %
          mostly DC-PSE construction; about 2x faster than remeshing).

Writes JSON, PNG and the Markdown page (results/burgers.md, see report()) into --out.

    python benchmarks/burgers.py            # full sizes (about 15 minutes)
    python benchmarks/burgers.py --quick    # seconds (used by the tests)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from arpy import cases
from arpy._bench import benchmark_args, md_table, run_info, span, write_page, write_result
from arpy.simulation import PHASES

HERE = Path(__file__).resolve().parent
FULL = dict(fig46=dict(Re=1000.0, T=0.17, D0=0.15), fig47=dict(Re=100.0, T=0.1, D0=[0.14, 0.1, 0.07, 0.05],
                                                               n_cells=[64, 128, 256, 512]))
QUICK = dict(fig46=dict(Re=1000.0, T=0.01, D0=0.25), fig47=dict(Re=100.0, T=0.02, D0=[0.25, 0.2],
                                                               n_cells=[32, 64]))
#: Reboux et al. (2012): Fig. 4.6 (fine/coarse scale ratio), Fig. 4.7 (orders; remeshed / adaptive
#: particles at equal error), §4.7 (net speed-up over remeshing; shares of the CPU time: self-
#: organization of the total, and DC-PSE / neighbour lists / the rest of self-organization;
#: gradient-descent iterations per adaptation), §4.4 (the reference solution's mesh).
PAPER = dict(scale_ratio=12, orders=2, particle_ratio=8, speedup=2, share_self_organization=0.36,
             self_organization_split=dict(dcpse=0.57, lists=0.38, rest=0.05), reference_grid=2048,
             iterations_usual=2, iterations_rearranging=(8, 18), iterations_N=40000, reorganize_every=10)
#: Time steps between re-organizations (the paper's).
REORGANIZE_EVERY = PAPER["reorganize_every"]


def cost_split(sim) -> dict:
    """Wall time of a run by phase (s) and the shares the paper quotes (§4.7)."""
    h = sim.history()
    tot = {k: float(h[k].sum()) for k in PHASES}
    tot["step"] = float(h["t_step"].sum())
    tot["other"] = tot["step"] - sum(tot[k] for k in PHASES)
    so = tot["t_monitor"] + tot["t_organize_lists"] + tot["t_organize_rest"]
    return dict(seconds=tot, share_self_organization=so / tot["step"],
                share_dcpse_and_rest=1 - so / tot["step"],
                self_organization_split=dict(dcpse_monitor=tot["t_monitor"] / so, lists=tot["t_organize_lists"] / so,
                                             rest=tot["t_organize_rest"] / so),
                so_iterations=h["so_iterations"][h["reorganized"]].tolist(),
                t_reorganized=h["t"][h["reorganized"]].tolist(), steps=int(len(h["t"])), N=h["n"].tolist())


# ------------------------------------------------------------------ report
def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    """A Markdown table and a blank line."""
    return md_table(header, rows) + [""]


def _span(values, fmt: str = "{:.1f}") -> str:
    """'lo–hi' of the values in ``fmt`` (one value if they agree at that precision)."""
    return span(values, fmt.format)


def report(res: dict) -> str:
    """The Markdown page of a result (results/burgers.md is this of results/burgers.json)."""
    stem = "burgers_quick" if res.get("quick") else "burgers"
    f46, f47 = res["fig46"], res["fig47"]
    adaptive, remeshed = f47["adaptive"], f47["remeshed"]
    every = res["parameters"].get("reorganize_every", REORGANIZE_EVERY)
    ref = f47["reference_grid"]
    pct = "{:.0f} %"
    lines = ["# Burgers equation: Figs. 4.6, 4.7 and 4.12 of Reboux et al. (2012)", ""]
    if res.get("quick"):
        lines += ["**Quick run** (small sizes, for the tests): the numbers are not comparable with the paper's.", ""]
    lines += ["`python benchmarks/burgers.py` runs the benchmark and writes `burgers.json`, this page and the "
              "figures into `benchmarks/results/`; `--quick` runs small sizes in seconds (for the tests) and writes "
              "`burgers_quick.*`.", "",
              "## Set-up", "",
              "- The 2D Burgers equation (Eq. 4.10), u = (f, f), f(x, y, 0) = sin(2πx) cos(2πy), in the doubly "
              "periodic unit square.",
              "- Adaptive (arpy): random particles self-organize to f(x, 0); forward Euler with dt from the CFL and "
              f"diffusion limits of the smallest spacing; re-organization every {every} steps "
              + ("(as in the paper)." if every == PAPER["reorganize_every"] else
                 f"(the paper: every {PAPER['reorganize_every']})."),
              "- Remeshed baseline, as in the paper: the conservative form (Eq. 4.11), velocity u/2, forward Euler "
              "with dt = h²·Re/4, M′4 remeshing at every step, diffusion by centred finite differences.",
              f"- Error: L∞ at T against a {ref}² pseudo-spectral solution (`arpy.reference.burgers`; its "
              f"convergence is tested in `tests/test_burgers.py`). The paper used a {PAPER['reference_grid']}² "
              "remeshed solution.",
              "- Wall times are those of whole runs, the adaptive method's initial self-organization included.", ""]

    # ---- Fig. 4.7
    lines += [f"## Fig. 4.7: convergence (Re = {f47['Re']:g}, T = {f47['T']:g})", ""]
    rows = [["adaptive", f"D0 = {a['D0']:g}", f"{a['N']}", f"{a['h']:.4f}", f"{a['error']:.2e}", f"{a['steps']}",
             f"{a['wall_s']:.1f}", f"{a['particle_ratio']:.1f}", f"{a['speedup']:.1f}"] for a in adaptive]
    rows += [["remeshed", f"{b['n_cells']}²", f"{b['N']}", f"{b['h']:.4f}", f"{b['error']:.2e}", f"{b['steps']}",
              f"{b['wall_s']:.1f}", "–", "–"] for b in remeshed]
    lines += _table(["method", "resolution", "N (largest)", "h = 1/√N", "L∞ error", "steps", "wall (s)",
                     "remeshed / adaptive N at equal error", "remeshed / adaptive wall time at equal error"], rows)
    pr, sp = [a["particle_ratio"] for a in adaptive], [a["speedup"] for a in adaptive]
    o = f47["orders"]
    worst = max(abs(o[k] - PAPER["orders"]) for k in ("adaptive", "remeshed"))
    second_order = worst <= 0.25
    lines += _table(["", "arpy", "paper"],
                    [["fitted order, adaptive", f"{o['adaptive']:.2f}", f"{PAPER['orders']}"],
                     ["fitted order, remeshed", f"{o['remeshed']:.2f}", f"{PAPER['orders']}"],
                     ["remeshed / adaptive particles at equal error", _span(pr), f"about {PAPER['particle_ratio']}"],
                     ["remeshed / adaptive wall time at equal error", _span(sp), f"about {PAPER['speedup']}"]])
    lines += ["The ratios at equal error come from a power-law fit of the remeshed runs' error against N (or wall "
              "time), evaluated at each adaptive run's error.", "",
              "- " + ("Both methods converge at about second order, as in the paper." if second_order else
                      f"The fitted orders differ from the paper's {PAPER['orders']} by up to {worst:.2f}."),
              f"- At equal error the remeshed method needs {_span(pr)} times as many particles as the adaptive one, "
              f"{_span([x / PAPER['particle_ratio'] for x in pr])} times the paper's ratio.",
              f"- The net speed-up at equal error is {_span(sp)}, {_span([x / PAPER['speedup'] for x in sp])} times "
              "the paper's. The remeshed baseline is NumPy while the adaptive method runs mostly in Fortran.", "",
              f"![Fig. 4.7: L∞ error against h = 1/√N, adaptive and remeshed]({stem}_fig47.png)", ""]

    # ---- Fig. 4.12
    cost = [a["cost"] for a in adaptive]
    so = [c["share_self_organization"] for c in cost]
    split = [c["self_organization_split"] for c in cost]
    its = [c["so_iterations"] for c in cost]
    ps = PAPER["self_organization_split"]
    lines += ["## Fig. 4.12 and §4.7: cost of the adaptive runs", "",
              "Shares of the time of all steps. Self-organization = the monitor (its DC-PSE gradient and Eq. 2.9), "
              "the neighbour lists and the rest (fusion, insertion, forces, line search and so on). The rest of a "
              "step is the right-hand side (DC-PSE operators built at every step) and, at re-organizations, DC-PSE "
              "old → new (interpolation and right-hand side).", ""]
    rows = [[f"{a['D0']:g}", f"{a['N']}", f"{c['steps']}", f"{1e3 * c['seconds']['step'] / c['steps']:.1f}",
             pct.format(100 * c["share_self_organization"]), pct.format(100 * c["share_dcpse_and_rest"]),
             pct.format(100 * s["dcpse_monitor"]), pct.format(100 * s["lists"]), pct.format(100 * s["rest"]),
             f"{sum(i) / len(i):.1f} ({max(i)})" if i else "–"]
            for a, c, s, i in zip(adaptive, cost, split, its)]
    rows.append(["paper", "", "", "", pct.format(100 * PAPER["share_self_organization"]),
                 pct.format(100 * (1 - PAPER["share_self_organization"])), pct.format(100 * ps["dcpse"]),
                 pct.format(100 * ps["lists"]), pct.format(100 * ps["rest"]),
                 f"usually {PAPER['iterations_usual']}; {PAPER['iterations_rearranging'][0]}–"
                 f"{PAPER['iterations_rearranging'][1]} at larger rearrangements"])
    lines += _table(["D0", "N", "steps", "ms per step", "self-organization", "rest of the step",
                     "of self-org.: DC-PSE", "neighbour lists", "rest", "iterations per adaptation: mean (max)"], rows)
    sec = [c["seconds"] for c in cost]
    parts = dict(dcpse_monitor="the monitor's DC-PSE gradient", lists="the neighbour lists", rest="the rest")
    key = max(parts, key=lambda k: sum(s[k] for s in split))
    top = parts[key]
    dc_like = [(s["t_monitor"] + s["t_interpolate"]) / (s["t_monitor"] + s["t_organize_lists"]
                                                        + s["t_organize_rest"] + s["t_interpolate"]) for s in sec]
    lines += [f"- Self-organization takes {_span([100 * x for x in so], '{:.0f}')} % of the step time, against "
              f"{100 * PAPER['share_self_organization']:.0f} % in the paper.",
              f"- Within it, the largest part of arpy's time goes to {top} "
              f"({_span([100 * s[key] for s in split], '{:.0f}')} %), the paper's to the DC-PSE operators and the "
              "neighbour lists. The paper's "
              f"{100 * ps['dcpse']:.0f} % also counts the operators that interpolate to the adapted positions, "
              "which arpy books outside self-organization; counted the same way (the monitor plus DC-PSE old → new), "
              "arpy's DC-PSE share is "
              f"{_span([100 * x for x in dc_like], '{:.0f}')} %.",
              f"- The paper's iteration counts are for N = {PAPER['iterations_N']}; the largest run here has N = "
              f"{max(a['N'] for a in adaptive)}.", "",
              f"![Fig. 4.12: (a) wall time per step by phase, (b) gradient-descent iterations per adaptation over "
              f"time]({stem}_fig412.png)", ""]

    # ---- Fig. 4.6
    lines += [f"## Fig. 4.6: Re = {f46['Re']:g}, T = {f46['T']:g}, D0 = {f46['D0']:g}", ""]
    lines += _table(["", "arpy", "paper"],
                    [["particles at t = 0 → T (largest)", f"{f46['N_initial']} → {f46['N']} ({f46['N_max']})",
                      "–"],
                     ["fine/coarse scale ratio max D_p / min D_p at T", f"{f46['scale_ratio']:.1f}",
                      f"about {PAPER['scale_ratio']}"],
                     ["D_p at T", f"{f46['D_min']:.3g} – {f46['D_max']:.3g}", "–"],
                     ["f at T", f"[{f46['f_min']:.3f}, {f46['f_max']:.3f}]", "–"],
                     ["steps, wall time", f"{f46['steps']}, {f46['wall_s']:.1f} s", "–"]])
    lines += [f"- The scale ratio is {f46['scale_ratio'] / PAPER['scale_ratio']:.1f} times the paper's.",
              f"- The {ref}² reference does not resolve Re = {f46['Re']:g}, so no error is given.", "",
              f"![Fig. 4.6: (a) f_p, (b) the particles coloured by D_p]({stem}_fig46.png)", ""]
    lines += [f"Run on {res['machine']} with Python {res['python']}; the whole benchmark took "
              f"{res['wall_s'] / 60:.0f} min."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = benchmark_args(__doc__, argv, HERE / "results")
    import matplotlib.pyplot as plt

    from arpy.plotting import plot_burgers, save_figure, slope_lines

    tag = "burgers_quick" if args.quick else "burgers"
    p = QUICK if args.quick else FULL
    result: dict = {**run_info(), "quick": args.quick, "parameters": {**p, "reorganize_every": REORGANIZE_EVERY}}
    t_all = time.perf_counter()

    q = p["fig46"]
    print(f"Fig. 4.6 (§4.4): Re = {q['Re']:g}, T = {q['T']}, D0 = {q['D0']}")
    r = cases.burgers(Re=q["Re"], D0=q["D0"], T=q["T"], reorganize_every=REORGANIZE_EVERY, reference=False,
                      progress=not args.quick)
    sim46 = r["sim"]
    result["fig46"] = dict(Re=q["Re"], T=q["T"], D0=q["D0"], N_initial=r["N_initial"], N=r["N"], N_max=r["N_max"],
                           scale_ratio=r["scale_ratio"], D_min=float(sim46.D.min()), D_max=float(sim46.D.max()),
                           f_min=float(sim46.f.min()), f_max=float(sim46.f.max()), steps=r["steps"],
                           wall_s=r["wall_s"], paper_scale_ratio=PAPER["scale_ratio"])
    print(f"  N {r['N_initial']} -> {r['N']} (largest {r['N_max']}), scale ratio max D / min D = "
          f"{r['scale_ratio']:.1f} (paper: about 12), f in [{sim46.f.min():.3f}, {sim46.f.max():.3f}], "
          f"{r['steps']} steps in {r['wall_s']:.1f} s")

    q = p["fig47"]
    print(f"\nFig. 4.7 (§4.4): Re = {q['Re']:g}, T = {q['T']}")
    ref = cases.burgers_reference(q["Re"], q["T"])
    print(f"{'method':>9s} {'D0/cells':>8s} {'N':>7s} {'h':>8s} {'error':>10s} {'steps':>6s} {'wall s':>7s}")
    remeshed, adaptive, sims = [], [], []
    for m in q["n_cells"]:
        b = cases.remeshed_burgers(Re=q["Re"], n_cells=m, T=q["T"], reference=ref)
        remeshed.append(dict(n_cells=m, N=b["N"], h=b["h"], error=b["error"], steps=b["steps"], wall_s=b["wall_s"]))
        print(f"{'remeshed':>9s} {m:8d} {b['N']:7d} {b['h']:8.5f} {b['error']:10.3e} {b['steps']:6d} "
              f"{b['wall_s']:7.1f}")
    for d0 in q["D0"]:
        r = cases.burgers(Re=q["Re"], D0=d0, T=q["T"], reorganize_every=REORGANIZE_EVERY, reference=ref)
        sims.append(r["sim"])
        adaptive.append(dict(D0=d0, N_initial=r["N_initial"], N=r["N_max"], h=r["h"], error=r["error"],
                             steps=r["steps"], wall_s=r["wall_s"], scale_ratio=r["scale_ratio"],
                             cost=cost_split(r["sim"])))
        print(f"{'adaptive':>9s} {d0:8.3f} {r['N_max']:7d} {r['h']:8.5f} {r['error']:10.3e} {r['steps']:6d} "
              f"{r['wall_s']:7.1f}")
    na, ea = np.array([a["N"] for a in adaptive], float), np.array([a["error"] for a in adaptive])
    nr, er = np.array([b["N"] for b in remeshed], float), np.array([b["error"] for b in remeshed])
    wa, wr = np.array([a["wall_s"] for a in adaptive]), np.array([b["wall_s"] for b in remeshed])
    orders = dict(adaptive=cases.slope(1 / np.sqrt(na), ea), remeshed=cases.slope(1 / np.sqrt(nr), er))
    ratio = cases.equal_error_ratio(nr, er, na, ea)
    speedup = cases.equal_error_ratio(wr, er, wa, ea)          # remeshed wall time at equal error / adaptive
    for a, x, s in zip(adaptive, ratio, speedup):
        a["particle_ratio"], a["speedup"] = float(x), float(s)
    result["fig47"] = dict(Re=q["Re"], T=q["T"], reference_grid=ref.n, adaptive=adaptive, remeshed=remeshed,
                           orders=orders, particle_ratio=ratio.tolist(), speedup=speedup.tolist(),
                           paper={k: PAPER[k] for k in ("orders", "particle_ratio", "speedup")})
    print(f"  fitted orders: adaptive {orders['adaptive']:.2f}, remeshed {orders['remeshed']:.2f} (paper: 2, 2)")
    print("  remeshed particles / adaptive particles at equal error: " + ", ".join(f"{x:.1f}" for x in ratio)
          + " (paper: about 8)")
    print("  remeshed wall time / adaptive wall time at equal error: " + ", ".join(f"{x:.2f}" for x in speedup)
          + " (paper: about 2)")

    print("\nFig. 4.12 (§4.7): cost split of the adaptive runs (shares of the wall time of all steps)")
    print(f"{'D0':>6s} {'N':>7s} {'self-org':>9s} {'DC-PSE+rest':>12s} | of self-organization: {'DC-PSE':>7s} "
          f"{'lists':>6s} {'rest':>6s} | {'SO iter/adapt':>13s}")
    for a in adaptive:
        c = a["cost"]
        sp = c["self_organization_split"]
        it = np.mean(c["so_iterations"]) if c["so_iterations"] else 0
        print(f"{a['D0']:6.3f} {a['N']:7d} {100 * c['share_self_organization']:8.0f}% "
              f"{100 * c['share_dcpse_and_rest']:11.0f}% | {'':22s}{100 * sp['dcpse_monitor']:6.0f}% "
              f"{100 * sp['lists']:5.0f}% {100 * sp['rest']:5.0f}% | {it:13.1f}")
    print("  paper: 36 % self-organization, 64 % mostly DC-PSE construction; of self-organization "
          "57 % DC-PSE, 38 % neighbour lists, 5 % the rest")
    result["wall_s"] = time.perf_counter() - t_all

    # ---- plots
    plot_burgers(sim46, args.out / f"{tag}_fig46.png", f"Re = {p['fig46']['Re']:g}, T = {p['fig46']['T']}")

    fig, ax = plt.subplots(figsize=(6, 4.6))
    ax.loglog(1 / np.sqrt(nr), er, "s-", label=f"remeshed LPM (order {orders['remeshed']:.2f})")
    ax.loglog(1 / np.sqrt(na), ea, "o-", mfc="none", label=f"adaptive (order {orders['adaptive']:.2f})")
    slope_lines(ax, 1 / np.sqrt(na), ea, [2])
    ax.set_xlabel("h = 1 / sqrt(N)")
    ax.set_ylabel("L-infinity error at T")
    ax.set_title(f"Fig. 4.7: Burgers, Re = {q['Re']:g}, T = {q['T']}")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    save_figure(fig, args.out / f"{tag}_fig47.png")

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    labels = dict(t_monitor="monitor (DC-PSE gradient, Eq. 2.9)", t_organize_lists="self-org.: neighbour lists",
                  t_organize_rest="self-org.: rest", t_interpolate="DC-PSE old -> new", t_rhs="right-hand side")
    bottom = np.zeros(len(adaptive))
    per_step = [np.array([a["cost"]["seconds"][k] / a["steps"] for a in adaptive]) for k in PHASES]
    for k, v in zip(PHASES, per_step):
        axes[0].bar(range(len(adaptive)), v, bottom=bottom, label=labels[k])
        bottom += v
    axes[0].set_xticks(range(len(adaptive)), [f"N = {a['N']}" for a in adaptive])
    axes[0].set_ylabel("wall time per step [s]")
    axes[0].set_title("(a) cost per step by phase")
    axes[0].legend(fontsize=7)
    for a in adaptive:
        axes[1].plot(a["cost"]["t_reorganized"], a["cost"]["so_iterations"], "o-", ms=3, label=f"N = {a['N']}")
    axes[1].set_xlabel("t")
    axes[1].set_ylabel("gradient-descent iterations per adaptation")
    axes[1].set_title("(b) Fig. 4.12b")
    axes[1].legend(fontsize=8)
    save_figure(fig, args.out / f"{tag}_fig412.png")

    write_result(args.out, tag, result, f"PNGs ({result['wall_s']:.0f} s)")
    page = write_page(args.out, tag, report)
    print(f"wrote {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
