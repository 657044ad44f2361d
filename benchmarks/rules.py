"""Benchmark: the cost of the max and sum cutoff rules against the min rule, at equal numbers of pairs.

N uniformly random particles in the unit square (cube) with per-particle cutoffs drawn log-uniformly
over a span of 10, the min rule's cutoffs chosen for about 8 (2D; 18 in 3D) neighbours per particle.
The max and sum rules find more pairs at the same cutoffs, so their cutoffs are scaled by one factor
per rule until their lists hold as many pairs as the min rule's (two secant steps on the pair count of
the uniform cell list).  Then each rule's half list is timed with the uniform cell list
(``method="cell"``) and the AR cell list (``method="ar"``), and the two methods' pairs are compared.
The target of issue 53: a max- or sum-rule list costs at most 1.3 times the min-rule list of as many
pairs.  The ratios are of CPU times (``time.process_time``, the best of several runs): on a machine
shared with other work the wall time of a run depends on what else runs, its CPU time much less; run
at one thread (``OMP_NUM_THREADS=1``) the two agree on a quiet machine.  Wall times are recorded too.

    python benchmarks/rules.py            # N = 1e5 and 1e6, 2D and 3D (a few minutes)
    python benchmarks/rules.py --quick    # N = 1e3 (seconds)

Results: ``results/rules.json``, ``.md`` (the page, from the JSON by :func:`report`) and ``.png``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

import arpy
from arpy._bench import benchmark_args, md_table, run_info, write_outputs

HERE = Path(__file__).resolve().parent
RULES = ("min", "max", "sum")
METHODS = ("cell", "ar")
#: the span max(rc) / min(rc) of the cutoffs
SPAN = 10.0


def make_case(n: int, d: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Uniform random points (n, d) and log-uniform cutoffs (n,) over SPAN, about 8 (2D) / 18 (3D)
    min-rule neighbours per particle."""
    rng = np.random.default_rng(seed)
    x = rng.random((n, d))
    target = 8.0 if d == 2 else 18.0
    ball = np.pi if d == 2 else 4.0 * np.pi / 3.0
    u = rng.random(n)
    # the min rule's mean pair volume grows with the smaller cutoff of a pair: <min(a, b)^d> of the span
    a, b = rng.random(200_000), rng.random(200_000)
    mean = float(np.mean(SPAN ** (d * np.minimum(a, b))))
    rc0 = (target / (ball * n * mean)) ** (1.0 / d)
    return x, rc0 * SPAN ** u


def scale_for(x: np.ndarray, rc: np.ndarray, rule: str, pairs: int) -> float:
    """The factor s with about ``pairs`` pairs in the ``rule`` list of cutoffs s rc (secant steps on
    log(pairs) against log(s), slope d to start)."""
    d = x.shape[1]
    s, slope = 1.0, float(d)
    count = len(arpy.neighbor_list(x, rc, rule=rule))
    for _ in range(3):
        if count == pairs:
            break
        s_new = s * (pairs / count) ** (1.0 / slope)
        count_new = len(arpy.neighbor_list(x, s_new * rc, rule=rule))
        if count_new != count and s_new != s:
            slope = float(np.log(count_new / count) / np.log(s_new / s))
        s, count = s_new, count_new
    return s


def best_times(fn, repeat: int) -> tuple[float, float, arpy.NeighborList]:
    """(least CPU time, least wall time, in s, the last result) of ``repeat`` calls of fn."""
    cpu, wall, out = np.inf, np.inf, None
    for _ in range(max(1, repeat)):
        c0, w0 = time.process_time(), time.perf_counter()
        out = fn()
        cpu, wall = min(cpu, time.process_time() - c0), min(wall, time.perf_counter() - w0)
    return cpu, wall, out


def run(sizes: list[int], dims: list[int], repeat: int) -> list[dict]:
    """The rows of every d, N, rule and method.  For each d, N and method the three rules' lists are
    built in turn, ``repeat`` rounds, so that the ratios compare runs made under the same load."""
    rows = []
    for d in dims:
        for n in sizes:
            x, rc = make_case(n, d)
            target = len(arpy.neighbor_list(x, rc))
            scales = {rule: 1.0 if rule == "min" else scale_for(x, rc, rule, target) for rule in RULES}
            cutoffs = {rule: scales[rule] * rc for rule in RULES}
            ref_pairs: dict[str, tuple[np.ndarray, np.ndarray]] = {}
            for method in METHODS:
                cpu = {rule: np.inf for rule in RULES}
                wall = dict(cpu)
                lists: dict[str, arpy.NeighborList] = {}
                for _ in range(max(1, repeat)):
                    for rule in RULES:
                        t, w, lists[rule] = best_times(
                            lambda: arpy.neighbor_list(x, cutoffs[rule], method=method, rule=rule), 1)
                        cpu[rule], wall[rule] = min(cpu[rule], t), min(wall[rule], w)
                for rule in RULES:
                    nl = lists.pop(rule)
                    pairs = nl.pairs()
                    same = True
                    if rule in ref_pairs:
                        same = all(np.array_equal(a, b) for a, b in zip(pairs, ref_pairs[rule]))
                    else:
                        ref_pairs[rule] = pairs
                    row = {"d": d, "n": n, "rule": rule, "method": method, "scale": scales[rule], "pairs": len(nl),
                           "seconds": cpu[rule], "wall_seconds": wall[rule], "same_pairs": bool(same)}
                    rows.append(row)
                    print(f"{d}D N={n:>9,} {rule:>4s} {method:>5s} scale {scales[rule]:6.3f} pairs {len(nl):>11,} "
                          f"CPU {1e3 * cpu[rule]:9.2f} ms wall {1e3 * wall[rule]:9.2f} ms "
                          f"{'ok' if same else 'DIFFERENT'}", flush=True)
    return rows


def ratios(rows: list[dict]) -> dict[tuple[int, int, str, str], float]:
    """(d, n, rule, method) -> time of the rule's list over the min rule's (same d, n, method)."""
    at = {(r["d"], r["n"], r["rule"], r["method"]): r for r in rows}
    return {k: r["seconds"] / at[(k[0], k[1], "min", k[3])]["seconds"] for k, r in at.items()}


def plot(res: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    rows = res["rows"]
    q = ratios(rows)
    fig, ax = plt.subplots(figsize=(7.5, 4))
    keys = sorted({(d, n) for d, n, _, _ in q})
    width = 0.2
    for k, (rule, method) in enumerate([(r, m) for r in ("max", "sum") for m in METHODS]):
        vals = [q[(d, n, rule, method)] for d, n in keys]
        ax.bar(np.arange(len(keys)) + (k - 1.5) * width, vals, width, label=f"{rule}, {method}")
    ax.axhline(1.3, color="k", ls="--", lw=1, label="target 1.3")
    ax.axhline(1.0, color="gray", lw=0.8)
    ax.set_xticks(np.arange(len(keys)), [f"{d}D, N = {n:.0e}" for d, n in keys])
    ax.set_ylabel("time / min-rule time (equal pairs)")
    ax.legend(fontsize=8, ncol=3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(res: dict) -> str:
    """The Markdown page of a result (results/rules.md is this of results/rules.json)."""
    rows, meta = res["rows"], res["meta"]
    q = ratios(rows)
    stem = "rules" + ("_quick" if meta.get("quick") else "")
    lines = [
        "# The cost of the max and sum cutoff rules",
        "",
        "Neighbour lists under the max rule (|x_p - x_q| <= max(rc_p, rc_q)) and the sum rule "
        "(<= rc_p + rc_q) against the min rule (<= min(rc_p, rc_q)), at equal numbers of pairs.",
        "",
        "    python benchmarks/rules.py            # the sizes below",
        "    python benchmarks/rules.py --quick    # N = 1e3, in seconds",
        "",
        "## Set-up",
        "",
        f"Uniformly random points in the unit square (cube), cutoffs log-uniform over a span of {meta['span']:g}, "
        "the min rule's for about 8 (2D) / 18 (3D) neighbours per particle. Each other rule's cutoffs are "
        "those times one factor (the scale column), chosen so that its list holds about as many pairs. "
        f"Half lists; times are the least CPU time (and wall time) of {meta['repeat']} run(s) at "
        f"{meta['threads']} thread(s), the three rules' lists built in turn in each round; the ratio is the CPU "
        "time over the min-rule CPU time of the same method, N and d (CPU times depend much less than wall times "
        "on other work of the machine).",
        "",
    ]
    table = []
    for r in rows:
        table.append([f"{r['d']}D", f"{r['n']:,}", r["rule"], r["method"], f"{r['scale']:.3f}", f"{r['pairs']:,}",
                      f"{1e3 * r['seconds']:.1f}", f"{1e3 * r['wall_seconds']:.1f}",
                      f"{q[(r['d'], r['n'], r['rule'], r['method'])]:.2f}",
                      "yes" if r["same_pairs"] else "NO"])
    lines += md_table(["d", "N", "rule", "method", "scale", "pairs", "CPU (ms)", "wall (ms)", "ratio to min",
                       "same pairs as cell"], table)
    worst = max((v, k) for k, v in q.items() if k[2] != "min")
    best = {}
    for r in rows:
        key = (r["d"], r["n"], r["rule"])
        best[key] = min(best.get(key, np.inf), r["seconds"])
    fastest = "; ".join(f"{d}D N = {n:,}: max {best[d, n, 'max'] / best[d, n, 'min']:.2f}, "
                        f"sum {best[d, n, 'sum'] / best[d, n, 'min']:.2f}"
                        for d, n in sorted({(d, n) for d, n, _ in best}))
    lines += ["", "## Findings", "",
              f"- The largest ratio is {worst[0]:.2f} ({worst[1][2]} rule, {worst[1][3]}, {worst[1][0]}D, "
              f"N = {worst[1][1]:,}); the target is 1.3.",
              f"- The faster method of each rule against the faster method of the min rule: {fastest}.",
              "- " + ("The uniform and AR cell lists found the same pairs under every rule." if all(
                  r["same_pairs"] for r in rows) else "Some lists of the two methods differ (see the table)."),
              "", f"![Time over the min rule's at equal pairs]({stem}.png)", "",
              f"Run of {meta['date']} on {meta['machine']}, Python {meta['python']}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    def extra(parser):
        parser.add_argument("--repeat", type=int, default=5, help="timing rounds; the best is reported")

    args = benchmark_args(__doc__, argv, HERE / "results", extra)
    sizes = [1_000] if args.quick else [100_000, 1_000_000]
    repeat = 1 if args.quick else args.repeat
    rows = run(sizes, [2, 3], repeat)
    stem = "rules" + ("_quick" if args.quick else "")
    meta = {**run_info(), "date": time.strftime("%Y-%m-%d"), "repeat": repeat, "quick": args.quick,
            "span": SPAN, "threads": arpy.get_num_threads()}
    write_outputs(args.out, stem, {"meta": meta, "rows": rows}, plot, report)
    return 0 if all(r["same_pairs"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
