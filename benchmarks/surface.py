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

Writes JSON, PNG and the Markdown page (results/surface.md, see report()) into --out.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from arpy._bench import (benchmark_args, break_even, compare_lists, kdtree_ball_pairs, md_table, run_info, span,
                         write_page)
from arpy.cases import BUD_DMIN, BUD_PAPER_N, bud_surface
from arpy.distributions import bud_benchmark
from arpy.plotting import plot_bud_surface, save_figure

HERE = Path(__file__).resolve().parent
#: Awile et al. (2012), §3.2: break-even lambda per h0 (h0 = 0.45 is the coarsest).
PAPER_BREAK_EVEN = {0.45: "about 60", 0.2: "about 4", 0.1: "< 2"}
#: Reboux et al. (2012), §4.6: the radii of the sphere, the bud and the neck's arc; the band's width in D~.
PAPER_BUD = dict(R=0.3, r=0.1, neck_arc=0.1, band=4)
#: Awile et al. (2012), §3.2: the radii of the bud and the sphere.
PAPER_LISTS = dict(r=1, R=3)
#: --quick (tests/test_cli_and_benchmarks.py): the bud at D0 = 0.5 (about 1900 particles;
#: tests/test_surface.py checks the self-organization itself), lists up to lambda = 30.
QUICK_D0 = 0.5


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


# ------------------------------------------------------------------ report
def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    """A Markdown table and a blank line."""
    return md_table(header, rows) + [""]


def _span(values, fmt: str = "{:.2f}") -> str:
    """'lo–hi' of the values in ``fmt`` (one value if they agree at that precision)."""
    return span(values, fmt.format)


def _num(v: float) -> str:
    """Three significant digits, or the integer part from 1000 on."""
    return f"{v:.3g}" if v < 1000 else f"{v:.0f}"


def _seconds(t: float) -> str:
    """A wall time in ms below one second, in s above."""
    return f"{_num(1e3 * t)} ms" if t < 1 else f"{_num(t)} s"


def _bud_section(rows: list[dict], stem: str) -> list[str]:
    R, r, arc = PAPER_BUD["R"], PAPER_BUD["r"], PAPER_BUD["neck_arc"]
    pinch = np.sqrt((R + arc) ** 2 - arc ** 2) + np.sqrt((r + arc) ** 2 - arc ** 2)   # the neck's radius is 0 there
    first = rows[0]
    lines = ["## Figs. 4.10 and 4.11 of Reboux et al.: particles around a budding cell (§4.6)", "",
             f"`arpy.surface.Bud`: a sphere (radius {R:g}), a bud (radius {r:g}) and a concave neck arc (radius "
             f"{arc:g}) tangent to both, rotated about the z axis (the paper's radii), with the exact signed distance "
             "φ, both principal curvatures and the distance to the opposing surface, hence the monitor of Eq. 4.14 "
             f"(D0 = {first['D0']:g}). `cases.bud_surface(L)` fills the narrow band |φ| ≤ "
             f"{PAPER_BUD['band']:g} D̃ with random particles and self-organizes them with V1 in free space, confined "
             f"to the band (N* = {first['n_star']}). Particles within r_c + D_p/2 of the band's edge need not reach "
             "N* (the outermost layer is sparser in free space).", "",
             "Points the paper leaves open, decided here:", "",
             f"- The paper sets the band's width to {PAPER_BUD['band']:g} D̃; arpy reads this as a half-width. "
             f"A total width of "
             f"{PAPER_BUD['band']:g} D̃ gives about half the paper's counts, and too few particles deep enough in the "
             "band to have a full neighbourhood.",
             f"- With these radii the neck pinches off at L = {pinch:.4f}."]
    for row in rows:
        if row.get("Dmin") is not None:
            extra = (f": Eq. 4.14 alone would start with {row['N_initial_without_Dmin']} particles"
                     if row.get("N_initial_without_Dmin") else "")
            lines[-1] += (f" At L = {row['L']:g} the neck's radius is {row['neck_radius']:.1g}{extra}. The paper "
                          f"reports {row['paper_N']:.0f} particles there and names no floor; arpy bounds D̃ below "
                          f"by {row['Dmin']:g} at that L (`cases.BUD_DMIN`).")
    lines += [""]
    table = []
    for row in rows:
        paper = row.get("paper_N")
        table.append([f"{row['L']:.2f}" + (f" (D̃ ≥ {row['Dmin']:g})" if row.get("Dmin") is not None else ""),
                      f"{row['neck_radius']:.2g}", f"{row['D_min']:.2g} – {row['D_max']:.3g}",
                      f"{row['N_initial']}", f"{row['N']}", f"{paper:.0f}" if paper else "–",
                      f"{row['N'] / paper:.2f}" if paper else "–",
                      f"{row['iterations']}" + ("" if row["converged"] else " (not converged)"),
                      f"{row['interior_min_neighbors']}" if row["interior_min_neighbors"] is not None else "–",
                      f"{100 * row['fraction_with_n_star']:.0f} %", f"{100 * row['interior_fraction']:.0f} %",
                      f"{row['wall_s']:.0f}"])
    lines += _table(["L", "neck radius", "D_p", "N at start", "N", "paper N", "N / paper N", "iterations",
                     "fewest neighbours, away from the edges", f"particles with ≥ {first['n_star']} neighbours",
                     "particles away from the edges", "wall (s)"], table)
    conv = all(row["converged"] for row in rows)
    full = all(row["interior_min_neighbors"] is not None and row["interior_min_neighbors"] >= row["n_star"]
               for row in rows)
    lines += ["- " + ("Every run converges" if conv else "Not every run converges") + " by the stopping rule of "
              "§3.1, and " + ("every" if full else "not every") + " particle away from the band's edges has at "
              "least N* neighbours. The neighbours are counted with cKDTree, independently of arpy's lists; \"away "
              "from the edges\": the particle's ball of radius r_c + D_p/2 lies in the band."]
    with_paper = [row for row in rows if row.get("paper_N")]
    if with_paper:
        pct = [100 * (row["N"] / row["paper_N"] - 1) for row in with_paper]
        a, b = with_paper[0], with_paper[-1]
        faster = "faster" if b["N"] / a["N"] > b["paper_N"] / a["paper_N"] else "no faster"
        off = (f"{_span(pct, '{:.0f}')} % above" if min(pct) >= 0 else
               f"{_span([-x for x in pct], '{:.0f}')} % below" if max(pct) <= 0 else
               f"between {min(pct):.0f} % and +{max(pct):.0f} % off")
        lines += [f"- N is {off} the paper's"
                  + (f" and grows {faster} with L: {b['N'] / a['N']:.2f}-fold from L = {a['L']:g} to {b['L']:g}, "
                     f"the paper's {b['paper_N'] / a['paper_N']:.2f}-fold." if b is not a else ".")]
    lines += [f"- D_p is {first['D_max']:.3g} on the large sphere (D0/√(1 + 1/R²)) and comes down at the neck to "
              + ", ".join(f"{row['D_min']:.2g}" for row in rows) + " (L = "
              + ", ".join(f"{row['L']:g}" for row in rows) + ").", "",
              "![Fig. 4.10: the surfaces coloured by D_p; Fig. 4.11: the particles in a slab through the neck]"
              f"({stem}_fig410.png)", "",
              "`arpy run bud-surface --L 0.4 0.45` draws the same and writes npz and VTK files.", ""]
    return lines


def _lists_section(res: dict, stem: str) -> list[str]:
    rows = sorted(res["lists"], key=lambda row: (-row["h0"], row["lam"]))
    h0s = sorted({row["h0"] for row in rows}, reverse=True)
    repeat = ("best of repeated runs" if not res.get("repeat") else "one run each" if res["repeat"] == 1 else
              f"best of {res['repeat']}")
    lines = ["## Fig. 9 of Awile et al.: neighbour lists on the bud (§3.2)", "",
             f"The same kind of surface with bud radius {PAPER_LISTS['r']:g}, sphere radius {PAPER_LISTS['R']:g} and "
             "neck arc r_P = 3/λ; particles spaced in proportion to the local radius of curvature in a band around "
             "it (`arpy.bud_benchmark(h0, lam)`), h0 the mean spacing on the large sphere. Cell lists + symmetric "
             f"Verlet lists, AR cell lists against the uniform cell list and cKDTree ball queries, timed in the same "
             f"run ({repeat}). \"~\": the uniform list's time estimated from its counted distance checks "
             "(measured runs would take minutes). "
             + ("All three find the same pairs in every configuration." if all(row["same_pairs"] for row in rows)
                else "**Not all three find the same pairs.**"), ""]
    table = []
    for row in rows:
        mem = row.get("ar_peak_bytes_per_particle")
        table.append([f"{row['h0']:g}", f"{row['lam']:.2g}" if row["lam"] < 10 else f"{row['lam']:.0f}",
                      f"{row['n']}", _seconds(row["ar_total"]),
                      ("~" if row["uniform_estimated"] else "") + _seconds(row["uniform_total"]),
                      _seconds(row["kd_best"]),
                      ("~" if row["uniform_estimated"] else "") + _num(row["uniform_total"] / row["ar_total"]),
                      _num(row["kd_best"] / row["ar_total"]), f"{row['ar_ns_per_particle'] / 1e3:.2f}",
                      f"{mem:.0f}" if mem is not None else "–"])
    lines += _table(["h0", "λ", "N", "AR", "uniform", "cKDTree", "uniform / AR", "cKDTree / AR",
                     "AR µs per particle", "AR peak bytes per particle"], table)
    be = res.get("break_even_lambda", {})
    table = []
    for h0 in h0s:
        v = be.get(str(h0), be.get(f"{h0:g}"))
        smallest = min(row["lam"] for row in rows if row["h0"] == h0)
        text = ("none in the range" if v is None else
                f"below {v:.2g} (AR is faster at the smallest λ measured)" if v == smallest else f"{v:.3g}")
        table.append([f"{h0:g}", text, PAPER_BREAK_EVEN.get(h0, "–")])
    lines += ["Break-even λ, where AR lists become faster than uniform ones:", ""]
    lines += _table(["h0", "arpy", "paper"], table)
    uni = [row["uniform_ns_per_particle"] / 1e3 for row in rows]
    kd = [row["kd_best"] / row["ar_total"] for row in rows]
    by_h0 = {h0: sorted((row for row in rows if row["h0"] == h0), key=lambda row: row["lam"]) for h0 in h0s}
    with_lam = all(rs[-1]["uniform_ns_per_particle"] > rs[0]["uniform_ns_per_particle"] for rs in by_h0.values())
    common = max(set.intersection(*({row["lam_target"] for row in rs} for rs in by_h0.values())))
    at = [next(row["uniform_ns_per_particle"] for row in rs if row["lam_target"] == common) for rs in by_h0.values()]
    with_n = len(at) > 1 and all(a < b for a, b in zip(at, at[1:]))              # h0 decreasing: N increasing
    grows = " and with N" if with_n else ""
    lines += [f"- AR lists cost {_span([row['ar_ns_per_particle'] / 1e3 for row in rows])} µs per particle over the "
              f"whole range of λ and N; the uniform list's cost "
              + (f"grows with λ{grows}, as in the paper (its Fig. 9b)" if with_lam else "does not grow with λ")
              + f": from {min(uni):.2g} to {_num(max(uni))} µs per particle.",
              f"- cKDTree takes {_span(kd, '{:.0f}')} times as long as the AR lists."]
    mem = [row["ar_peak_bytes_per_particle"] for row in rows
           if row.get("ar_peak_bytes_per_particle") is not None and row["n"] >= 1e5]
    if mem:
        lines += [f"- Peak memory of the AR list: {_span(mem, '{:.0f}')} bytes per particle at N ≥ 10⁵."]
    lams = sorted({row["lam_target"] for row in rows})
    for h0 in h0s:
        done = [row for row in rows if row["h0"] == h0]
        last = max(done, key=lambda row: row["lam_target"])
        if last["lam_target"] < lams[-1]:
            limit = f" (N > {res['max_n']:.2g})" if res.get("max_n") else ""
            lines += [f"- h0 = {h0:g} stops at λ = {last['lam']:.0f} (N = {last['n']}): the larger configurations "
                      f"are skipped{limit}, as cKDTree's ball queries of the coarse particles would outgrow the "
                      "memory."]
    lines += ["", f"![Fig. 9: (a) the time of cell lists + Verlet lists against λ, (b) per particle]({stem}_fig9.png)",
              ""]
    return lines


def report(res: dict) -> str:
    """The Markdown page of a result (results/surface.md is this of results/surface.json)."""
    meta = res.get("meta", {})
    stem = "surface_quick" if meta.get("quick") else "surface"
    lines = ["# Bud surface: Figs. 4.10 and 4.11 of Reboux et al. (2012), Fig. 9 of Awile et al. (2012)", ""]
    if meta.get("quick"):
        lines += ["**Quick run** (small sizes, for the tests): the numbers are not comparable with the papers'.", ""]
    lines += ["`python benchmarks/surface.py` runs both parts and writes `surface.json`, this page and the figures "
              "into `benchmarks/results/`; `--only bud` or `--only lists` runs one part and merges it into the JSON; "
              "`--quick` runs small sizes (for the tests) and writes `surface_quick.*`.", ""]
    if res.get("bud"):
        lines += _bud_section(res["bud"], stem)
    if res.get("lists"):
        lines += _lists_section(res, stem)
    machine = res.get("machine", meta.get("machine"))
    lines += [f"Run {'on ' + machine + ' ' if machine else ''}with Python {meta.get('python', res.get('python'))}."]
    return "\n".join(lines) + "\n"


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
    data["meta"] = {"date": time.strftime("%Y-%m-%d"), **run_info(), "quick": args.quick}
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
        data["repeat"], data["max_n"] = 1 if args.quick else args.repeat, args.max_n
        plot_fig9(rows, args.out / f"{stem}_fig9.png")
        for h0 in h0s:
            v = be[str(h0)]
            first = min((r for r in rows if r["h0"] == h0), key=lambda r: r["lam"])
            text = ("none in range" if v is None else
                    f"below {v:.3g} (AR is already faster at the smallest lambda)" if v == first["lam"] else f"{v:.3g}")
            print(f"break-even lambda, h0 = {h0:g}: {text} (paper: {PAPER_BREAK_EVEN.get(h0, '-')})")
        ok &= all(r["same_pairs"] for r in rows)
    path.write_text(json.dumps(data, indent=1, default=float))
    page = write_page(args.out, stem, report)
    print(f"wrote {path} and {page}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
