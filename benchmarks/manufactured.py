"""Benchmark: a PDE of your own on self-organizing particles, against its exact solution.

The reaction-diffusion system of :mod:`arpy.cases.reaction_diffusion` (two fields, a variable
diffusivity, a reaction, a compressible flow with -f div w, sources made so that the exact fields are
known), with each kind of wall: both fields held at their values (Dirichlet), both given their fluxes
(Neumann), or u held and v given its fluxes (mixed); and in the periodic box (its own exact solution).  RK4, re-organization every 5 steps.  Reports the
RMS and largest errors of u and v at T and their orders against h = 1 / sqrt(N) over the resolutions,
for several seeds.  Writes JSON, PNG and the Markdown page (results/manufactured.md, see report()) into
--out.

    python benchmarks/manufactured.py            # D0 = 0.1 ... 0.035, seeds 1-3 (a few minutes)
    python benchmarks/manufactured.py --quick    # seconds (used by the tests)
"""

from __future__ import annotations

import sys
from pathlib import Path

from arpy import cases
from arpy._bench import benchmark_args, md_table, run_info, span, write_page, write_result
from arpy.cases.reaction_diffusion import WALLS

HERE = Path(__file__).resolve().parent
FULL = dict(D0=(0.1, 0.07, 0.05, 0.035), seeds=(1, 2, 3), T=0.5, reorganize_every=5)
QUICK = dict(D0=(0.1, 0.07), seeds=(1,), T=0.1, reorganize_every=2)
NAMES = ("u", "v")


def report(res: dict) -> str:
    """The Markdown page of a result (results/manufactured.md is this of results/manufactured.json)."""
    stem = "manufactured_quick" if res.get("quick") else "manufactured"
    p = res["parameters"]
    lines = ["# A PDE of your own: a reaction-diffusion system against its exact solution", ""]
    if res.get("quick"):
        lines += ["**Quick run** (small sizes, for the tests).", ""]
    lines += ["`python benchmarks/manufactured.py` runs the benchmark and writes `manufactured.json`, this page "
              "and `manufactured.png` into `benchmarks/results/`; `--quick` runs two coarse resolutions in "
              "seconds (for the tests) and writes `manufactured_quick.*`. `arpy run manufactured` runs one "
              "seed of it.", "",
              "## Set-up", "",
              "The system of `arpy.cases.reaction_diffusion` in the unit square: two fields u, v carried by a "
              "compressible velocity w tangential to the walls (`conservative=True`: each rate gains −f ∇·w), "
              "u diffusing with k(x) = 0.01 (1 + 0.5 sin(x + y)) (`ops.diffusion(k, \"u\")`), v with 0.005, a "
              "reaction ∓uv, and sources computed from the exact fields. RK4 with dt = 0.2 D0, "
              f"T = {p['T']:g}, a re-organization every {p['reorganize_every']} steps (monitor Eq. 2.8 on both "
              "fields, Dmin = D0 / 2), m = 4. Walls: both fields held at their exact values (dirichlet), both "
              "given their exact fluxes (neumann), or u held and v given its fluxes (mixed); or the periodic unit "
              "square (periodic: the fields, k and w of the module docstring with wavenumbers 2π, a velocity "
              "with a mean drift). h = 1 / √N at T.",
              "", "## Results", ""]
    rows = []
    for walls in res["walls"]:
        for seed, runs in res["runs"][walls].items():
            for r in runs:
                rows.append([walls, seed, f"{r['D0']:g}", f"{r['N']}", f"{r['rms']['u']:.2e}", f"{r['max']['u']:.2e}",
                             f"{r['rms']['v']:.2e}", f"{r['max']['v']:.2e}", f"{r['degenerate']}",
                             f"{r['wall_s']:.1f}"])
    lines += md_table(["walls", "seed", "D0", "N", "u RMS", "u max", "v RMS", "v max", "failed stencils",
                       "wall (s)"], rows) + [""]
    lines += ["Orders (least-squares slope of log error against log h; 2 expected, the DC-PSE Laplacian's), "
              "the range over the seeds:", ""]
    orders = res["orders"]
    lines += md_table(["walls"] + [f"{kind} {name}" for kind in ("RMS", "max") for name in NAMES],
                      [[walls] + [span(orders[walls][f"{kind} {name}"], lambda v: f"{v:.2f}")
                                  for kind in ("rms", "max") for name in NAMES] for walls in res["walls"]]) + [""]
    every = [v for walls in res["walls"] for v in orders[walls]["rms u"] + orders[walls]["rms v"]]
    lines += [f"- The RMS errors fall at orders {span(every, lambda v: f'{v:.2f}')} over every kind of wall and "
              "seed (expected: 2, the order of the DC-PSE Laplacian; interpolation at each "
              "re-organization is O(h⁴), RK4 O(dt⁴)).",
              "- Dirichlet walls carry boundary particles with the wall's values and one-sided stencils; "
              "Neumann walls mirror images with values f_p + 2 s q, exact to O(s³) only (see "
              "`arpy.dcpse.boundary`).", "",
              f"![errors against h ({res['figure_walls']} walls, seed {res['figure_seed']}) and u at T on the "
              f"finest particles]({stem}.png)", "",
              f"Run on {res['machine']} with Python {res['python']}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = benchmark_args(__doc__, argv, HERE / "results")
    from arpy.cases.analysis import slope
    from arpy.plotting import plot_manufactured

    tag = "manufactured_quick" if args.quick else "manufactured"
    p = QUICK if args.quick else FULL
    walls_list = ("mixed",) if args.quick else WALLS
    runs: dict = {}
    orders: dict = {}
    figure_runs = None
    for walls in walls_list:
        runs[walls], orders[walls] = {}, {f"{kind} {name}": [] for kind in ("rms", "max") for name in NAMES}
        for seed in p["seeds"]:
            done = [cases.manufactured(D0, walls, p["T"], p["reorganize_every"], seed) for D0 in p["D0"]]
            for kind in ("rms", "max"):
                for name in NAMES:
                    orders[walls][f"{kind} {name}"].append(slope([r["h"] for r in done], [r[kind][name] for r in done]))
            runs[walls][str(seed)] = [{k: r[k] for k in ("D0", "N", "h", "steps", "rms", "max", "degenerate", "wall_s")}
                                      for r in done]
            rms_u = ", ".join(f"{r['rms']['u']:.2e}" for r in done)
            print(f"{walls:9s} seed {seed}: N {[r['N'] for r in done]}, RMS u {rms_u}; orders "
                  + ", ".join(f"{k} {v[-1]:.2f}" for k, v in orders[walls].items()))
            if figure_runs is None:
                figure_runs = done
    assert figure_runs is not None
    plot_manufactured(figure_runs, args.out / f"{tag}.png", figure_runs[-1])
    result = dict(**run_info(), quick=args.quick, parameters={k: list(v) if isinstance(v, tuple) else v
                                                              for k, v in p.items()},
                  walls=list(walls_list), runs=runs, orders=orders, figure_walls=walls_list[0],
                  figure_seed=p["seeds"][0])
    write_result(args.out, tag, result, f"{tag}.png", gap=False)
    page = write_page(args.out, tag, report)
    print(f"wrote {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
