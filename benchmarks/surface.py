"""Benchmark: the budding-cell surface of both papers.

Part "bud" (Reboux et al. 2012, §4.6, Figs. 4.10 and 4.11): particles
self-organize (Morse potential V1, free space) in a narrow band around the
surface (:class:`arpy.surface.Bud`: sphere 0.3, bud 0.1, neck arc 0.1) with
the curvature monitor of Eq. 4.14, D0 = 0.1, for L = 0.40, 0.45, 0.50, 0.56;
the particle numbers are compared with the paper's, and the neighbour counts
checked against N* = 20.

Part "lists" (Awile et al. 2012, §3.2, Fig. 9): the same kind of surface
with bud radius 1, sphere radius 3 (touching), neck curvature r_P = 3 / lambda,
particles spaced in proportion to the local radius of curvature
(:func:`arpy.distributions.bud_benchmark`), mean resolution h0 = 0.45, 0.2,
0.1 on the large sphere.  Cell lists + symmetric Verlet lists are timed with
AR cell lists, the uniform cell list and cKDTree in the same run (as in
benchmarks/ar_cell_lists.py; uniform runs that would take minutes are
estimated from their counted distance checks, marked "~"); the break-even
lambda per h0 is reported.

    python benchmarks/surface.py                 # both parts, full size (about half an hour)
    python benchmarks/surface.py --only lists    # one part, merged into the JSON
    python benchmarks/surface.py --quick         # small sizes, for the tests
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from arpy._bench import benchmark_args, break_even, compare_lists, kdtree_ball_pairs
from arpy.cases import BUD_DMIN, BUD_PAPER_N, bud_surface
from arpy.distributions import bud_benchmark
from arpy.plotting import plot_bud_surface, save_figure

HERE = Path(__file__).resolve().parent
#: Awile et al. (2012), §3.2: break-even lambda per h0 (h0 = 0.45 is the coarsest).
PAPER_BREAK_EVEN = {0.45: "about 60", 0.2: "about 4", 0.1: "< 2"}
#: --quick (tests/test_cli_and_benchmarks.py): the bud at D0 = 0.35 (about 3300 particles;
#: tests/test_surface.py checks the self-organization itself), lists up to lambda = 30.
QUICK_D0 = 0.35


def neighbour_check(res: dict) -> dict:
    """Neighbour counts under the min rule (cKDTree, independent of arpy's lists): the
    fewest among the particles whose neighbourhood ball lies in the band, and the
    fraction of all particles with at least N*.  (Each particle queries its own
    radius: one query at the largest radius would pair every fine particle with
    every other within that radius, about 1e9 pairs at L = 0.56.)"""
    ps, interior = res["particles"], res["interior"]
    i, j = kdtree_ball_pairs(ps.x, ps.rc)
    counts = np.bincount(i, minlength=ps.n) + np.bincount(j, minlength=ps.n)
    return dict(n_star=ps.n_star, interior_fraction=float(interior.mean()),
                interior_min_neighbors=int(counts[interior].min()) if interior.any() else None,
                fraction_with_n_star=float((counts >= ps.n_star).mean()), min_neighbors=int(counts.min()))


def run_bud(Ls, D0: float, max_iter: int) -> tuple[list[dict], list[dict]]:
    rows, results = [], []
    print(f"{'L':>5s} {'neck':>8s} {'N init':>8s} {'N':>8s} {'paper':>8s} {'it':>4s} {'conv':>5s} "
          f"{'D min':>9s} {'D max':>8s} {'interior min nb':>15s} {'>= N*':>6s} {'wall s':>7s}")
    for L in Ls:
        Dmin = BUD_DMIN.get(round(L, 2))
        res = bud_surface(L, D0=D0, Dmin=Dmin, max_iter=max_iter)
        nb = neighbour_check(res)
        row = {k: res[k] for k in ("L", "D0", "N_initial", "N", "D_min", "D_max", "iterations", "converged",
                                   "neck_radius", "wall_s")}
        row.update(nb, paper_N=BUD_PAPER_N.get(round(L, 2)), Dmin=Dmin)
        if Dmin is not None:
            bud = res["bud"]
            row["N_initial_without_Dmin"] = int(len(bud.sample_band(bud.monitor_spacing(D0), half_width=4.0, seed=0)))
            print(f"    (L = {L:g}: D~ bounded below by Dmin = {Dmin:g}; without it the band would start with "
                  f"{row['N_initial_without_Dmin']} particles)")
        rows.append(row)
        results.append(res)
        print(f"{L:5.2f} {res['neck_radius']:8.2g} {res['N_initial']:8d} {res['N']:8d} "
              f"{row['paper_N'] or float('nan'):8.3g} {res['iterations']:4d} {str(res['converged']):>5s} "
              f"{res['D_min']:9.3g} {res['D_max']:8.3g} {nb['interior_min_neighbors']:15d} "
              f"{nb['fraction_with_n_star']:6.1%} {res['wall_s']:7.1f}", flush=True)
    return rows, results


def run_lists(h0s, lams, repeat: int, max_n: float, memory: bool) -> list[dict]:
    rows, ns_per_check = [], []
    print(f"{'h0':>5s} {'lambda':>7s} {'N':>8s} | {'AR total':>9s} {'uni total':>10s} {'kd best':>9s} | "
          f"{'uni/AR':>7s} {'kd/AR':>6s} {'AR ns/p':>8s} {'uni ns/p':>9s}  pairs")
    for h0 in h0s:
        for lam in lams:
            x, rc, _ = bud_benchmark(h0, lam, seed=0)
            if len(x) > max_n:
                print(f"{h0:5.2f} {lam:7g} {len(x):8d} | skipped (N > --max-n = {max_n:g})")
                continue
            row = {"h0": h0, "lam_target": lam, "lam": float(rc.max() / rc.min()),
                   **compare_lists(x, rc, repeat, ns_per_check, memory)}
            row["uniform_ns_per_particle"] = 1e9 * row["uniform_total"] / row["n"]
            rows.append(row)
            est = "~" if row["uniform_estimated"] else " "
            print(f"{h0:5.2f} {row['lam']:7.1f} {row['n']:8d} | {1e3 * row['ar_total']:9.1f} "
                  f"{est}{1e3 * row['uniform_total']:9.1f} {1e3 * row['kd_best']:9.1f} | "
                  f"{row['uniform_total'] / row['ar_total']:7.2f} {row['kd_best'] / row['ar_total']:6.1f} "
                  f"{row['ar_ns_per_particle']:8.0f} {row['uniform_ns_per_particle']:9.0f}  "
                  f"{'ok' if row['same_pairs'] else 'DIFFERENT'}", flush=True)
    return rows


def plot_fig9(rows: list[dict], path: Path) -> None:
    import matplotlib.pyplot as plt

    marks = {0.1: "x", 0.2: "o", 0.45: "^"}
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.4))
    for h0 in sorted({r["h0"] for r in rows}):
        rs = sorted((r for r in rows if r["h0"] == h0), key=lambda r: r["lam"])
        lam = [r["lam"] for r in rs]
        m = marks.get(h0, "s")
        for ax, scale in ((a, lambda r: 1.0), (b, lambda r: 1.0 / r["n"])):
            ax.loglog(lam, [r["ar_total"] * scale(r) for r in rs], "-" + m, color="C0",
                      label=f"AR, h0 = {h0:g}")
            ax.loglog(lam, [r["uniform_total"] * scale(r) for r in rs], "--" + m, color="C3",
                      label=f"uniform, h0 = {h0:g}")
            ax.loglog(lam, [r["kd_best"] * scale(r) for r in rs], ":" + m, color="C2", alpha=0.6,
                      label=f"cKDTree, h0 = {h0:g}")
            est = [r for r in rs if r["uniform_estimated"]]
            if est:
                ax.loglog([r["lam"] for r in est], [r["uniform_total"] * scale(r) for r in est], "o", mfc="none",
                          ms=11, color="C3")
    a.set_ylabel("time [s]: cell lists + Verlet lists")
    b.set_ylabel("time per particle [s]")
    a.set_title("(a) total (cf. Awile et al. Fig. 9a)")
    b.set_title("(b) per particle (cf. Fig. 9b); open circles: estimated")
    for ax in (a, b):
        ax.set_xlabel("resolution span lambda")
        ax.grid(True, which="both", alpha=0.3)
    a.legend(fontsize=7, ncol=2)
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    def extra(p):
        p.add_argument("--only", choices=("bud", "lists"), help="run one part; merge it into the JSON")
        p.add_argument("--repeat", type=int, default=3, help="timing repeats; the best is reported")
        p.add_argument("--max-n", type=float, default=1.6e6,
                       help="skip list configurations with more particles (default 1.6e6: beyond it the "
                            "cKDTree ball queries of the coarse particles outgrow 24 GB of memory)")
        p.add_argument("--no-memory", action="store_true", help="skip the peak-memory subprocesses")

    args = benchmark_args(__doc__, argv, HERE / "results", extra)
    stem = "surface" + ("_quick" if args.quick else "")
    path = args.out / f"{stem}.json"
    data = json.loads(path.read_text()) if args.only and path.exists() else {}
    data["meta"] = {"date": time.strftime("%Y-%m-%d"), "python": sys.version.split()[0], "quick": args.quick}
    ok = True
    if args.only in (None, "bud"):
        print("Part bud: §4.6, self-organized particles in the narrow band (V1, D0 = "
              f"{QUICK_D0 if args.quick else 0.1})")
        Ls = [0.40] if args.quick else [0.40, 0.45, 0.50, 0.56]
        rows, results = run_bud(Ls, D0=QUICK_D0 if args.quick else 0.1, max_iter=40 if args.quick else 150)
        data["bud"] = rows
        path.write_text(json.dumps(data, indent=1, default=float))      # (the lists part takes long)
        plot_bud_surface(results, args.out / f"{stem}_fig410.png", BUD_PAPER_N)
        ok &= all(r["interior_min_neighbors"] is None or r["interior_min_neighbors"] >= r["n_star"] for r in rows)
    if args.only in (None, "lists"):
        h0s = [0.45] if args.quick else [0.45, 0.2, 0.1]
        lams = [3.0, 30.0] if args.quick else [3.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0, 2000.0]
        print("\nPart lists: Awile et al. §3.2, Fig. 9 (3D, build + symmetric Verlet list)")
        rows = run_lists(h0s, lams, 1 if args.quick else args.repeat, args.max_n,
                         memory=not (args.quick or args.no_memory))
        be = {str(h0): break_even([r for r in rows if r["h0"] == h0]) for h0 in h0s}
        data["lists"] = rows
        data["break_even_lambda"] = be
        plot_fig9(rows, args.out / f"{stem}_fig9.png")
        for h0 in h0s:
            v = be[str(h0)]
            first = min((r for r in rows if r["h0"] == h0), key=lambda r: r["lam"])
            text = ("none in range" if v is None else
                    f"below {v:.3g} (AR is already faster at the smallest lambda)" if v == first["lam"] else f"{v:.3g}")
            print(f"break-even lambda, h0 = {h0:g}: {text} (paper: {PAPER_BREAK_EVEN.get(h0, '-')})")
        ok &= all(r["same_pairs"] for r in rows)
    path.write_text(json.dumps(data, indent=1, default=float))
    print(f"wrote {path}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
