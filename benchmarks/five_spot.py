"""Benchmark: the five-spot problem of Reboux et al. (2012), §4.5 (Figs. 4.8 and 4.9).

The viscous Buckley-Leverett equation (Eqs. 4.12-4.13) in [-0.5, 0.5]^2 with
water injected at the centre and sucked out at the corners; f = 1 in a disk
of radius 0.02 at t = 0.  The paper states neither mu nor nu; arpy uses
mu = 0.5 and nu = 0.01 (see arpy.cases.five_spot).  Reports N over time (the
paper: 373 -> 7300), the saturation range (0 <= f <= 1 up to the front's
undershoot) and the particle sets at t = 0, 0.056, 0.09.

    python benchmarks/five_spot.py            # T = 0.09 (a few minutes)
    python benchmarks/five_spot.py --quick    # seconds (used by the tests)
"""

from __future__ import annotations

import sys
from pathlib import Path

from arpy import cases
from arpy._bench import benchmark_args, run_info, write_result

HERE = Path(__file__).resolve().parent


def main(argv: list[str] | None = None) -> int:
    args = benchmark_args(__doc__, argv, HERE / "results")
    from arpy.plotting import plot_five_spot

    tag = "five_spot_quick" if args.quick else "five_spot"
    T, shots = (0.002, (0.0, 0.001, 0.002)) if args.quick else (0.09, (0.0, 0.056, 0.09))
    r = cases.five_spot(T=T, snapshots=shots, progress=not args.quick)
    sim = r["sim"]
    h = sim.history()
    result = dict(**run_info(), mu=r["mu"], nu=r["nu"], D0=r["D0"], T=T, N_initial=r["N_initial"], N=r["N"],
                  N_max=int(r["n"].max()), f_min=r["f_min"], f_max=r["f_max"], steps=r["steps"], wall_s=r["wall_s"],
                  degenerate_max=int(h["degenerate"].max()),
                  snapshots={f"{t:g}": dict(N=len(s["f"]), f_min=float(s["f"].min()), f_max=float(s["f"].max()))
                             for t, s in r["snapshots"].items()},
                  t=r["t"][:: max(1, len(r["t"]) // 400)].tolist(), n=r["n"][:: max(1, len(r["n"]) // 400)].tolist(),
                  paper=dict(N_initial=373, N_final=7300))
    print(f"five-spot (§4.5): mu = {r['mu']}, nu = {r['nu']}, D0 = {r['D0']}, T = {T}")
    print(f"  N {r['N_initial']} -> {r['N']} (largest {result['N_max']}; the paper: 373 -> 7300), "
          f"{r['steps']} steps in {r['wall_s']:.0f} s")
    print(f"  saturation range at T: [{r['f_min']:.4f}, {r['f_max']:.4f}]")
    for t, s in result["snapshots"].items():
        print(f"  t = {t}: N = {s['N']}, f in [{s['f_min']:.3f}, {s['f_max']:.3f}]")
    plot_five_spot(r, args.out / f"{tag}.png")
    write_result(args.out, tag, result, f"{tag}.png", gap=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
