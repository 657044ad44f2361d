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

Results: ``results/ar_cell_lists.json``, ``_fig6.png``, ``_fig7.png`` and ``.md`` (the page, from the
JSON by :func:`report`).
"""

from __future__ import annotations

import itertools
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

import arpy
from arpy._bench import (MAX_KD_PAIRS_CANDIDATES, benchmark_args, best_time, break_even, compare_lists, md_table,
                         write_page)

HERE = Path(__file__).resolve().parent


def measure(n_small: int, lam: float, repeat: int, ns_per_check: list[float], memory: bool,
            kd_pairs_max: float = MAX_KD_PAIRS_CANDIDATES) -> dict:
    x, rc = arpy.ar_benchmark(n_small, lam)
    return {"lam": lam, "n_small": n_small, **compare_lists(x, rc, repeat, ns_per_check, memory, kd_pairs_max)}


def stencil_candidates(x: np.ndarray, lo: np.ndarray, edge: float) -> float:
    """The mean number of other particles in the 3^d cells around each particle's own cell, for cells
    of the given edge anchored at lo: the distance checks per particle of a one-level cell list
    (counted from the cell occupancy, both directions)."""
    c = np.floor((x - lo) / edge).astype(np.int64)
    c -= c.min(axis=0) - 1
    dims = c.max(axis=0) + 2
    key = np.ravel_multi_index(c.T, dims)
    cells, count = np.unique(key, return_counts=True)
    total = np.zeros(len(cells))
    for shift in itertools.product((-1, 0, 1), repeat=x.shape[1]):
        k = np.ravel_multi_index((np.array(np.unravel_index(cells, dims)).T + shift).T, dims)
        pos = np.clip(np.searchsorted(cells, k), 0, len(cells) - 1)
        total += np.where(cells[pos] == k, count[pos], 0)
    return float(((total - 1) * count).sum() / len(x))


def ar_phases(x: np.ndarray, rc: np.ndarray) -> dict:
    """Calls that split the AR list's time: the tree alone (build), and tree + pairs published in
    the tree's order (search); the whole call adds the hand-off into arrays in particle order."""
    from arpy import _core

    xt = np.asfortranarray(x.T)
    code = arpy.METHODS["ar"]

    def search():
        lh, nnz, info, bad = _core.arpy_neighbors(xt, rc, 0.0, code, 0, 1, 0, np.empty(0, np.int64))
        _core.arpy_result_free(lh)

    return {"build": lambda: _core.arpy_build_only(xt, rc, code), "search": search}


def page_faults(call) -> int:
    """Minor page faults (first touches of memory the process got from the system) of one call,
    after a first call."""
    import resource

    call()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    call()
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


#: glibc keeps the memory a call frees for the next one (no heap trimming, no mmap for large blocks).
MALLOC_KEEP = {"MALLOC_TRIM_THRESHOLD_": "4000000000", "MALLOC_MMAP_THRESHOLD_": "2000000000"}

_KEEP_RUN = """
import json, sys
import numpy as np
import arpy
from arpy._bench import best_time
sys.path.insert(0, sys.argv[1])
from ar_cell_lists import lam1_input
d, n_small, repeat = (int(a) for a in sys.argv[2:5])
x, rc = lam1_input(d, n_small)
best = {"ar": np.inf, "uniform": np.inf}
for _ in range(repeat):
    for key, method in (("ar", "ar"), ("uniform", "cell")):
        best[key] = min(best[key], best_time(lambda: arpy.neighbor_list(x, rc, method=method), 1)[0])
print(json.dumps(best))
"""


def malloc_kept(d: int, n_small: int, repeat: int) -> dict:
    """The lambda = 1 row's AR and uniform lists (random order) in a process whose glibc keeps freed
    memory (MALLOC_KEEP): what the page faults of fresh memory cost."""
    import os
    import subprocess

    out = subprocess.run([sys.executable, "-c", _KEEP_RUN, str(HERE), str(d), str(n_small), str(repeat)], check=True,
                         capture_output=True, text=True, env={**os.environ, **MALLOC_KEEP}).stdout
    return {"d": d, "n_small": n_small, "env": MALLOC_KEEP, **json.loads(out.strip().splitlines()[-1])}


def small_pages(call):
    """``call`` with the core's huge-page advice off (arpy.set_huge_pages)."""
    def run():
        before = arpy.set_huge_pages(False)
        try:
            return call()
        finally:
            arpy.set_huge_pages(before)
    return run


def lam1_input(d: int, n_small: int) -> tuple[np.ndarray, np.ndarray]:
    """The lambda = 1 sweep's particles: the paper's distribution (generated in lattice order) in
    a random order, the same for every run."""
    x, rc = arpy.ar_benchmark(n_small, 1.0, d=d)
    shuffle = np.random.default_rng(d).permutation(len(x))
    return x[shuffle], rc[shuffle]


def lam1_row(d: int, n_small: int, repeat: int) -> dict:
    """lambda = 1 (one cutoff): AR and uniform lists (build + symmetric list) side by side on the
    particles in random order and in cache order (arpy.cache_order), the floor (one copy of the
    list's arrays), the AR list's phases, and the checks per particle of the fitted root's cells
    against those of the paper's root (D_m = the extent)."""
    x, rc = lam1_input(d, n_small)
    row: dict = {"d": d, "n": len(x)}
    row["cache_order"], perm = best_time(lambda: arpy.cache_order(x), repeat)
    orders = (("", (x, rc)), ("_cache_order", (x[perm], rc[perm])))
    nl = arpy.neighbor_list(x, rc, method="ar")
    calls = {"floor": lambda: (nl.offsets.copy(), nl.indices.copy())}
    for tag, (xs, rcs) in orders:
        calls[f"ar_total{tag}"] = lambda xs=xs, rcs=rcs: arpy.neighbor_list(xs, rcs, method="ar")
        calls[f"uniform_total{tag}"] = lambda xs=xs, rcs=rcs: arpy.neighbor_list(xs, rcs, method="cell")
        calls.update({f"ar_{k}{tag}": f for k, f in ar_phases(xs, rcs).items()})
    calls["ar_total_small_pages"] = small_pages(calls["ar_total"])
    # the list in the search's cell order (no pass back to input order), on the random input and on
    # the particles already in that order (a caller who keeps them sorted)
    order, cl = arpy.neighbor_list_in_cell_order(x, rc, method="ar")
    xo, ro = x[order], rc[order]
    ci, cj = (order[k] for k in cl.pairs(sort=False))
    mapped = arpy.NeighborList.from_pairs(len(x), ci, cj).pairs()
    row["cells_same_pairs"] = all(np.array_equal(a, b) for a, b in zip(mapped, nl.pairs()))
    calls["ar_cells"] = lambda: arpy.neighbor_list_in_cell_order(x, rc, method="ar")
    calls["ar_cells_sorted"] = lambda: arpy.neighbor_list_in_cell_order(xo, ro, method="ar")
    row.update(dict.fromkeys(calls, np.inf))
    for _ in range(repeat):           # every call once per round: a slow spell of the machine hits them all
        for key, call in calls.items():
            row[key] = min(row[key], best_time(call, 1)[0])
    # the floor also with nothing in between: the copies reuse the memory the one before freed
    row["floor_warm"], _ = best_time(calls["floor"], repeat)
    row["faults_per_particle"] = page_faults(calls["ar_total"]) / len(x)
    row["faults_per_particle_small_pages"] = page_faults(calls["ar_total_small_pages"]) / len(x)
    tree = arpy.ARCellList(x, rc)
    extent = float(np.max(x.max(axis=0) - x.min(axis=0)))
    r = float(rc.min())
    paper_edge = extent                                    # the paper's levels: the deepest extent / 2^k above r
    while paper_edge / 2 > r:
        paper_edge /= 2
    fitted_edge = float(np.ldexp(tree.edge, -tree.maxlevel))
    row.update(D_m=tree.edge, extent=extent, edge_over_rc=fitted_edge / r, paper_edge_over_rc=paper_edge / r,
               checks=stencil_candidates(x, tree.lo, fitted_edge),
               paper_checks=stencil_candidates(x, x.min(axis=0), paper_edge),
               predicted_checks_ratio=(fitted_edge / paper_edge) ** d, entries=len(nl))
    return row


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


# ------------------------------------------------------------------ the results page
#: The paper's statements (Awile et al. 2012, Sec. 3.1): (what, the paper's words, its value)
PAPER = {
    "build": ("AR build / uniform build (Fig. 7a)", "about 10 (\"about one order of magnitude\")", 10.0),
    "lam1": ("AR total / uniform total at lambda = 1", "1.25 (conventional lists \"about 25% faster\")", 1.25),
    "break_even": ("break-even lambda (uniform total = AR total)", "3.65", 3.65),
    "lam10": ("uniform total / AR total at lambda = 10", "about 10 (\"about one order of magnitude\")", 10.0),
    "lam1000": ("uniform total / AR total at lambda = 1000, N = 1e6 (Fig. 6d)",
                "almost 1000 (\"almost three orders of magnitude\")", 1000.0),
    "plateau": ("uniform total stops growing with lambda (Fig. 7b)", "at lambda = 200", 200.0),
}


def seconds(t: float) -> str:
    return f"{1e6 * t:.3g} us" if t < 1e-3 else f"{1e3 * t:.3g} ms" if t < 1 else f"{t:.3g} s"


def ratio(q: float) -> str:
    return f"{q:.2f}" if q < 10 else f"{q:.1f}" if q < 100 else f"{q:,.0f}"


def exponent(a: dict, b: dict, key: str) -> float:
    """The growth exponent of ``key`` between two rows: log(t_b / t_a) / log(N_b / N_a)."""
    return float(np.log(b[key] / a[key]) / np.log(b["n"] / a["n"]))


def lam1_section(res: dict) -> list[str]:
    """The lambda = 1 sweep: AR against uniform and against the floor, and the checks per particle."""
    rows = res.get("lam1")
    if not rows:
        return []
    meta = res.get("lam1_meta", {})
    lines = ["", "## lambda = 1 against N: the root fitted to the smallest cutoff", "",
             "The paper's distribution at lambda = 1 (one cutoff), N from "
             f"{rows[0]['n']:,} to {max(r['n'] for r in rows):,} in 2D and 3D, build + symmetric list, best of "
             f"{meta.get('repeat', '-')} runs at {meta.get('threads', '-')} threads ({meta.get('date', '')}). "
             "The floor is one copy of the list's own arrays (`offsets` and `indices`) into new arrays, timed "
             "between the lists (\"floor\", the memory as fresh as the list's own) and in a row (\"warm\": each "
             "copy reuses the memory the one before freed). How fresh the memory between the lists is depends on "
             "what glibc kept from the calls before, so the floor moves between runs (at N = 1e6, 2D: from the "
             "warm copy's time to over twice it). The particles are "
             "given in random order, and in cache order (`arpy.cache_order`, the Morton curve; the time it takes "
             "is listed). The root's edge D_m is fitted to the smallest cutoff "
             "(r 2^K, r the double above it): the finest cells are r wide. The paper's root (D_m = the extent) "
             "would make them extent / 2^k, anywhere in (r_c, 2 r_c] depending on N; its checks per particle are "
             "counted from the cell occupancy of that geometry, as are the fitted root's. The core asks for "
             "transparent huge pages for its arrays of 4 MiB and more (`arpy.set_huge_pages`); the findings give "
             "the AR list without them too.", ""]
    lines += md_table(
        ["d", "N", "AR", "uniform", "AR / uniform", "floor", "AR / floor", "warm", "AR / warm", "AR, cache order",
         "uniform, cache order",
         "its AR / uniform", "its AR / floor", "cache_order", "cell edge / r_c", "paper's", "checks per particle",
         "paper's", "ratio (predicted)"],
        [[str(r["d"]), f"{r['n']:,}", seconds(r["ar_total"]), seconds(r["uniform_total"]),
          f"{r['ar_total'] / r['uniform_total']:.2f}", seconds(r["floor"]), f"{r['ar_total'] / r['floor']:.1f}",
          seconds(r["floor_warm"]), f"{r['ar_total'] / r['floor_warm']:.1f}", seconds(r["ar_total_cache_order"]),
          seconds(r["uniform_total_cache_order"]),
          f"{r['ar_total_cache_order'] / r['uniform_total_cache_order']:.2f}",
          f"{r['ar_total_cache_order'] / r['floor']:.1f}", seconds(r["cache_order"]),
          f"{r['edge_over_rc']:.3f}", f"{r['paper_edge_over_rc']:.3f}", f"{r['checks']:.1f}",
          f"{r['paper_checks']:.1f}", f"{r['checks'] / r['paper_checks']:.2f} ({r['predicted_checks_ratio']:.2f})"]
         for r in rows])
    if "ar_cells" in rows[0]:
        lines += ["", "The AR list in the search's own cell order (`arpy.neighbor_list_in_cell_order`: rows and "
                  "entries are the particles sorted by level and cell, returned with that order, without the pass "
                  "back to input order): on the particles in random order, and on the particles already in that "
                  "order (what a caller who keeps them sorted gives it), against the floor.", ""]
        lines += md_table(
            ["d", "N", "random order in", "AR / floor", "cell order in", "AR / floor", "AR (input order out) / floor"],
            [[str(r["d"]), f"{r['n']:,}", seconds(r["ar_cells"]), f"{r['ar_cells'] / r['floor']:.1f}",
              seconds(r["ar_cells_sorted"]), f"{r['ar_cells_sorted'] / r['floor']:.1f}",
              f"{r['ar_total'] / r['floor']:.1f}"] for r in rows])
    lines += ["", "Where the AR list's time goes, in multiples of the floor: the tree (build), the pairs "
              "(search: tree + pairs in the tree's order, less the tree), and the hand-off into arrays in particle "
              "order with the Python around it (total less search).", ""]
    lines += md_table(
        ["d", "N", "build", "pairs", "hand-off", "total", "cache order: build", "pairs", "hand-off", "total"],
        [[str(r["d"]), f"{r['n']:,}"]
         + [f"{v / r['floor']:.1f}" for tag in ("", "_cache_order")
            for v in (r["ar_build" + tag], r["ar_search" + tag] - r["ar_build" + tag],
                      r["ar_total" + tag] - r["ar_search" + tag], r["ar_total" + tag])]
         for r in rows])
    lines += ["", "### Findings", ""]
    for d in sorted({r["d"] for r in rows}):
        dr = [r for r in rows if r["d"] == d]
        q = [r[f"ar_total{tag}"] / r[f"uniform_total{tag}"] for r in dr for tag in ("", "_cache_order")]
        worst = dr[int(np.argmax(q)) // 2]
        lines.append(f"- {d}D: AR / uniform is {min(q):.2f} to {max(q):.2f} (the largest at N = {worst['n']:,}; "
                     f"target 1.15: {'met' if max(q) <= 1.15 else 'not met'}). The fitted cells make "
                     f"{min(r['checks'] for r in dr):.1f} to {max(r['checks'] for r in dr):.1f} checks per particle, "
                     f"the paper's root {min(r['paper_checks'] for r in dr):.1f} to "
                     f"{max(r['paper_checks'] for r in dr):.1f}.")
    big = [r for r in rows if r["d"] == 2 and r["n"] == max(x["n"] for x in rows if x["d"] == 2)]
    if big:
        r = big[0]
        lines.append(f"- At N = {r['n']:,} (2D) the AR list takes {r['ar_total'] / r['floor']:.1f} times the floor "
                     f"on input in random order, {r['ar_total_cache_order'] / r['floor']:.1f} times in cache order "
                     f"(target 6: {'met' if r['ar_total'] / r['floor'] <= 6 else 'not met'}); the tree alone takes "
                     f"{r['ar_build'] / r['floor']:.1f} and {r['ar_build_cache_order'] / r['floor']:.1f} times. "
                     f"Against a copy into reused memory the list takes {r['ar_total'] / r['floor_warm']:.1f} and "
                     f"{r['ar_total_cache_order'] / r['floor_warm']:.1f} times.")
        if "ar_cells" in r:
            lines.append(f"- In the search's cell order (no pass back to input order) the same list takes "
                         f"{r['ar_cells'] / r['floor']:.1f} times the floor on input in random order, and "
                         f"{r['ar_cells_sorted'] / r['floor']:.1f} times on input already in that order "
                         f"({seconds(r['ar_cells_sorted'])}).")
        if "ar_total_small_pages" in r:
            q = [x["ar_total_small_pages"] / x["ar_total"] for x in rows]
            lines.append(
                f"- Huge pages: with the advice off (`arpy.set_huge_pages(False)`) the AR list takes {min(q):.2f} to "
                f"{max(q):.2f} times as long over the sweep; at N = {r['n']:,} (2D) "
                f"{seconds(r['ar_total_small_pages'])} against {seconds(r['ar_total'])}. Page faults of the second "
                f"of two calls in a row: "
                f"{r['faults_per_particle'] * r['n']:,.0f}, and {r['faults_per_particle_small_pages'] * r['n']:,.0f} "
                f"with the advice off"
                + (" (glibc hands the calls the memory the calls before freed)."
                   if r["faults_per_particle"] == 0 else "."))
        kept = meta.get("malloc_kept")
        if kept:
            env = " ".join(f"{k}={v}" for k, v in kept["env"].items())
            lines.append(
                f"- In a process started with `{env}` (glibc keeps all the memory the calls free) the same lists "
                f"take {seconds(kept['ar'])} (AR, {kept['ar'] / r['floor']:.1f} times the floor) and "
                f"{seconds(kept['uniform'])} (uniform), against {seconds(r['ar_total'])} and "
                f"{seconds(r['uniform_total'])} here.")
    return lines


def report(res: dict) -> str:
    """The Markdown page of a result (results/ar_cell_lists.md is this of results/ar_cell_lists.json)."""
    meta, summary, fig6, fig7 = res["meta"], res["summary"], res["fig6"], res["fig7"]
    stem = "ar_cell_lists" + ("_quick" if meta.get("quick") else "")
    fig7 = sorted(fig7, key=lambda r: r["lam"])
    by_lam = {r["lam"]: r for r in fig7}
    n7 = fig7[0]["n"]
    lams6 = sorted({r["lam"] for r in fig6})
    sizes6 = sorted({r["n"] for r in fig6})
    est = lambda r: "~" if r["uniform_estimated"] else ""        # noqa: E731
    lines = [
        "# AR cell lists against uniform cell lists and cKDTree (AR paper, Figs. 6 and 7)",
        "",
        "Awile et al. (2012), Sec. 3.1: the cost of building cell lists and the symmetric Verlet list from them, "
        "for adaptive-resolution (AR) and conventional (uniform) cell lists, against the number of particles N "
        "(Fig. 6) and the resolution span lambda (Fig. 7).",
        "",
        "    python benchmarks/ar_cell_lists.py           # the sizes below",
        "    python benchmarks/ar_cell_lists.py --quick   # N up to 1e4 and five values of lambda, one run each, "
        "in seconds",
        "",
        "## Set-up",
        "",
        "The paper's distribution (`arpy.ar_benchmark`): 10 x 10 large particles (cutoff 0.15) and N small ones "
        "(cutoff 0.15 / lambda) on Cartesian meshes side by side, every particle with 8 neighbours. "
        f"Fig. 6: lambda = {', '.join(f'{v:g}' for v in lams6)} and {sizes6[0]:,} to {sizes6[-1]:,} particles; "
        f"Fig. 7: N = {n7:,} and lambda = {', '.join(format(r['lam'], 'g') for r in fig7)}. "
        f"Each time is the best of {meta['repeat']} runs.",
        "",
        "- AR build: the AR tree alone (Algorithms 1-2); AR total: tree + symmetric Verlet list (Algorithm 3), "
        "`neighbor_list(x, rc, method=\"ar\")`.",
        "- uniform build: the uniform cell grid alone; uniform total: grid + symmetric list, "
        "`neighbor_list(x, rc, method=\"cell\")`.",
        "- cKDTree: the faster of `query_ball_point` (each particle's own radius) and `query_pairs` (largest "
        "radius), both followed by the min-rule filter.",
    ]
    if summary.get("ns_per_check_uniform"):
        lines.append(
            "- ~: a uniform run that would take minutes (its cells are sized by the largest cutoff and hold most "
            "of the small particles) is not run; its time is the uniform build plus the exact number of distance "
            f"checks it would make times the measured cost per check ({summary['ns_per_check_uniform']:.2f} ns).")

    lines += ["", f"## Fig. 7: N = {n7:,}, lambda from {fig7[0]['lam']:g} to {fig7[-1]['lam']:g}", ""]
    lines += md_table(
        ["lambda", "AR build", "AR total", "uniform build", "uniform total", "uniform / AR", "cKDTree",
         "cKDTree / AR", "AR ns per particle", "AR peak bytes per particle"],
        [[f"{r['lam']:g}", seconds(r["ar_build"]), seconds(r["ar_total"]), seconds(r["uniform_build"]),
          est(r) + seconds(r["uniform_total"]), est(r) + ratio(r["uniform_total"] / r["ar_total"]),
          seconds(r["kd_best"]), ratio(r["kd_best"] / r["ar_total"]), f"{r['ar_ns_per_particle']:.0f}",
          "-" if r.get("ar_peak_bytes_per_particle") is None else f"{r['ar_peak_bytes_per_particle']:.0f}"]
         for r in fig7])

    table6 = []
    for lam in lams6:
        rows = sorted((r for r in fig6 if r["lam"] == lam), key=lambda r: r["n"])
        for prev, r in zip([None] + rows[:-1], rows):
            grow = (["-", "-"] if prev is None else
                    [f"{exponent(prev, r, 'uniform_total'):.2f}", f"{exponent(prev, r, 'ar_total'):.2f}"])
            table6.append([f"{lam:g}", f"{r['n']:,}", seconds(r["ar_build"]), seconds(r["ar_total"]),
                           seconds(r["uniform_build"]), est(r) + seconds(r["uniform_total"]),
                           est(r) + ratio(r["uniform_total"] / r["ar_total"]), seconds(r["kd_best"])] + grow)
    lines += ["", "## Fig. 6: time against N", "",
              "Growth exponent: log(t / t') / log(N / N') against the row above (1: linear in N, 2: quadratic).",
              ""]
    lines += md_table(["lambda", "N", "AR build", "AR total", "uniform build", "uniform total", "uniform / AR",
                       "cKDTree", "growth exponent, uniform total", "growth exponent, AR total"], table6)

    # ---- arpy's figures for the paper's statements
    build = [r["ar_build"] / r["uniform_build"] for r in fig7]
    ours = {"build": f"{ratio(min(build))} to {ratio(max(build))}"}
    if 1.0 in by_lam:
        ours["lam1"] = ratio(by_lam[1.0]["ar_total"] / by_lam[1.0]["uniform_total"])
    be = summary.get("break_even_lambda")
    ours["break_even"] = "never" if be is None else f"{be:.2f}"
    for key, lam in (("lam10", 10.0), ("lam1000", 1000.0)):
        if lam in by_lam:
            r = by_lam[lam]
            ours[key] = (est(r) + ratio(r["uniform_total"] / r["ar_total"])
                         + (f" (N = {n7:,})" if key == "lam1000" else ""))
    top = max(r["uniform_total"] for r in fig7)
    flat = [r["lam"] for r in fig7 if r["uniform_total"] >= 0.99 * top]
    if len(flat) > 1 and flat == [r["lam"] for r in fig7][-len(flat):]:
        ours["plateau"] = f"at lambda = {flat[0]:g} (from the counted distance checks)"
    else:
        ours["plateau"] = f"still growing at lambda = {fig7[-1]['lam']:g}"
    lines += ["", "## Against the paper", ""]
    lines += md_table(["", "paper", "arpy"], [[what, words, ours.get(key, "-")]
                                               for key, (what, words, _) in PAPER.items()])

    lines += lam1_section(res)
    ar_ns = [r["ar_ns_per_particle"] for r in fig7]
    mem = [r["ar_peak_bytes_per_particle"] for r in fig7 if r.get("ar_peak_bytes_per_particle") is not None]
    kd = [r["kd_best"] / r["ar_total"] for r in fig7]
    lines += ["", "## Findings", ""]
    lines.append("- " + ("Every method found the same pairs in every run." if all(r["same_pairs"] for r in fig6 + fig7)
                         else "Some methods found different pairs: see the JSON (same_pairs)."))
    if "lam1" in ours:
        lam1 = by_lam[1.0]["ar_total"] / by_lam[1.0]["uniform_total"]
        lam1_6 = [r["ar_total"] / r["uniform_total"] for r in fig6 if r["lam"] == 1.0]
        lines.append(
            f"- Break-even: arpy's AR lists catch up with the uniform ones at lambda = {ours['break_even']} "
            f"(paper: {PAPER['break_even'][2]:g})" + (", because" if lam1 < PAPER["lam1"][2] else ";")
            + f" at lambda = 1 they cost {ours['lam1']} times the uniform list (paper: {PAPER['lam1'][2]:g})"
            + (f"; at the Fig. 6 sizes this ratio is {ratio(min(lam1_6))} to {ratio(max(lam1_6))}" if lam1_6 else "")
            + ". At lambda = 1 the AR tree has one level, a uniform grid of cell edge D_m / 2^k, and its pairs come "
            "from the uniform list's own loop. What remains is the build (the level pass and the ancestor flags) "
            + ("and the cell size: the root fitted to the smallest cutoff makes it r_c (see the lambda = 1 sweep)."
               if meta.get("root") == "fitted" else
               "and the cell size, which in this run (D_m = the extent, before the root was fitted to the "
               "smallest cutoff) the power-of-two levels put between r_c and 2 r_c depending on N.")
            + (" The ratio is close to 1, so the break-even moves noticeably between runs." if lam1 < 1.25 else ""))
    lines.append(
        f"- The AR build costs {ours['build']} times the uniform build (paper: about "
        f"{PAPER['build'][2]:g} times). Dense levels (every level of this benchmark) keep their cells in a plain "
        "array filled by one counting sort in row-major order, as the uniform list does, so a cell's forward "
        "neighbours are 2 contiguous slot ranges in 2D (5 in 3D); sparse levels use Algorithm 2 and the hash table.")
    lines.append(
        f"- The AR total is flat in lambda, as in the paper: {min(ar_ns):.0f} to {max(ar_ns):.0f} ns per particle "
        f"from lambda = {fig7[0]['lam']:g} to {fig7[-1]['lam']:g}"
        + (f", with a peak memory of {min(mem):.0f} to {max(mem):.0f} bytes per particle." if mem else "."))
    lines.append(
        "- Against N (Fig. 6) the paper's conventional lists grow first as N^2, then as N past a saturation point "
        "that moves to larger N with lambda. The growth exponents of arpy's uniform total: "
        + "; ".join(f"lambda = {lam:g}: " + ", ".join(r[-2] for r in table6 if r[0] == f"{lam:g}" and r[-2] != "-")
                    for lam in lams6) + ".")
    lines.append(f"- cKDTree (the faster of its two queries) takes {ratio(min(kd))} to {ratio(max(kd))} times as "
                 "long as the AR lists.")
    lines += ["", f"![Fig. 6: time against N for each lambda]({stem}_fig6.png)", "",
              f"![Fig. 7: time against lambda at N = {n7:,}, and the speed-up of the AR lists]({stem}_fig7.png)", "",
              f"Run of {meta['date']} on {meta['machine']}, Python {meta['python']}, NumPy {meta['numpy']}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    def extra(parser):
        parser.add_argument("--repeat", type=int, default=3, help="timing repeats; the best is reported")
        parser.add_argument("--no-memory", action="store_true", help="skip the peak-memory subprocesses")
        parser.add_argument("--only", choices=("lam1",), help="run only the lambda = 1 sweep and merge it into "
                            "the existing JSON")

    args = benchmark_args(__doc__, argv, HERE / "results", extra)
    stem = "ar_cell_lists" + ("_quick" if args.quick else "")
    lam1_sizes = [2_000, 8_000] if args.quick else [50_000, 100_000, 200_000, 400_000, 1_000_000]
    print("lambda = 1: AR and uniform lists (build + symmetric list), the floor (a copy of the list)")
    print(f"{'d':>2s} {'N':>9s} | {'AR':>9s} {'uniform':>9s} {'AR/uni':>7s} | {'floor':>8s} {'AR/floor':>8s} | "
          f"{'AR, cache order':>15s} | {'edge/rc':>7s} {'paper':>6s} | {'checks':>7s} {'paper':>7s}")
    lam1 = []
    for d in (2, 3):
        for n_small in lam1_sizes:
            # at least 5 runs, and about 4e6 particles' worth at small N (the ratios are noisy there)
            r = lam1_row(d, n_small, max(args.repeat, 5, 4_000_000 // n_small) if not args.quick else 1)
            lam1.append(r)
            print(f"{d:2d} {r['n']:9d} | {1e3 * r['ar_total']:9.2f} {1e3 * r['uniform_total']:9.2f} "
                  f"{r['ar_total'] / r['uniform_total']:7.2f} | {1e3 * r['floor']:8.2f} "
                  f"{r['ar_total'] / r['floor']:8.1f} | {1e3 * r['ar_total_cache_order']:15.2f} | "
                  f"{r['edge_over_rc']:7.3f} {r['paper_edge_over_rc']:6.3f} | {r['checks']:7.1f} "
                  f"{r['paper_checks']:7.1f}")
    kept = malloc_kept(2, lam1_sizes[-1], max(args.repeat, 5) if not args.quick else 1)
    lam1_meta = {"date": time.strftime("%Y-%m-%d"), "threads": arpy.get_num_threads(), "malloc_kept": kept,
                 "repeat": f"{max(args.repeat, 5)} (N = 1e6) to {max(args.repeat, 5, 4_000_000 // lam1_sizes[0])}"
                 if not args.quick else 1}
    if args.only == "lam1":
        path = args.out / f"{stem}.json"
        result = json.loads(path.read_text())
        result.update(lam1=lam1, lam1_meta=lam1_meta)
        path.write_text(json.dumps(result, indent=1))
        write_page(args.out, stem, report)
        print(f"\nmerged lam1 into {path} and wrote {stem}.md")
        return 0
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

    be = break_even(fig7)
    by_lam = {r["lam"]: r for r in fig7}
    summary = {
        "break_even_lambda": be,
        "uniform_over_ar": {str(r["lam"]): r["uniform_total"] / r["ar_total"] for r in fig7},
        "kd_over_ar": {str(r["lam"]): r["kd_best"] / r["ar_total"] for r in fig7},
        "ns_per_check_uniform": float(np.median(ns_per_check)) if ns_per_check else None,
    }
    meta = {"python": sys.version.split()[0], "numpy": np.__version__, "machine": platform.machine(),
            "date": time.strftime("%Y-%m-%d"), "repeat": repeat, "quick": args.quick, "root": "fitted"}
    (args.out / f"{stem}.json").write_text(json.dumps({"meta": meta, "summary": summary, "fig6": fig6,
                                                        "fig7": fig7, "lam1": lam1, "lam1_meta": lam1_meta},
                                                       indent=1))
    write_page(args.out, stem, report)
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
    print(f"wrote {args.out / (stem + '.json')}, {stem}.md, {stem}_fig6.png, {stem}_fig7.png")
    return 0 if all(r["same_pairs"] for r in fig6 + fig7) else 1


if __name__ == "__main__":
    sys.exit(main())
