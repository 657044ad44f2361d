"""Benchmark: building neighbour lists with arpy's uniform cell list vs scipy's cKDTree.

For N = 1e3 ... 1e6 uniformly random particles in the unit square (or cube),
with one cutoff chosen for about 8 neighbours per particle (2D; 18 in 3D)
and with per-particle cutoffs (log-uniform in [0.5, 2] x that cutoff, min
rule), it times in the same run:

  arpy cell (sym)    arpy.neighbor_list(x, rc)                         half list, CSR
  arpy cell (full)   arpy.neighbor_list(x, rc, full=True)              full list, CSR
  arpy brute         arpy.neighbor_list(x, rc, method="brute")         N <= 1e4 only
  kd query_pairs     cKDTree(x).query_pairs(max rc) (+ min-rule filter) pair array
  kd ball_point      cKDTree(x).query_ball_point(x, rc) (+ min rule)    lists per particle

and checks that every method finds the same pairs.  Peak memory of the arpy
build is measured in a fresh subprocess (growth of the resident set's high-water
mark during the call, Linux).  Prints a table, writes JSON and a PNG plot.

    python benchmarks/cell_lists.py              # full run (about 2 minutes)
    python benchmarks/cell_lists.py --quick      # small sizes, seconds

Results: ``results/cell_lists_2d.json``, ``.png`` and ``.md`` (the page, from the JSON by :func:`report`).
"""

from __future__ import annotations

import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import scipy.spatial  # noqa: F401  (imported before timing starts)

import arpy
from arpy._bench import (benchmark_args, best_time, kdtree_ball_pairs, kdtree_pairs, md_table, peak_memory_growth,
                         write_page)

HERE = Path(__file__).resolve().parent


def make_case(n: int, d: int, kind: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Uniform random points and cutoffs for about 8 (2D) / 18 (3D) neighbours."""
    rng = np.random.default_rng(seed)
    x = rng.random((n, d))
    target = 8.0 if d == 2 else 18.0
    ball = np.pi if d == 2 else 4.0 * np.pi / 3.0
    rc0 = (target / (ball * n)) ** (1.0 / d)
    if kind == "single":
        return x, np.full(n, rc0)
    return x, rc0 * np.exp(rng.uniform(np.log(0.5), np.log(2.0), n))


def sorted_pairs(i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.minimum(i, j), np.maximum(i, j)
    order = np.lexsort((b, a))
    return a[order], b[order]


def peak_memory_bytes(n: int, d: int, kind: str, method: str) -> float:
    """Peak resident-memory growth (bytes) during one arpy build, in a fresh process."""
    setup = (f"import sys, arpy\nsys.path.insert(0, {str(HERE)!r})\nfrom cell_lists import make_case\n"
             f"x, rc = make_case({n}, {d}, {kind!r})\narpy.neighbor_list(x[:10], rc[:10])")
    return float(peak_memory_growth(setup, f"nl = arpy.neighbor_list(x, rc, method={method!r})"))


def run(sizes: list[int], d: int, repeat: int, memory: bool) -> list[dict]:
    rows = []
    for kind in ("single", "per-particle"):
        for n in sizes:
            x, rc = make_case(n, d, kind)
            methods = {
                "arpy cell (sym)": lambda: arpy.neighbor_list(x, rc),
                "arpy cell (full)": lambda: arpy.neighbor_list(x, rc, full=True),
                "kd query_pairs": lambda: kdtree_pairs(x, rc),
                "kd ball_point": lambda: kdtree_ball_pairs(x, rc),
            }
            if n <= 10_000:
                methods["arpy brute"] = lambda: arpy.neighbor_list(x, rc, method="brute")
            reference = None
            for name, fn in methods.items():
                t, out = best_time(fn, repeat=repeat if n < 1_000_000 or name != "kd ball_point" else 1)
                pairs = out.pairs() if isinstance(out, arpy.NeighborList) else sorted_pairs(*out)
                if reference is None:
                    reference = pairs
                same = bool(np.array_equal(pairs[0], reference[0]) and np.array_equal(pairs[1], reference[1]))
                row = {"d": d, "cutoffs": kind, "n": n, "method": name, "seconds": t,
                       "ns_per_particle": 1e9 * t / n, "pairs": int(pairs[0].size),
                       "neighbours_per_particle": 2.0 * pairs[0].size / n, "same_pairs": same}
                if memory and name == "arpy cell (sym)":
                    row["peak_bytes_per_particle"] = peak_memory_bytes(n, d, kind, "cell") / n
                rows.append(row)
                print_row(row)
    return rows


def print_row(r: dict) -> None:
    mem = r.get("peak_bytes_per_particle")
    mem_s = "       -" if mem is None else f"{mem:8.0f}"
    print(f"{r['cutoffs']:>12s} {r['n']:>8d} {r['method']:>17s} {1e3 * r['seconds']:10.2f} "
          f"{r['ns_per_particle']:9.0f} {r['neighbours_per_particle']:6.2f} {mem_s}  {'ok' if r['same_pairs'] else 'DIFFERENT'}")


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for ax, kind in zip(axes, ("single", "per-particle")):
        for method in sorted({r["method"] for r in rows}):
            pts = [(r["n"], r["ns_per_particle"]) for r in rows if r["cutoffs"] == kind and r["method"] == method]
            if pts:
                n, t = zip(*pts)
                ax.loglog(n, t, "o-", label=method)
        ax.set_title(f"{kind} cutoff{'s' if kind != 'single' else ''}, d = {rows[0]['d']}")
        ax.set_xlabel("N particles")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("build time per particle [ns]")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ------------------------------------------------------------------ the results page
#: the methods of a row (JSON name -> column name, call)
METHODS = {
    "arpy cell (sym)": ("arpy sym", "`arpy.neighbor_list(x, rc)`: half list, CSR"),
    "arpy cell (full)": ("arpy full", "`arpy.neighbor_list(x, rc, full=True)`: full list, CSR"),
    "kd query_pairs": ("query_pairs", "`cKDTree(x).query_pairs(max rc)`, then the min rule: a pair array"),
    "kd ball_point": ("ball_point", "`cKDTree(x).query_ball_point(x, rc)`, then the min rule: a list per particle"),
    "arpy brute": ("brute", "`arpy.neighbor_list(x, rc, method=\"brute\")`: every pair checked (N <= 1e4)"),
}


def report(res: dict) -> str:
    """The Markdown page of a result (results/cell_lists_2d.md is this of results/cell_lists_2d.json)."""
    meta, rows = res["meta"], res["rows"]
    d = rows[0]["d"]
    stem = f"cell_lists_{d}d" + ("_quick" if meta.get("quick") else "")
    at = {(r["cutoffs"], r["n"], r["method"]): r for r in rows}
    sizes = sorted({r["n"] for r in rows})
    kinds = [k for k in ("single", "per-particle") if any(r["cutoffs"] == k for r in rows)]
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    big = sizes[-1]
    repeat = f"best of {meta['repeat']} runs" if "repeat" in meta else "best of several runs"
    once = f" (`query_ball_point` at N = {big:,}: one run)" if big >= 1_000_000 and meta.get("repeat", 2) > 1 else ""
    lines = [
        f"# Uniform cell lists against scipy's cKDTree ({d}D)",
        "",
        "arpy's uniform cell list (the conventional cell list of the AR paper) and scipy's `cKDTree`, "
        "timed in the same run on uniformly random points. The papers give no times for this case; "
        "[ar_cell_lists.md](ar_cell_lists.md) has the AR paper's Figs. 6 and 7.",
        "",
        "    python benchmarks/cell_lists.py           # the sizes below",
        "    python benchmarks/cell_lists.py --quick   # N = 1e3 and 1e4, one run each, in seconds",
        "    python benchmarks/cell_lists.py --d 3     # the same in the unit cube",
        "",
        "## Set-up",
        "",
        f"N = {', '.join(f'{n:,}' for n in sizes)} uniformly random points in the unit "
        f"{'square' if d == 2 else 'cube'}, with one cutoff for about {8 if d == 2 else 18} neighbours per particle, "
        "or with per-particle cutoffs drawn log-uniformly from 0.5 to 2 times that cutoff (a pair is kept "
        f"within the smaller of its two cutoffs: the min rule). Times are the {repeat}{once}; "
        "the tables give them in nanoseconds per particle. The peak memory is the growth of the resident set during "
        "one symmetric build, in a fresh process.",
        "",
    ]
    lines += md_table(["method", "call"], [list(METHODS[m]) for m in methods])
    for kind in kinds:
        header = ["N", "neighbours per particle"] + [METHODS[m][0] for m in methods]
        header += ["query_pairs / arpy sym", "ball_point / arpy sym", "peak memory, arpy sym (bytes per particle)"]
        table = []
        for n in sizes:
            r = {m: at.get((kind, n, m)) for m in methods}
            sym = r["arpy cell (sym)"]
            mem = sym.get("peak_bytes_per_particle")
            table.append([f"{n:,}", f"{sym['neighbours_per_particle']:.2f}"]
                         + [f"{r[m]['ns_per_particle']:.0f}" if r[m] else "-" for m in methods]
                         + [f"{r['kd query_pairs']['seconds'] / sym['seconds']:.1f}",
                            f"{r['kd ball_point']['seconds'] / sym['seconds']:.0f}",
                            "-" if mem is None else f"{mem:.0f}"])
        title = "one cutoff" if kind == "single" else "per-particle cutoffs (min rule)"
        lines += ["", f"## Results: {title}", ""] + md_table(header, table)

    lines += ["", "## Findings", ""]
    different = sorted({(r["cutoffs"], r["n"], r["method"]) for r in rows if not r["same_pairs"]})
    lines.append("- Every method found the same pairs at every size." if not different else
                 "- Pairs that differ from the first method's: " + ", ".join(f"{m} ({k}, N = {n})"
                                                                          for k, n, m in different) + ".")
    for kind in kinds:
        sym = at[kind, big, "arpy cell (sym)"]
        full, qp, bp = (at[kind, big, m] for m in ("arpy cell (full)", "kd query_pairs", "kd ball_point"))
        fit = np.polyfit(np.log(sizes), np.log([at[kind, n, "arpy cell (sym)"]["seconds"] for n in sizes]), 1)[0]
        lines.append(
            f"- {'One cutoff' if kind == 'single' else 'Per-particle cutoffs'}, N = {big:,}: the symmetric list takes "
            f"{1e3 * sym['seconds']:.0f} ms, the full list {1e3 * full['seconds']:.0f} ms; `query_pairs` is "
            f"{qp['seconds'] / sym['seconds']:.1f} times slower and `query_ball_point` "
            f"{bp['seconds'] / sym['seconds']:.0f} times. The symmetric build's time grows as N^{fit:.2f} "
            f"(least-squares fit over N = {sizes[0]:,} to {big:,}).")
    sym = at["single", big, "arpy cell (sym)"]
    if sym.get("peak_bytes_per_particle"):
        result = 8 + 4 * sym["pairs"] / big
        lines.append(
            f"- Memory: a symmetric build of N = {big:,} (one cutoff) peaks at "
            f"{sym['peak_bytes_per_particle']:.0f} bytes per particle. The list itself holds {result:.0f} of them: "
            f"an 8-byte row offset per particle and a 4-byte index per stored pair ({sym['pairs'] / big:.2f} pairs "
            "per particle). The resident set grows in whole pages, so the smallest sets read close to 0.")
    lines += ["", f"![Build time per particle against N, one cutoff and per-particle cutoffs]({stem}.png)", "",
              f"Run of {meta['date']} on {meta['machine']}, Python {meta['python']}, NumPy {meta['numpy']}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    def extra(parser):
        parser.add_argument("--d", type=int, default=2, choices=(2, 3))
        parser.add_argument("--repeat", type=int, default=5, help="timing repeats; the best is reported")
        parser.add_argument("--no-memory", action="store_true", help="skip the peak-memory subprocesses")

    args = benchmark_args(__doc__, argv, HERE / "results", extra)
    sizes = [1_000, 10_000] if args.quick else [1_000, 10_000, 100_000, 1_000_000]
    repeat = 1 if args.quick else args.repeat
    print(f"{'cutoffs':>12s} {'N':>8s} {'method':>17s} {'time [ms]':>10s} {'ns/part':>9s} {'nbrs':>6s} {'B/part':>8s}  pairs")
    rows = run(sizes, args.d, repeat, memory=not args.no_memory)
    stem = f"cell_lists_{args.d}d" + ("_quick" if args.quick else "")
    meta = {"python": sys.version.split()[0], "numpy": np.__version__, "machine": platform.machine(),
            "processor": platform.processor(), "date": time.strftime("%Y-%m-%d"), "repeat": repeat,
            "quick": args.quick}
    (args.out / f"{stem}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    write_page(args.out, stem, report)
    plot(rows, args.out / f"{stem}.png")
    # the headline ratio: arpy symmetric build vs query_pairs at the largest N, one cutoff
    big = max(sizes)
    t = {r["method"]: r["seconds"] for r in rows if r["n"] == big and r["cutoffs"] == "single"}
    print(f"\nN = {big}, one cutoff: arpy cell (sym) {1e3 * t['arpy cell (sym)']:.1f} ms, "
          f"cKDTree.query_pairs {1e3 * t['kd query_pairs']:.1f} ms, ratio 1/{t['kd query_pairs'] / t['arpy cell (sym)']:.1f}")
    print(f"wrote {args.out / (stem + '.json')}, {stem}.md and {stem}.png")
    return 0 if all(r["same_pairs"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
