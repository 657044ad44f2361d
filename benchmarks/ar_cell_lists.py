"""Benchmark: adaptive-resolution (AR) vs uniform cell lists, Figs. 6 and 7 of Awile et al. (2012).

The particle distribution is the paper's (Sec. 3.1, arpy.ar_benchmark): 10 x 10
large particles (rc = 0.15) plus N small ones (rc = 0.15 / lambda) on Cartesian
meshes, every particle with 8 neighbours inside its block.  For each case it
times, in the same run:

  AR build         the AR tree alone (Algorithms 1-2)
  AR total         tree + symmetric Verlet list (Algorithm 3), as neighbor_list(method="ar")
  uniform build    the uniform cell grid alone
  uniform total    grid + symmetric list, as neighbor_list(method="cell")
  cKDTree          the better of query_ball_point (each particle's own radius) and
                   query_pairs (largest radius), both followed by the min-rule filter

and checks that every list holds the same pairs.  Where the uniform cell list
(or query_pairs) would take minutes, because its cells (or radius) are sized
by the largest cutoff and hold most of the small particles, the run is
skipped and its time is *estimated* from the number of distance checks it
would make (counted exactly from the cell occupancy) times the measured cost
per check; such entries are marked "~" and flagged in the JSON.

    python benchmarks/ar_cell_lists.py            # Fig. 6 (N = 1e3..1e6) and Fig. 7 (N = 1e6)
    python benchmarks/ar_cell_lists.py --quick    # small sizes, seconds
"""

from __future__ import annotations

import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

import arpy
from arpy._bench import MAX_KD_PAIRS_CANDIDATES, benchmark_args, break_even, compare_lists

HERE = Path(__file__).resolve().parent


def measure(n_small: int, lam: float, repeat: int, ns_per_check: list[float], memory: bool,
            kd_pairs_max: float = MAX_KD_PAIRS_CANDIDATES) -> dict:
    x, rc = arpy.ar_benchmark(n_small, lam)
    return {"lam": lam, "n_small": n_small, **compare_lists(x, rc, repeat, ns_per_check, memory, kd_pairs_max)}


def print_header() -> None:
    print(f"{'lambda':>8s} {'N':>8s} | {'AR build':>9s} {'AR total':>9s} | {'uni build':>9s} {'uni total':>10s} |"
          f" {'kd best':>9s} | {'uni/AR':>7s} {'kd/AR':>7s} {'ns/part':>8s} {'B/part':>7s}  pairs")


def print_row(r: dict) -> None:
    est = "~" if r["uniform_estimated"] else " "
    mem = r.get("ar_peak_bytes_per_particle")
    print(f"{r['lam']:8g} {r['n']:8d} | {1e3 * r['ar_build']:9.2f} {1e3 * r['ar_total']:9.2f} | "
          f"{1e3 * r['uniform_build']:9.2f} {est}{1e3 * r['uniform_total']:9.1f} | {1e3 * r['kd_best']:9.1f} | "
          f"{r['uniform_total'] / r['ar_total']:7.2f} {r['kd_best'] / r['ar_total']:7.1f} "
          f"{r['ar_ns_per_particle']:8.0f} {'' if mem is None else f'{mem:7.0f}':>7s}  {'ok' if r['same_pairs'] else 'DIFFERENT'}")


def plot(fig6: list[dict], fig7: list[dict], path6: Path, path7: Path) -> None:
    import matplotlib.pyplot as plt

    styles = [("ar_build", "AR build", "C0", "x--"), ("ar_total", "AR build + Verlet", "C0", "o-"),
              ("uniform_build", "uniform build", "C3", "x--"), ("uniform_total", "uniform build + Verlet", "C3", "o-"),
              ("kd_best", "cKDTree (best)", "C2", "s:")]
    lams = sorted({r["lam"] for r in fig6})
    fig, axes = plt.subplots(1, len(lams), figsize=(4.2 * len(lams), 4), sharey=True, squeeze=False)
    for ax, lam in zip(axes[0], lams):
        rows = sorted((r for r in fig6 if r["lam"] == lam), key=lambda r: r["n"])
        for key, label, color, fmt in styles:
            ax.loglog([r["n"] for r in rows], [r[key] for r in rows], fmt, color=color, label=label)
        est = [r for r in rows if r["uniform_estimated"]]
        if est:
            ax.loglog([r["n"] for r in est], [r["uniform_total"] for r in est], "o", mfc="none", ms=11,
                      color="C3", label="uniform: estimated")
        ax.set_title(f"lambda = {lam:g}")
        ax.set_xlabel("N particles")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("time [s]")
    axes[0][-1].legend(fontsize=7)
    fig.suptitle("AR vs uniform cell lists (cf. Awile et al. 2012, Fig. 6)")
    fig.tight_layout()
    fig.savefig(path6, dpi=110)
    plt.close(fig)

    rows = sorted(fig7, key=lambda r: r["lam"])
    lam = [r["lam"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    for key, label, color, fmt in styles:
        a.loglog(lam, [r[key] for r in rows], fmt, color=color, label=label)
    est = [r for r in rows if r["uniform_estimated"]]
    if est:
        a.loglog([r["lam"] for r in est], [r["uniform_total"] for r in est], "o", mfc="none", ms=11, color="C3",
                 label="uniform: estimated")
    a.set_xlabel("resolution span lambda")
    a.set_ylabel("time [s]")
    a.set_title(f"N = {rows[0]['n']} (cf. Fig. 7a)")
    a.grid(True, which="both", alpha=0.3)
    a.legend(fontsize=7)
    b.loglog(lam, [r["uniform_total"] / r["ar_total"] for r in rows], "o-", color="C3", label="uniform / AR")
    b.loglog(lam, [r["kd_best"] / r["ar_total"] for r in rows], "s:", color="C2", label="cKDTree / AR")
    b.axhline(1.0, color="k", lw=0.8)
    b.set_xlabel("resolution span lambda")
    b.set_ylabel("time ratio (build + Verlet)")
    b.set_title("speed-up of AR cell lists (cf. Fig. 7b)")
    b.grid(True, which="both", alpha=0.3)
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path7, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    def extra(parser):
        parser.add_argument("--repeat", type=int, default=3, help="timing repeats; the best is reported")
        parser.add_argument("--no-memory", action="store_true", help="skip the peak-memory subprocesses")

    args = benchmark_args(__doc__, argv, HERE / "results", extra)
    if args.quick:
        sizes, lams6, n7 = [1_000, 10_000], [1.0, 10.0, 1000.0], 10_000
        lams7 = [1.0, 3.65, 10.0, 100.0, 1000.0]
    else:
        sizes, lams6, n7 = [1_000, 10_000, 100_000, 1_000_000], [1.0, 10.0, 100.0, 1000.0], 1_000_000
        lams7 = [1.0, 2.0, 3.65, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0, 2000.0, 5000.0, 10000.0]
    repeat = 1 if args.quick else args.repeat
    # --quick checks the code paths: cKDTree.query_pairs only where it takes milliseconds
    kd_pairs_max = 5e6 if args.quick else MAX_KD_PAIRS_CANDIDATES
    ns_per_check: list[float] = []
    memory = not args.no_memory and not args.quick

    print("Fig. 6: runtime vs N")
    print_header()
    fig6 = []
    for lam in lams6:
        for n_small in sizes:
            fig6.append(measure(n_small, lam, repeat, ns_per_check, False, kd_pairs_max))
            print_row(fig6[-1])
    print(f"\nFig. 7: runtime vs lambda at N = {n7}")
    print_header()
    fig7 = []
    for lam in lams7:
        fig7.append(measure(n7, lam, repeat, ns_per_check, memory, kd_pairs_max))
        print_row(fig7[-1])

    stem = "ar_cell_lists" + ("_quick" if args.quick else "")
    be = break_even(fig7)
    by_lam = {r["lam"]: r for r in fig7}
    summary = {
        "break_even_lambda": be,
        "uniform_over_ar": {str(r["lam"]): r["uniform_total"] / r["ar_total"] for r in fig7},
        "kd_over_ar": {str(r["lam"]): r["kd_best"] / r["ar_total"] for r in fig7},
        "ns_per_check_uniform": float(np.median(ns_per_check)) if ns_per_check else None,
    }
    meta = {"python": sys.version.split()[0], "numpy": np.__version__, "machine": platform.machine(),
            "date": time.strftime("%Y-%m-%d"), "repeat": repeat}
    (args.out / f"{stem}.json").write_text(json.dumps({"meta": meta, "summary": summary, "fig6": fig6,
                                                        "fig7": fig7}, indent=1))
    plot(fig6, fig7, args.out / f"{stem}_fig6.png", args.out / f"{stem}_fig7.png")

    print(f"\nbreak-even lambda (uniform total = AR total): {be if be is None else round(be, 2)}  (paper: 3.65)")
    for lam, target, what in ((1.0, 1 / 1.25, "AR <= 1.25x uniform"), (10.0, 10.0, "AR >= 10x faster"),
                              (1000.0, 500.0, "AR >= 500x faster")):
        if lam in by_lam:
            r = by_lam[lam]
            ratio = r["uniform_total"] / r["ar_total"]
            est = " (uniform estimated)" if r["uniform_estimated"] else ""
            print(f"lambda = {lam:g}: uniform/AR = {ratio:.2f}{est}; target {what}: "
                  f"{'met' if ratio >= target else 'NOT met'}")
    worst_kd = min(r["kd_best"] / r["ar_total"] for r in fig7)
    print(f"cKDTree (best) / AR, worst over lambda: {worst_kd:.1f} (target >= 5): {'met' if worst_kd >= 5 else 'NOT met'}")
    print(f"wrote {args.out / (stem + '.json')}, {stem}_fig6.png, {stem}_fig7.png")
    return 0 if all(r["same_pairs"] for r in fig6 + fig7) else 1


if __name__ == "__main__":
    sys.exit(main())
