"""Benchmark: particles in cache order (arpy.cache_order, Simulation(cache_order=True)).

  dcpse   DC-PSE assembly (gradient + Laplacian at the particles, lists given), N = 1e5 in 2D and
          3D: the particles in random order against the same particles in cache order, and the
          time cache_order itself takes
  steps   microseconds per particle-step, with the phase breakdown of the simulation log, of
          (a) the RK4 advection-diffusion run of benchmarks/threads.py (the blob of §4.2 in the
          reversing vortex, periodic, re-organization every 10 steps) and (b) the §4.3 pulse
          (forward Euler, walls), each at two resolutions, with and without cache order

The lists themselves, on random input and on input in cache order, are in
``ar_cell_lists.py --only lam1``.  Every figure is the best of several runs; the runs with and
without cache order alternate in one process.

    python benchmarks/cache_order.py            # full sizes (about ten minutes)
    python benchmarks/cache_order.py --quick    # small sizes, seconds (tests)

Results: ``results/cache_order.json`` and ``results/cache_order.md`` (generated from the JSON by
:func:`report`).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import arpy
from arpy import DCPSE
from arpy._bench import benchmark_args, best_time, md_table, run_info, write_page, write_result

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from threads import PHASES, advection_run, dcpse_set, pulse_run, step_cost  # noqa: E402  (a sibling script)

FULL = dict(dcpse_n=100_000, repeat=3,
            steps=[("advection", 0.12, 0.05), ("advection", 0.04, 0.05), ("pulse", 0.08, 0.07),
                   ("pulse", 0.03, 0.012)])
QUICK = dict(dcpse_n=2_000, repeat=1, steps=[("advection", 0.28, 0.0025)])


def dcpse_rows(n: int, repeat: int) -> list[dict]:
    """DC-PSE assembly on the same particles in random order and in cache order."""
    rows = []
    for d in (2, 3):
        x, eps = dcpse_set(d, n)
        t_order, perm = best_time(lambda: arpy.cache_order(x), repeat)
        xs = x[perm]
        lists = {name: DCPSE(p, eps, strict=False).neighbors for name, p in (("random", x), ("cache", xs))}
        best = {"random": np.inf, "cache": np.inf}
        for _ in range(repeat):                                # alternating
            for name, p in (("random", x), ("cache", xs)):
                t, _ = best_time(lambda: DCPSE(p, eps, neighbors=lists[name], strict=False), 1)
                best[name] = min(best[name], t)
        rows.append(dict(d=d, n=n, neighbours=len(lists["random"]) / n, random=best["random"], cache=best["cache"],
                         speedup=best["random"] / best["cache"], cache_order=t_order))
    return rows


def step_rows(steps: list, repeat: int) -> list[dict]:
    """Step cost of each case with and without cache order, the runs alternating."""
    runs = {"advection": advection_run, "pulse": pulse_run}
    rows = []
    for case, D0, T in steps:
        best: dict = {}
        for _ in range(repeat):
            for cache in (False, True):
                cost = step_cost(runs[case](D0, T, cache_order=cache))
                if cache not in best or cost["us"] < best[cache]["us"]:
                    best[cache] = cost
        rows.append(dict(case=case, D0=D0, T=T, plain=best[False], cache=best[True],
                         speedup=best[False]["us"] / best[True]["us"]))
    return rows


def report(res: dict) -> str:
    """The Markdown page of a result (``results/cache_order.md`` is this of ``results/cache_order.json``)."""
    lines = [f"# Particles in cache order ({res['machine']}, Python {res['python']}, {res['threads']} threads)", "",
             "## DC-PSE assembly (gradient + Laplacian at the particles, lists given)", ""]
    lines += md_table(["d", "N", "neighbours", "random order (s)", "cache order (s)", "speed-up", "cache_order (s)"],
                      [[r["d"], f"{r['n']:,}", f"{r['neighbours']:.1f}", f"{r['random']:.3f}", f"{r['cache']:.3f}",
                        f"{r['speedup']:.2f}", f"{r['cache_order']:.4f}"] for r in res["dcpse"]])
    lines += ["", "## Simulation steps", "",
              "Microseconds per particle-step over the run (re-organizations included), and per phase: the "
              "monitor, self-organization lists / rest, interpolation old -> new, right-hand sides, Python glue. "
              "(a) RK4 advection-diffusion, periodic; (b) the §4.3 pulse, forward Euler, walls.", ""]
    table = []
    for r in res["steps"]:
        for name in ("plain", "cache"):
            c = r[name]
            table.append([r["case"], r["D0"], f"{c['n_mean']:.0f}", c["steps"], "yes" if name == "cache" else "no",
                          f"{c['us']:.1f}", *(f"{c[k]:.1f}" for k in PHASES + ("glue",)),
                          f"{r['speedup']:.2f}" if name == "cache" else ""])
    lines += md_table(["case", "D0", "N", "steps", "cache order", "us / particle-step", "monitor", "SO lists",
                       "SO rest", "interp.", "rhs", "glue", "speed-up"], table)
    best = max(res["steps"], key=lambda r: r["speedup"])
    worst = min(res["steps"], key=lambda r: r["speedup"])
    speedups = ", ".join(f"{r['speedup']:.2f} in {r['d']}D" for r in res["dcpse"])
    costs = ", ".join(f"{100 * r['cache_order'] / r['random']:.1f} %" for r in res["dcpse"])
    lines += ["", "## Findings", "",
              f"- DC-PSE assembly, time in random order / in cache order: {speedups}; ordering the particles "
              f"costs {costs} of one assembly.",
              f"- Whole simulation steps, time without / with cache order: {worst['speedup']:.2f} ({worst['case']}, "
              f"N ~ {worst['cache']['n_mean']:.0f}) to {best['speedup']:.2f} ({best['case']}, "
              f"N ~ {best['cache']['n_mean']:.0f})."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = benchmark_args(__doc__, argv, HERE / "results")
    cfg = QUICK if args.quick else FULL
    res = dict(run_info(), quick=args.quick, threads=arpy.get_num_threads())
    res["dcpse"] = dcpse_rows(cfg["dcpse_n"], cfg["repeat"])
    for r in res["dcpse"]:
        print(f"DC-PSE {r['d']}D N = {r['n']}: random {r['random']:.3f} s, cache order {r['cache']:.3f} s "
              f"({r['speedup']:.2f}x); cache_order {r['cache_order']:.4f} s", flush=True)
    res["steps"] = step_rows(cfg["steps"], cfg["repeat"])
    for r in res["steps"]:
        print(f"{r['case']} D0 = {r['D0']}: N ~ {r['cache']['n_mean']:.0f}, {r['plain']['us']:.1f} -> "
              f"{r['cache']['us']:.1f} us / particle-step ({r['speedup']:.2f}x)", flush=True)
    tag = "cache_order_quick" if args.quick else "cache_order"
    write_result(args.out, tag, res, f"{args.out / tag}.md")
    print(write_page(args.out, tag, report).read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
