"""Benchmark: arpy on every core -- the core's parallel kernels at 1 and 2 threads, periodic lists,
and the cost of a simulation step, side by side with scipy's cKDTree and with an older build.

  dcpse     DC-PSE assembly (gradient and Laplacian at the particles, neighbour lists given),
            N = 1e5 in 2D and 3D (random order), at 1 and 2 threads
  lists     uniform and AR cell lists (build + symmetric list) of the AR paper's distribution
            (arpy.ar_benchmark, lambda = 1 and 10), N = 1e6, at 1 and 2 threads, and scipy's
            cKDTree.query_ball_point at each particle's own radius with workers = 1 and 2
  periodic  lists in a periodic box against free space (uniform random, N = 1e6, ~10 neighbours),
            and cKDTree with boxsize (query_pairs)
  steps     microseconds per particle-step of (a) an RK4 advection-diffusion run in a periodic box
            (the blob of §4.2 in the reversing vortex, nu = 1e-3, D0 = 0.12, dt = 0.0025,
            re-organization every 10 steps, N ~ 3600) and (b) the §4.3 pulse main job (2D,
            Pe = 1000, D0 = 0.08, forward Euler, walls); (a) also with Verlet lists reused across
            stages and steps (Simulation(verlet_skin=SKIN)); with the phase breakdown of the
            simulation log (monitor, self-organization lists and the rest of it, interpolation
            old -> new, right-hand sides, and the Python in between)

Every figure is the best of several runs; the 1- and 2-thread runs alternate in one process.

    python benchmarks/threads.py                          # full sizes (a few minutes)
    python benchmarks/threads.py --quick                  # small sizes, a few seconds (tests)
    python benchmarks/threads.py --only periodic          # one section again, merged into the JSON
    python benchmarks/threads.py --only steps --baseline OLD_PYTHON   # the steps again, old and new
    python benchmarks/threads.py --baseline OLD_PYTHON    # the steps also with an older build

``--baseline`` takes the interpreter of another arpy build (e.g. ``../shared/tools/install-rev``'s):
the steps run there as well, at one thread, and the table gives the ratio of each new figure to the
old one-thread figure.  Results: ``results/threads.json`` and ``results/threads.md`` (generated from
the JSON by :func:`report`).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import arpy
from arpy import DCPSE, Domain, Simulation, neighbor_list, self_organize

HERE = Path(__file__).resolve().parent
PHASES = ("t_monitor", "t_organize_lists", "t_organize_rest", "t_interpolate", "t_rhs")
FULL = dict(dcpse_n=100_000, lists_n=1_000_000, lams=(1.0, 10.0), periodic_n=1_000_000, repeat=10,
            advection=dict(D0=0.12, T=0.05), pulse=dict(D0=0.08, T=0.07), step_repeat=5)
QUICK = dict(dcpse_n=4_000, lists_n=20_000, lams=(1.0, 10.0), periodic_n=20_000, repeat=1,
             advection=dict(D0=0.28, T=0.005), pulse=dict(D0=0.3, T=0.002), step_repeat=1)


def threads_available() -> bool:
    """Whether this arpy build has thread control (older builds run serially)."""
    return hasattr(arpy, "set_num_threads")


def at_threads(n: int) -> None:
    if threads_available():
        arpy.set_num_threads(n)


def best_of(fn, repeat: int) -> float:
    """Shortest wall time of ``repeat`` calls (s)."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def alternate(fns: dict, repeat: int) -> dict:
    """Best time of each named (threads, fn) pair, the pairs run in turn ``repeat`` times."""
    best = dict.fromkeys(fns, np.inf)
    for _ in range(repeat):
        for name, (threads, fn) in fns.items():
            at_threads(threads)
            best[name] = min(best[name], best_of(fn, 1))
    at_threads(0)
    return best


# ------------------------------------------------------------------ kernels
def dcpse_set(d: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The DC-PSE assembly's particles: n uniform random points in the unit square (2D) or cube
    (3D), in random order, with core sizes of 3.2 (2D) or 2.4 (3D) mean spacings."""
    x = np.random.default_rng(d).random((n, d))
    return x, np.full(n, {2: 3.2, 3: 2.4}[d] / n ** (1 / d))


def dcpse_rows(n: int, repeat: int) -> list[dict]:
    rows = []
    for d in (2, 3):
        x, eps = dcpse_set(d, n)
        nl = DCPSE(x, eps, strict=False).neighbors
        t = alternate({t: (t, lambda: DCPSE(x, eps, neighbors=nl, strict=False)) for t in (1, 2)}, repeat)
        rows.append(dict(d=d, n=n, neighbours=len(nl) / n, t1=t[1], t2=t[2], speedup=t[1] / t[2]))
    return rows


def list_rows(n: int, lams, repeat: int) -> list[dict]:
    from scipy.spatial import cKDTree

    rows = []
    for lam in lams:
        x, rc = arpy.ar_benchmark(n, lam)
        fns = {(m, t): (t, lambda m=m: neighbor_list(x, rc, method=m)) for m in ("cell", "ar") for t in (1, 2)}
        t = alternate(fns, repeat)
        tree = cKDTree(x)
        kd = {w: best_of(lambda w=w: tree.query_ball_point(x, rc, workers=w, return_sorted=False), max(1, repeat // 2))
              for w in (1, 2)}
        row = dict(lam=lam, n=len(x), kd1=kd[1], kd2=kd[2])
        for m in ("cell", "ar"):
            row.update({f"{m}1": t[m, 1], f"{m}2": t[m, 2], f"{m}_speedup": t[m, 1] / t[m, 2],
                        f"kd2_over_{m}2": kd[2] / t[m, 2]})
        rows.append(row)
    return rows


def periodic_rows(n: int, repeat: int) -> list[dict]:
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    x = rng.random((n, 2))
    rc = np.full(n, np.sqrt(10.0 / (np.pi * n)))
    torus = Domain([1.0, 1.0], periodic=True)
    rows = []
    for m in ("cell", "ar"):
        fns = {(dom, t): (t, lambda dom=dom: neighbor_list(x, rc, method=m, domain=torus if dom else None))
               for dom in (False, True) for t in (1, 2)}
        t = alternate(fns, repeat)
        kd = best_of(lambda: cKDTree(x, boxsize=1.0).query_pairs(rc[0], output_type="ndarray"), max(1, repeat // 2))
        rows.append(dict(method=m, n=n, free1=t[False, 1], periodic1=t[True, 1], free2=t[False, 2],
                         periodic2=t[True, 2], ratio1=t[True, 1] / t[False, 1], ratio2=t[True, 2] / t[False, 2],
                         kd_boxsize=kd, kd_over_periodic2=kd / t[True, 2]))
    return rows


# ------------------------------------------------------------------ simulation steps
def advection_run(D0: float, T: float, skin: float = 0.0, **options) -> Simulation:
    """(a): the blob in the reversing vortex with diffusion, RK4, doubly periodic; ``skin``: Verlet
    lists reused across stages (``Simulation(verlet_skin=skin)``); ``options``: more Simulation
    arguments."""
    from arpy.cases.reversing_vortex import blob, blob_monitor, vortex

    torus = Domain([1.0, 1.0], periodic=True)
    x = np.random.default_rng(1).random((800, 2))
    ps = self_organize(x, resolution=lambda p: blob_monitor(p, D0), domain=torus, seed=1)
    extra = {"verlet_skin": skin} if skin else {}
    sim = Simulation(ps, blob, velocity=vortex(2.5), nu=1e-3, D0=D0, integrator="rk4", dt=0.0025,
                     reorganize_every=10, seed=1, **extra, **options)
    return sim.run(T)


def pulse_run(D0: float, T: float, **options) -> Simulation:
    """(b): the §4.3 pulse, 2D, Pe = 1000, forward Euler (the main job of ``arpy run pulse``);
    ``options``: more arguments of :func:`arpy.cases.gaussian_pulse`."""
    from arpy import cases

    return cases.gaussian_pulse(d=2, D0=D0, T=T, **options)["sim"]


def step_cost(sim: Simulation) -> dict:
    """Microseconds per particle-step, in total and per phase of the log (glue: the rest)."""
    log = sim.log
    ps = float(sum(e["n"] for e in log))
    out = {"steps": len(log), "n_mean": ps / len(log), "us": 1e6 * sum(e["t_step"] for e in log) / ps}
    for k in PHASES:
        out[k] = 1e6 * sum(e.get(k, 0.0) for e in log) / ps
    out["glue"] = out["us"] - sum(out[k] for k in PHASES)
    return out


#: The skin of the reused-lists variant of (a), as a fraction of the smallest core size.
SKIN = 0.3


def step_rows(cfg: dict, threads: tuple[int, ...], repeat: int, skin: bool = True) -> dict:
    """Best (by total) step cost of each case at each thread count, runs alternating; ``skin``: also
    (a) with reused Verlet lists ("advection+skin")."""
    cases = [("advection", advection_run, {}), ("pulse", pulse_run, {})]
    if skin:
        cases.insert(1, ("advection+skin", advection_run, {"skin": SKIN}))
    best: dict = {}
    for _ in range(repeat):
        for case, run, extra in cases:
            for t in threads:
                at_threads(t)
                cost = step_cost(run(**cfg[case.split("+")[0]], **extra))
                if (case, t) not in best or cost["us"] < best[case, t]["us"]:
                    best[case, t] = cost
    at_threads(0)
    return {f"{case}@{t}": v for (case, t), v in best.items()}


def baseline_steps(python: str, quick: bool) -> dict:
    """The steps at one thread with another arpy build (its interpreter), in a subprocess."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [python, str(Path(__file__).resolve()), "--steps-only"] + (["--quick"] if quick else [])
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, check=True, cwd=str(HERE.parent.parent))
    return json.loads(out.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------ report
def section(title: str, header: list[str], rows: list[str], intro: str = "") -> list[str]:
    """A Markdown section: title, optional paragraph, and a table with ``header`` and ``rows``."""
    from arpy._bench import md_table                 # (here: an older build running --steps-only may lack it)

    return ["", f"## {title}", ""] + ([intro, ""] if intro else []) + md_table(header, []) + rows


def report(res: dict) -> str:
    """The Markdown page of a result (``results/threads.md`` is this of ``results/threads.json``)."""
    lines = [f"# Threads ({res['machine']}, Python {res['python']})"]
    if res.get("remeasured"):
        lines += ["", "Sections measured again later: "
                  + ", ".join(f"{k} ({v})" for k, v in sorted(res["remeasured"].items())) + "."]
    lines += section("DC-PSE assembly (gradient + Laplacian at the particles, lists given)",
                     ["d", "N", "neighbours", "1 thread (s)", "2 threads (s)", "speed-up"],
                     [f"| {r['d']} | {r['n']} | {r['neighbours']:.1f} | {r['t1']:.3f} | {r['t2']:.3f} | "
                      f"{r['speedup']:.2f} |" for r in res["dcpse"]])
    lines += section("Cell lists (build + symmetric list), the AR paper's distribution",
                     ["lambda", "N", "uniform 1 / 2 threads (s)", "speed-up", "AR 1 / 2 threads (s)", "speed-up",
                      "cKDTree ball, workers 1 / 2 (s)", "cKDTree(2) / uniform(2)", "cKDTree(2) / AR(2)"],
                     [f"| {r['lam']:g} | {r['n']} | {r['cell1']:.3f} / {r['cell2']:.3f} | {r['cell_speedup']:.2f} | "
                      f"{r['ar1']:.3f} / {r['ar2']:.3f} | {r['ar_speedup']:.2f} | {r['kd1']:.2f} / {r['kd2']:.2f} | "
                      f"{r['kd2_over_cell2']:.1f} | {r['kd2_over_ar2']:.1f} |" for r in res["lists"]])
    lines += section("Periodic box against free space (uniform random, ~10 neighbours)",
                     ["method", "N", "free 1 / 2 threads (s)", "periodic 1 / 2 threads (s)",
                      "periodic / free, 1 / 2 threads", "cKDTree boxsize query_pairs (s)",
                      "cKDTree / periodic (2 threads)"],
                     [f"| {r['method']} | {r['n']} | {r['free1']:.3f} / {r['free2']:.3f} | {r['periodic1']:.3f} / "
                      f"{r['periodic2']:.3f} | {r['ratio1']:.2f} / {r['ratio2']:.2f} | {r['kd_boxsize']:.2f} | "
                      f"{r['kd_over_periodic2']:.1f} |" for r in res["periodic"]])
    steps = []
    old = res.get("baseline") or {}
    rows = [("old", k, v) for k, v in old.items()] + [("new", k, v) for k, v in res["steps"].items()]
    for build, key, r in sorted(rows, key=lambda row: (row[1].split("@")[0], row[0] == "new", row[1])):
        case, t = key.split("@")
        ref = baseline_of(old, case)
        ratio = f"{r['us'] / ref['us']:.2f}" if ref else "-"
        steps.append(f"| {case} | {build} | {t} | {r['n_mean']:.0f} | {r['us']:.1f} | {ratio} | "
                     + " | ".join(f"{r[k]:.1f}" for k in PHASES + ("glue",)) + " |")
    lines += section("Microseconds per particle-step",
                     ["case", "build", "threads", "N", "us / particle-step", "vs old, 1 thread", "monitor",
                      "SO lists", "SO rest", "interp.", "rhs", "glue"], steps,
                     f"(a) RK4 advection-diffusion, periodic box (+skin: Verlet lists reused, skin {SKIN} of the smallest "
                     "core size); (b) the §4.3 pulse, forward Euler.  Phases in "
                     "microseconds per particle-step: monitor, self-organization lists / rest, interpolation "
                     "old -> new, right-hand sides, Python glue; vs old: against the old build's one-thread "
                     "figure of the same case ((a) for +skin).")
    lines += ["", "## Targets", ""] + [f"- {line}" for line in targets(res)]
    wide = [r for r in res["lists"] if r["lam"] > 1 and r["kd2_over_cell2"] < 5.0]
    for r in wide:
        lines += ["", f"The uniform list at lambda = {r['lam']:g} is the conventional one, with cells as wide as the "
                  f"largest cutoff: it takes {r['cell2'] / r['ar2']:.0f} times the AR list's time here (2 threads), "
                  "because every particle is tested against all particles in the cells around its own, cells sized "
                  "for the coarsest cutoff.  cKDTree's ball queries adapt to each radius as the AR list does, so "
                  "this baseline could reach 5 times their speed only by becoming an adaptive search itself; it is "
                  "kept as it is, the AR paper's comparison."]
    return "\n".join(lines) + "\n"


def baseline_of(old: dict, case: str) -> dict | None:
    """The old build's one-thread figures a case is compared with: its own, (a)'s for (a) with reused
    lists (the old build has no reuse)."""
    return old.get(f"{case.split('+')[0]}@1")


def targets(res: dict) -> list[str]:
    """Each target of the benchmark against this result: the figure, the bound, met or not."""
    def check(what: str, value: float, bound: float, below: bool, shown: str = "") -> str:
        ok = value <= bound if below else value >= bound
        return f"{what}: {value:.2f} ({'<=' if below else '>='} {shown or f'{bound:g}'}: {'met' if ok else 'not met'})"

    out = [check(f"DC-PSE speed-up at 2 threads, {r['d']}D", r["speedup"], 1.8, False) for r in res["dcpse"]]
    for r in res["lists"]:
        out += [check(f"{name} list speed-up at 2 threads, lambda = {r['lam']:g}", r[f"{key}_speedup"], 1.5, False)
                for name, key in (("uniform", "cell"), ("AR", "ar"))]
        out += [check(f"cKDTree(2) / {name}(2), lambda = {r['lam']:g}", r[f"kd2_over_{key}2"], 5.0, False)
                for name, key in (("uniform", "cell"), ("AR", "ar"))]
    for r in res["periodic"]:
        out += [check(f"periodic / free, {r['method']}, {t} thread{'s' if t > 1 else ''}", r[f"ratio{t}"], 1.3, True)
                for t in (1, 2)]
    old = res.get("baseline") or {}
    for key, r in sorted(res["steps"].items()):
        case, t = key.split("@")
        ref = baseline_of(old, case)
        if t == "2" and ref:
            out.append(check(f"{case}: us per particle-step at 2 threads / the old build's at 1", r["us"] / ref["us"],
                             1 / 3, True, "1/3"))
    return out


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small sizes only (for tests)")
    parser.add_argument("--out", type=Path, default=HERE / "results", help="output folder")
    parser.add_argument("--baseline", help="interpreter of an older arpy build: the steps run there too")
    parser.add_argument("--steps-only", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--only", choices=("dcpse", "lists", "periodic", "steps"),
                        help="re-measure one section and merge it into the existing JSON (steps: with --baseline, "
                             "the older build's steps too)")
    args = parser.parse_args(argv)
    cfg = QUICK if args.quick else FULL
    if args.steps_only:                         # (the baseline's subprocess: one thread, JSON on stdout)
        print(json.dumps(step_rows(cfg, (1,), cfg["step_repeat"], skin=False)))
        return 0
    from arpy._bench import run_info, write_page, write_result

    args.out.mkdir(parents=True, exist_ok=True)
    tag = "threads_quick" if args.quick else "threads"
    if args.only:
        sections = {"dcpse": lambda: dcpse_rows(cfg["dcpse_n"], cfg["repeat"]),
                    "lists": lambda: list_rows(cfg["lists_n"], cfg["lams"], cfg["repeat"]),
                    "periodic": lambda: periodic_rows(cfg["periodic_n"], cfg["repeat"]),
                    "steps": lambda: step_rows(cfg, (1, 2), cfg["step_repeat"])}
        path = args.out / f"{tag}.json"
        res = json.loads(path.read_text())
        res[args.only] = sections[args.only]()
        if args.only == "steps" and args.baseline:
            res["baseline"] = baseline_steps(args.baseline, args.quick)
        res.setdefault("remeasured", {})[args.only] = time.strftime("%Y-%m-%d")
        write_result(args.out, tag, res, f"{args.out / tag}.md")
        print(write_page(args.out, tag, report).read_text())
        return 0
    res = dict(run_info(), quick=args.quick, cores=os.cpu_count())
    res["dcpse"] = dcpse_rows(cfg["dcpse_n"], cfg["repeat"])
    res["lists"] = list_rows(cfg["lists_n"], cfg["lams"], cfg["repeat"])
    res["periodic"] = periodic_rows(cfg["periodic_n"], cfg["repeat"])
    res["steps"] = step_rows(cfg, (1, 2), cfg["step_repeat"])
    res["baseline"] = baseline_steps(args.baseline, args.quick) if args.baseline else None
    write_result(args.out, tag, res, f"{args.out / tag}.md")
    page = write_page(args.out, tag, report)
    print(page.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
