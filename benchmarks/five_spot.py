"""Benchmark: the five-spot problem of Reboux et al. (2012), §4.5 (Figs. 4.8 and 4.9).

The viscous Buckley-Leverett equation (Eqs. 4.12-4.13) in [-0.5, 0.5]^2 with
water injected at the centre and sucked out at the corners; f = 1 in a disk
of radius 0.02 at t = 0.  The paper states neither mu nor nu; arpy uses
mu = 0.5 and nu = 0.01 (see arpy.cases.five_spot).  Reports N over time (the
paper: 373 -> 7300), the saturation range (0 <= f <= 1 up to the front's
undershoot) and the particle sets at t = 0, 0.056, 0.09.  Writes JSON, PNG and the Markdown
page (results/five_spot.md, see report()) into --out.

    python benchmarks/five_spot.py            # T = 0.09 (a few minutes)
    python benchmarks/five_spot.py --quick    # seconds (used by the tests)
"""

from __future__ import annotations

import sys
from pathlib import Path

from arpy import cases
from arpy._bench import benchmark_args, md_table, run_info, write_page, write_result

HERE = Path(__file__).resolve().parent
#: Reboux et al. (2012), §4.5: N grows from 373 to 7300; the initial water disk's radius.
PAPER = dict(N_initial=373, N_final=7300, disk_radius=0.02)


# ------------------------------------------------------------------ report
def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    """A Markdown table and a blank line."""
    return md_table(header, rows) + [""]


def report(res: dict) -> str:
    """The Markdown page of a result (results/five_spot.md is this of results/five_spot.json)."""
    stem = "five_spot_quick" if res.get("quick") else "five_spot"
    dmin = f"Dmin = {res['Dmin']:g}" if res.get("Dmin") is not None else "Dmin (by default D0/10)"
    every = f"; re-organization every {res['reorganize_every']} steps" if res.get("reorganize_every") else ""
    shots = sorted(res["snapshots"].items(), key=lambda kv: float(kv[0]))
    lines = ["# Five-spot problem: Figs. 4.8 and 4.9 of Reboux et al. (2012)", ""]
    if res.get("quick"):
        lines += ["**Quick run** (small sizes, for the tests): the numbers are not comparable with the paper's.",
                  ""]
    lines += ["`python benchmarks/five_spot.py` runs the benchmark and writes `five_spot.json`, this page and "
              "`five_spot.png` into `benchmarks/results/`; `--quick` runs to a small T in seconds (for the tests) "
              "and writes `five_spot_quick.*`.", "",
              "## Set-up", "",
              "- The viscous Buckley–Leverett equation (Eqs. 4.12–4.13) in [−0.5, 0.5]², u = −∇p of an "
              "injection well at the centre and production wells at the four corners; f = 1 in a disk of radius "
              f"{PAPER['disk_radius']:g} (the paper's) at t = 0.",
              "- In Lagrangian form the particles move with g′(f)·u and f changes by diffusion only.",
              f"- D0 = {res['D0']:g}, T = {res['T']:g}; forward Euler with dt from the CFL and diffusion "
              f"limits{every}.",
              "", "Points the paper leaves open, decided here:", "",
              f"- μ = {res['mu']:g} and ν = {res['nu']:g}: the paper states neither. This ν keeps the front about "
              f"as wide as the finest resolution {dmin}.",
              "- The wells are regularized over the radius r_w of the initial water disk: |x − c|² becomes "
              "|x − c|² + r_w².",
              "- f = 1 is held at the particles inside the injection well after every step.",
              f"- Walls use mirror images; the edge of the initial disk is smoothed over {dmin}.",
              "- f is interpolated old → new with a local min/max limiter (`Simulation(bounded=True)`): each new "
              "value is clipped to the range of the old values in its stencil. Without it, the fourth-order "
              "interpolation of the steep front undershoots well below f = 0 within the first few "
              "re-organizations.", "",
              "## Results", ""]
    growth, paper_growth = res["N"] / res["N_initial"], PAPER["N_final"] / PAPER["N_initial"]
    lines += _table(["", "arpy", "paper"],
                    [["particles at t = 0", f"{res['N_initial']}", f"{PAPER['N_initial']}"],
                     [f"particles at T = {res['T']:g} (largest)", f"{res['N']} ({res['N_max']})",
                      f"{PAPER['N_final']}"],
                     ["growth N(T) / N(0)", f"{growth:.1f}", f"{paper_growth:.1f}"],
                     ["steps, wall time", f"{res['steps']}, {res['wall_s']:.0f} s", "–"]])
    lines += ["The snapshots of Fig. 4.9:", ""]
    lines += _table(["t", "N", "smallest f", "largest f"],
                    [[t, f"{s['N']}", f"{s['f_min']:.4f}", f"{s['f_max']:.4f}"] for t, s in shots])
    lines += [f"- N grows {growth:.1f}-fold, the paper's {paper_growth:.1f}-fold; at T arpy has "
              f"{res['N'] / PAPER['N_final']:.2f} times the paper's particles. μ and ν set the front's shape and "
              "width, and the paper states neither, so the two runs need not resolve the same front.",
              f"- f stays within [{res['f_min']:.4f}, {res['f_max']:.4f}] at T"
              + (": what is left of the undershoot comes from the diffusion steps between re-organizations (the "
                 "limiter keeps the interpolation within bounds)." if res["f_min"] < 0 else "."),
              "- Every particle had a DC-PSE stencil at every step." if res["degenerate_max"] == 0 else
              f"- Particles without a DC-PSE stencil: at most {res['degenerate_max']} in a step.", "",
              f"![Figs. 4.8 and 4.9: the velocity field, the particles coloured by f at t = "
              f"{', '.join(t for t, _ in shots)}, and N over time]({stem}.png)", "",
              f"Run on {res['machine']} with Python {res['python']}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = benchmark_args(__doc__, argv, HERE / "results")
    from arpy.plotting import plot_five_spot

    tag = "five_spot_quick" if args.quick else "five_spot"
    T, shots = (0.002, (0.0, 0.001, 0.002)) if args.quick else (0.09, (0.0, 0.056, 0.09))
    r = cases.five_spot(T=T, snapshots=shots, progress=not args.quick)
    sim = r["sim"]
    h = sim.history()
    result = dict(**run_info(), quick=args.quick, mu=r["mu"], nu=r["nu"], D0=r["D0"], T=T, N_initial=r["N_initial"],
                  N=r["N"], N_max=int(r["n"].max()), f_min=r["f_min"], f_max=r["f_max"], steps=r["steps"],
                  wall_s=r["wall_s"], degenerate_max=int(h["degenerate"].max()), Dmin=sim.Dmin,
                  reorganize_every=sim.reorganize_every,
                  snapshots={f"{t:g}": dict(N=len(s["f"]), f_min=float(s["f"].min()), f_max=float(s["f"].max()))
                             for t, s in r["snapshots"].items()},
                  t=r["t"][:: max(1, len(r["t"]) // 400)].tolist(), n=r["n"][:: max(1, len(r["n"]) // 400)].tolist(),
                  paper=dict(N_initial=PAPER["N_initial"], N_final=PAPER["N_final"]))
    print(f"five-spot (§4.5): mu = {r['mu']}, nu = {r['nu']}, D0 = {r['D0']}, T = {T}")
    print(f"  N {r['N_initial']} -> {r['N']} (largest {result['N_max']}; the paper: 373 -> 7300), "
          f"{r['steps']} steps in {r['wall_s']:.0f} s")
    print(f"  saturation range at T: [{r['f_min']:.4f}, {r['f_max']:.4f}]")
    for t, s in result["snapshots"].items():
        print(f"  t = {t}: N = {s['N']}, f in [{s['f_min']:.3f}, {s['f_max']:.3f}]")
    plot_five_spot(r, args.out / f"{tag}.png")
    write_result(args.out, tag, result, f"{tag}.png", gap=False)
    page = write_page(args.out, tag, report)
    print(f"wrote {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
