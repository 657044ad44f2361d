"""Benchmark: the AR paper's Verlet-list options against arpy's defaults (Awile et al. 2012, Alg. 3, §2.4).

* **Algorithm 3's asymmetric branch**: the full list built directly, each particle searching its
  neighbours from the root (``verlet_list(full=True, direct=True)``), against the half
  list expanded into both rows (``full=True``, arpy's default) and the half list itself;
* **the ghost-ghost filter** (§2.4): a subdomain (the unit square or cube of a periodic box of edge
  2 along x; random particles, cutoffs log-uniform over a span of 1 and 10) with halo layers on its
  upper faces, every particle within its own cutoff beyond a face a ghost; the symmetric list with
  and without ``ghost_bits`` (:func:`arpy.lists.ar.halo_bits`): the pairs it drops and the time it takes.

Full lists on the paper's benchmark distribution (``arpy.distributions.ar_benchmark``) at λ = 1 and
100; times are the best of ``repeat`` runs (full lists: tree build + list; the filter: the list of a
built tree) on this machine's threads.  Writes
JSON and the Markdown page (results/verlet_options.md, see report()) into --out.

    python benchmarks/verlet_options.py            # about a minute
    python benchmarks/verlet_options.py --quick    # seconds (used by the tests)
"""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

import numpy as np

import arpy
from arpy._bench import benchmark_args, best_time, md_table, run_info, write_page, write_result
from arpy.lists.ar import halo_bits
from arpy.distributions import ar_benchmark

HERE = Path(__file__).resolve().parent
FULL = dict(n_small={2: 200_000, 3: 60_000}, lams=[1.0, 100.0], n_box={2: 400_000, 3: 200_000}, spans=[1.0, 10.0],
            repeat=5)
QUICK = dict(n_small={2: 5_000, 3: 3_000}, lams=[1.0, 100.0], n_box={2: 8_000, 3: 6_000}, spans=[1.0, 10.0], repeat=1)


def full_lists(d: int, n_small: int, lam: float, repeat: int) -> dict:
    """Tree build + symmetric list, + the expanded full list, + the direct full list (seconds)."""
    x, rc = ar_benchmark(n_small, lam, d)

    def build(**kw):
        return arpy.ARCellList(x, rc).verlet_list(**kw)

    t_sym, sym = best_time(lambda: build(), repeat)
    t_exp, exp = best_time(lambda: build(full=True), repeat)
    t_dir, dr = best_time(lambda: build(full=True, direct=True), repeat)
    same = bool(np.array_equal(np.stack(exp.canonical().pairs()), np.stack(dr.canonical().pairs())))
    return dict(d=d, lam=lam, n=int(x.shape[0]), pairs=int(sym.indices.size), symmetric_s=t_sym, expanded_s=t_exp,
                direct_s=t_dir, same_rows=same)


def subdomain(d: int, n: int, lam: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """n random particles in a periodic box [0, 2) x [0, 1)^(d-1), cutoffs log-uniform over a span lam
    (the finest holding about 12 neighbours at this density), and the subdomain [0, 1)^d with its ghosts
    on the upper faces: (x, rc, lo, hi) of its particles and ghosts."""
    rng = np.random.default_rng(d)
    edge = np.array([2.0] + [1.0] * (d - 1))
    x = rng.random((n, d)) * edge
    ball = np.pi if d == 2 else 4 * np.pi / 3
    r_min = (12 * 2.0 / (n * ball)) ** (1 / d)
    rc = r_min * lam ** rng.random(n)
    shifts = np.array(list(itertools.product((0.0, 1.0), repeat=d))) * edge
    xi, ri = (x[None] + shifts[:, None]).reshape(-1, d), np.tile(rc, len(shifts))
    lo, hi = np.zeros(d), np.ones(d)
    keep = np.all((xi >= lo) & (xi < hi + ri[:, None]), axis=1)
    return xi[keep], ri[keep], lo, hi


def ghost_filter(d: int, n: int, lam: float, repeat: int) -> dict:
    x, rc, lo, hi = subdomain(d, n, lam)
    bits = halo_bits(x, lo, hi)
    tree = arpy.ARCellList(x, rc, domain=arpy.Domain(np.stack([lo, hi + rc.max()])))
    t_all, every = best_time(lambda: tree.verlet_list(), repeat)
    t_filt, kept = best_time(lambda: tree.verlet_list(ghost_bits=bits), repeat)
    rows = every.rows()
    ghost_pairs = int(np.sum((bits[rows] != 0) & (bits[every.indices] != 0)))
    return dict(d=d, lam=lam, n=int(x.shape[0]), ghosts=int(np.count_nonzero(bits)), pairs=int(every.indices.size),
                ghost_ghost_pairs=ghost_pairs, kept_pairs=int(kept.indices.size), list_s=t_all, filtered_s=t_filt)


def report(res: dict) -> str:
    """The Markdown page of a result (results/verlet_options.md is this of results/verlet_options.json)."""
    tag = "verlet_options_quick" if res.get("quick") else "verlet_options"
    lines = ["# The AR paper's Verlet-list options: Algorithm 3's asymmetric branch and the ghost–ghost filter", ""]
    if res.get("quick"):
        lines += ["**Quick run** (small sizes, for the tests).", ""]
    lines += [f"`python benchmarks/verlet_options.py` writes `verlet_options.json` and this page into "
              f"`benchmarks/results/`; `--quick` writes `{tag}.*` at small sizes. The paper's benchmark "
              f"distribution; best of {res['repeat']} runs of tree build + list, {res['threads']} threads.", "",
              "## Full lists: expanded from the symmetric list, or built directly", ""]
    lines += md_table(["d", "λ", "N", "pairs", "symmetric", "full, expanded", "full, direct", "direct / expanded",
                       "same rows"],
                      [[str(r["d"]), f"{r['lam']:g}", f"{r['n']:,}", f"{r['pairs']:,}", f"{r['symmetric_s']:.3f} s",
                        f"{r['expanded_s']:.3f} s", f"{r['direct_s']:.3f} s", f"{r['direct_s'] / r['expanded_s']:.2f}",
                        "yes" if r["same_rows"] else "no"] for r in res["full"]])
    ratios = [r["direct_s"] / r["expanded_s"] for r in res["full"]]
    lines += ["", f"- The direct branch takes {min(ratios):.2f}–{max(ratios):.2f} times the expansion's time: it "
              "tests every pair from both sides and searches each particle's coarser levels, where the expansion "
              "writes each pair found once into both rows. The expansion stays the default."
              if min(ratios) > 1 else f"- direct / expanded: {min(ratios):.2f}–{max(ratios):.2f}.", "",
              "## The ghost–ghost filter (§2.4)", "",
              "A subdomain [0, 1)^d of a periodic box of edge 2 along x (random particles, cutoffs log-uniform "
              "over the span given), halo layers on its upper faces (the particles and periodic images within "
              "their own cutoff beyond a face). Ghost–ghost pairs: the symmetric list's pairs of two ghosts; the "
              "filter keeps those in different halos.", ""]
    lines += md_table(["d", "span", "particles + ghosts", "ghosts", "pairs", "ghost–ghost pairs", "pairs kept",
                       "list", "list + filter"],
                      [[str(r["d"]), f"{r['lam']:g}", f"{r['n']:,}", f"{r['ghosts']:,}", f"{r['pairs']:,}",
                        f"{r['ghost_ghost_pairs']:,}", f"{r['kept_pairs']:,}", f"{r['list_s']:.3f} s",
                        f"{r['filtered_s']:.3f} s"] for r in res["ghosts"]])
    drop = [1 - r["kept_pairs"] / r["pairs"] for r in res["ghosts"]]
    lines += ["", f"- The filter drops {100 * min(drop):.1f}–{100 * max(drop):.1f} % of the subdomain's pairs (those "
              "another subdomain computes); its pass over the list adds "
              + ", ".join(f"{100 * (r['filtered_s'] / r['list_s'] - 1):+.0f} %" for r in res["ghosts"])
              + " to the build (timing noise included).", "",
              f"Run on {res['machine']} with Python {res['python']}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = benchmark_args(__doc__, argv, HERE / "results")
    tag = "verlet_options_quick" if args.quick else "verlet_options"
    p = QUICK if args.quick else FULL
    full, ghosts = [], []
    for d in (2, 3):
        for lam in p["lams"]:
            full.append(full_lists(d, p["n_small"][d], lam, p["repeat"]))
            f = full[-1]
            print(f"d = {d}, lambda = {lam:g}: N {f['n']}, symmetric {f['symmetric_s']:.3f} s, expanded "
                  f"{f['expanded_s']:.3f} s, direct {f['direct_s']:.3f} s")
        for span in p["spans"]:
            ghosts.append(ghost_filter(d, p["n_box"][d], span, p["repeat"]))
            g = ghosts[-1]
            print(f"d = {d}, span {span:g}: subdomain {g['n']} with {g['ghosts']} ghosts: {g['pairs']} pairs, "
                  f"{g['pairs'] - g['kept_pairs']} dropped, {g['list_s']:.3f} s -> {g['filtered_s']:.3f} s")
    result = dict(**run_info(), quick=args.quick, threads=arpy.get_num_threads(), repeat=p["repeat"], full=full,
                  ghosts=ghosts)
    write_result(args.out, tag, result, "", gap=False)
    print(f"wrote {write_page(args.out, tag, report)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
