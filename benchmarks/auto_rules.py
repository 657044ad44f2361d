"""Benchmark: what ``method="auto"`` chooses under the max and sum cutoff rules.

Under the max rule (SPH: |x_p - x_q| <= max(h_p, h_q)) and the sum rule (contacts: <= r_p + r_q) the
AR list finds a pair from its finer particle, which searches its own level's half stencil and the
full 3^d stencil around its cell on every coarser level that holds particles; the uniform list's
cells are as wide as the largest reach (under the sum rule twice the largest radius).  ``auto``
estimates both times with the statistics and costs of the min rule (``benchmarks/auto_calibration.py``)
except the AR list's search towards the coarse side: ``W_coarse``, the coarser levels' particles in
those stencils, and ``W_up``, the stencil cells looked up there (:func:`arpy.lists.auto.auto_work`),
whose two costs this benchmark fits (``--fit``).

The sets: uniform positions in the unit box, radii of three kinds, scaled so that a particle has on
average 6 contacts (sum rule) or 16 neighbours (max rule), boundary effects aside:

  loguniform   radii log-uniform over a factor span
  bimodal5     5 % of the radii span times the others
  lognormal    radii log-normal with standard deviation ln(span) / 4.6 of their logarithm (about 98 %
               of them within a factor span): a few very large ones, as in granular piles

Spans 1 (loguniform only: one radius) to 1000, d = 2 and 3, N = 1e4 to 1e6, each at 1 and 2 threads.
The costs are fitted on the loguniform and bimodal5 sets; the lognormal sets test them.  The timing
is that of ``benchmarks/auto_calibration.py`` (methods interleaved, minimum over the repeats; a uniform
list of more than ``MAX_CHECKS`` checks is estimated, unless auto picks it).

    python benchmarks/auto_rules.py            # the sizes above (about 20 minutes)
    python benchmarks/auto_rules.py --quick    # N = 2000 (seconds; tests)
    python benchmarks/auto_rules.py --fit      # the costs that fit the JSON's times

Results: ``results/auto_rules.json`` and ``results/auto_rules.md`` (generated from the JSON by
:func:`report`).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

import arpy
from arpy._bench import benchmark_args, md_table, run_info, write_page, write_result
from arpy.lists.auto import AUTO_AR_COST, AUTO_AR_WORK, AUTO_CELL_COST

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from auto_calibration import (MAX_CHECKS, TOLERANCE, choice_slowdown, cost_slowdown,  # noqa: E402  (a sibling
                              estimate_skipped, fit_rest, measure, refit_choices,     # script)
                              sampling, slowdown)

#: Mean number of neighbours per particle of the sets, by rule.
NEIGHBOURS = {"sum": 6.0, "max": 16.0}
KINDS = ("loguniform", "bimodal5", "lognormal")
#: The kinds the two costs of the search towards the coarse side are fitted on; the lognormal sets test them.
FIT_KINDS = ("loguniform", "bimodal5")
FULL = dict(sizes=(10_000, 100_000, 1_000_000), spans=(1.0, 10.0, 100.0, 1000.0),
            repeat={10_000: 5, 100_000: 3, 1_000_000: 1}, threads=(1, 2))
QUICK = dict(sizes=(2_000,), spans=(1.0, 100.0), repeat={2_000: 1}, threads=(1, 2))


def radii(kind: str, n: int, span: float, rng: np.random.Generator) -> np.ndarray:
    """n radii of the kind (see the module's notes), the smallest of their scale about 1."""
    if kind == "loguniform":
        return np.exp(rng.uniform(0.0, np.log(span), n))
    if kind == "bimodal5":
        return np.where(rng.random(n) < 0.05, span, 1.0)
    if kind == "lognormal":
        return np.exp(rng.normal(0.0, np.log(span) / 4.6, n))
    raise ValueError(f"unknown kind {kind!r}")


def rule_set(rule: str, kind: str, d: int, n: int, span: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Uniform positions in [0, 1]^d and radii of the kind, scaled so that a particle has NEIGHBOURS[rule]
    neighbours under ``rule`` on average: the mean over pairs of the ball of the pair's reach (the sum rule:
    E[(r_p + r_q)^d] expanded in the radii's moments; the max rule: the i-th smallest radius is the larger
    one of i pairs) times n - 1."""
    rng = np.random.default_rng(seed)
    x = rng.random((n, d))
    r = radii(kind, n, span, rng)
    m = [float(np.mean(r ** k)) for k in range(4)]
    if rule == "sum":
        mean = 2.0 * m[2] + 2.0 * m[1] ** 2 if d == 2 else 2.0 * m[3] + 6.0 * m[2] * m[1]
    else:
        mean = float(np.sum(np.sort(r) ** d * np.arange(n))) / (n * (n - 1) / 2.0)
    ball = np.pi if d == 2 else 4.0 * np.pi / 3.0
    return x, r * (NEIGHBOURS[rule] / ((n - 1) * ball * mean)) ** (1.0 / d)


def fit(rows: list[dict], ar: dict = AUTO_AR_COST) -> dict:
    """``ar`` with the costs of the search towards the coarse side ("coarse" per check, "up" per stencil cell
    looked up) fitted on FIT_KINDS' rows (:func:`auto_calibration.fit_rest`)."""
    return fit_rest([r for r in rows if r["kind"] in FIT_KINDS], ar, ("coarse", "up"), lambda r: r["terms"][2:4])


def within(rows: list[dict], picks: list[str], t: int, clock: str) -> tuple[int, float]:
    """(how many of the picked lists are within TOLERANCE of the faster one at t threads, the worst ratio)."""
    ratios = [choice_slowdown(dict(r, choice=p), t, clock) for r, p in zip(rows, picks)]
    return sum(v <= TOLERANCE for v in ratios), max(ratios)


def report(res: dict) -> str:
    """The Markdown page of a result (``results/auto_rules.md`` is this of its JSON)."""
    meta, rows = res["meta"], res["rows"]
    threads = meta["threads"]
    ar = meta["ar_cost"]
    refit = fit(rows)
    lines = ["# method=\"auto\" under the max and sum rules", "",
             "`neighbor_list(x, rc, method=\"auto\", rule=...)` estimates the time of the uniform and of the AR "
             "list (`arpy.lists.auto.auto_work`) and picks the AR list when `T_cell > "
             f"{meta['auto_ar_work']:g} T_ar`. Under the max and sum rules the AR list finds a pair from its finer "
             "particle: its own level's half stencil, then the full 3^d stencil around its cell on every coarser "
             "level that holds particles. Its model is the min rule's (`benchmarks/results/auto_calibration.md`) "
             "with the search towards the fine side replaced: `T_ar = C_d N + E_own W_own + E_coarse W_coarse + "
             "E_up W_up + (the tree's tables)`, `W_coarse = N mean_s f_s sum_j occ(c_j, N_j)` over the coarser "
             "levels j holding particles (their numbers N_j counted over every particle: a few large radii make "
             "a level every particle searches) and `W_up = N mean_s 3^d` (the number of those levels). A "
             "particle's level is that of its level reach, r + skin (max rule) or 2 r + skin (sum rule), and the "
             "uniform list's cells are as wide as the largest reach.", "",
             "    python benchmarks/auto_rules.py            # this page",
             "    python benchmarks/auto_rules.py --quick    # N = 2000, seconds",
             "    python benchmarks/auto_rules.py --fit      # the costs that fit the JSON's times", "",
             f"Costs in use (ns): `E_coarse` = {ar['coarse']:.2f} per check, `E_up` = {ar['up']:.2f} per stencil "
             "cell looked up, fitted (`--fit`: least squares on the relative errors, both >= 0) on the 1-thread CPU "
             "times of the AR lists of the log-uniform and bimodal sets of a first run at N = 1e4 and 1e5, on what "
             "the min rule's costs (unchanged) leave of them; the log-normal sets were not in the fit. Refitted on "
             f"this run's times: {refit['coarse']:.2f} and {refit['up']:.2f}, with which auto would pick the same "
             f"list on {sum(a == r['choice'] for a, r in zip(refit_choices(rows, AUTO_CELL_COST, refit), rows))} of {len(rows)} sets.", "",
             f"Sets: uniform positions in the unit box, {NEIGHBOURS['sum']:g} contacts per particle (sum rule) or "
             f"{NEIGHBOURS['max']:g} neighbours (max rule) on average; radii `loguniform` over a factor span, "
             "`bimodal5` (5 % of them span times the others) and `lognormal` (the logarithm's standard deviation "
             "ln(span) / 4.6: a few very large radii). A uniform list of more than "
             f"{meta['max_checks']:.0e} checks is estimated from its counted checks (marked ~) unless auto picks "
             "it. Times are minima over the repeats (by N: "
             + ", ".join(f"{int(k):,}: {v}" for k, v in meta["repeat"].items()) + ").", "",
             "## Summary", "",
             "The list auto chose against the faster of the two (1 thread: CPU time; more: wall time), and the "
             "same for auto's former fixed choice, the uniform list:", ""]
    table = []
    for rule in ("sum", "max"):
        for label, group in (("all", KINDS), ("fitted kinds", FIT_KINDS), ("lognormal (held out)", ("lognormal",))):
            sel = [r for r in rows if r["rule"] == rule and r["kind"] in group]
            if not sel:
                continue
            cells = []
            for t in threads:
                clock = "cpu" if t == 1 else "wall"
                ok, worst = within(sel, [r["choice"] for r in sel], t, clock)
                cells.append(f"{ok}/{len(sel)}, worst {worst:.2f}")
                if t == threads[0]:
                    ok0, worst0 = within(sel, ["cell"] * len(sel), t, clock)
                    costs = [cost_slowdown(r, t, clock) for r in sel]
                    cells += [f"{sum(c <= TOLERANCE for c in costs)}/{len(sel)}, worst {max(costs):.2f}",
                              f"{ok0}/{len(sel)}, worst {worst0:.2f}"]
            table.append([rule, label] + cells)
    header = ["rule", "sets", f"chosen list within {TOLERANCE:g}x, {threads[0]} thread",
              "chosen list + statistics", "the uniform list always (before)"]
    header += [f"chosen list, {t} threads" for t in threads[1:]]
    lines += md_table(header, table)
    ran = {rule: [choice_slowdown(dict(r, choice="cell"), threads[0], "cpu" if threads[0] == 1 else "wall")
                  for r in rows if r["rule"] == rule and not r[f"t{threads[0]}"]["cell_estimated"]] for rule in ("sum", "max")}
    lines += ["", "Where the uniform list was not run (marked ~ below) its time is estimated from its checks, and the "
              "worst slowdowns of always taking it include those estimates; among the sets where it ran, its worst is "
              + " and ".join(f"{max(v):.1f}x under the {rule} rule" for rule, v in ran.items() if v) + "."]
    lines += ["", "## Every set", "",
              f"Times in ms at {threads[0]} thread (CPU); `ar/cell` is the AR list's time over the uniform list's "
              "(below 1: the AR list is faster); the model's ratio likewise.", ""]
    body = []
    for r in rows:
        m = r["t1"]["cpu"]
        est = "~" if r["t1"]["cell_estimated"] else ""
        body.append([r["rule"], r["kind"], r["d"], f"{r['n']:,}", f"{r['span']:g}", f"{2 * r['pairs'] / r['n']:.1f}",
                     f"{est}{1e3 * m['cell']:.3g}", f"{1e3 * m['ar']:.3g}", f"{m['ar'] / m['cell']:.2f}",
                     f"{r['model_ar'] / r['model_cell']:.2f}", r["choice"], f"{1e3 * r['t1']['terms_cpu']:.3g}",
                     f"{choice_slowdown(r, 1, 'cpu'):.2f}", f"{slowdown(r, 1, 'cpu'):.2f}"])
    lines += md_table(["rule", "radii", "d", "N", "span", "neighbours", "cell (ms)", "ar (ms)", "ar/cell",
                       "model ar/cell", "auto picks", "statistics (ms)", "chosen / faster", "auto / faster"], body)
    lines.append("")
    for m in meta.get("remeasured", []):
        lines.append(f"- Measured again on {m['date']} with {m['repeat']} repeats (their rows above are of that "
                     f"run): {', '.join(m['sets'])}.")
    lines.append("- Every method found the same rows (row lengths compared) in every run." if all(
        r[f"t{t}"]["same_rows"] for r in rows for t in threads) else "- Some rows differ: see the JSON.")
    lines += ["", f"Run of {meta['date']} on {res['machine']}, Python {res['python']}."]
    return "\n".join(lines) + "\n"


def measure_set(rule: str, kind: str, d: int, n: int, span: float, repeat: int, threads: tuple[int, ...]) -> dict:
    """One set's row (:func:`auto_calibration.measure` on :func:`rule_set`'s particles), with its rule."""
    r = measure(kind, d, n, span, repeat, threads, rule=rule, sets=lambda k, dd, nn, sp: rule_set(rule, k, dd, nn, sp))
    return dict(r, rule=rule)


def remeasure(path: Path, sets: list[str], repeat: int, threads: tuple[int, ...], tag: str) -> int:
    """Measure the sets named ``RULE:KIND:D:N:SPAN`` again, ``repeat`` times, in place of their rows of the
    result at ``path`` (noted in its meta), and rewrite the JSON and the page."""
    res = json.loads(path.read_text())
    for item in sets:
        rule, kind, d, n, span = item.split(":")
        r = measure_set(rule, kind, int(d), int(n), float(span), repeat, threads)
        key = (r["rule"], r["kind"], r["d"], r["n"], r["span"])
        res["rows"] = [r if (o["rule"], o["kind"], o["d"], o["n"], o["span"]) == key else o for o in res["rows"]]
        print(item, {t: {m: round(1e3 * v, 2) for m, v in r[f"t{t}"]["cpu"].items()} for t in threads})
    res["meta"].setdefault("remeasured", []).append(dict(date=time.strftime("%Y-%m-%d"), sets=sets, repeat=repeat,
                                                         load=os.getloadavg()[0]))
    estimate_skipped(res["rows"], threads)
    write_result(path.parent, tag, res, f"{tag}.md")
    print(f"wrote {write_page(path.parent, tag, report)}")
    return 0


def main(argv: list[str] | None = None) -> int:
    def extra(parser):
        parser.add_argument("--fit", action="store_true", help="print the costs that fit the 1-thread CPU times of "
                            "the JSON of the last run and how the chosen lists fare with them; nothing is measured")
        parser.add_argument("--only", nargs="+", metavar="RULE:KIND:D:N:SPAN", help="measure these sets again "
                            "(e.g. sum:bimodal5:3:100000:1000) in place of their rows of the last run; rewrite its page")
        parser.add_argument("--repeat", type=int, default=5, help="repeats of the sets of --only (default 5)")

    args = benchmark_args(__doc__, argv, HERE / "results", extra)
    cfg = QUICK if args.quick else FULL
    threads = tuple(t for t in cfg["threads"] if t <= arpy.threads.max_threads()) or (1,)
    tag = "auto_rules_quick" if args.quick else "auto_rules"
    if args.fit:
        rows = json.loads((args.out / f"{tag}.json").read_text())["rows"]
        for label, ar in (("in use", AUTO_AR_COST), ("fitted", fit(rows))):
            print(f"{label}: coarse {ar['coarse']:.3f} ns, up {ar['up']:.3f} ns; chosen list within {TOLERANCE:g}x "
                  f"(1 thread, CPU): {within(rows, refit_choices(rows, AUTO_CELL_COST, ar), 1, 'cpu')}")
        return 0
    if args.only:
        return remeasure(args.out / f"{tag}.json", args.only, args.repeat, threads, tag)
    load = os.getloadavg()[0]
    rows: list[dict] = []
    todo = [(rule, kind, d, n, s) for n in cfg["sizes"] for rule in ("sum", "max") for d in (2, 3) for kind in KINDS
            for s in cfg["spans"] if s != 1.0 or kind == "loguniform"]       # (one radius: as loguniform)
    for rule, kind, d, n, s in todo:
        r = measure_set(rule, kind, d, n, s, cfg["repeat"][n], threads)
        rows.append(r)
        (args.out / f"{tag}.partial.json").write_text(json.dumps(rows, indent=1))
        print(f"{rule} {kind:>10s} {d} {n:9d} {s:7g} {r['choice']:>4s} | " + " | ".join(
            " ".join(f"{1e3 * r[f't{t}']['cpu'].get(m, np.nan):9.2f}" for m in ("cell", "ar", "auto"))
            for t in threads), flush=True)
    estimate_skipped(rows, threads)
    meta = dict(date=time.strftime("%Y-%m-%d"), quick=args.quick, load=load, cpus=os.cpu_count(), sizes=list(cfg["sizes"]),
                repeat={str(k): v for k, v in cfg["repeat"].items()}, threads=list(threads), neighbours=NEIGHBOURS,
                tolerance=TOLERANCE, max_checks=MAX_CHECKS, auto_ar_work=AUTO_AR_WORK, cell_cost=AUTO_CELL_COST,
                ar_cost=AUTO_AR_COST, sampling=sampling())
    (args.out / f"{tag}.partial.json").unlink()
    write_result(args.out, tag, dict(run_info(), meta=meta, rows=rows), f"{tag}.md")
    print(f"wrote {write_page(args.out, tag, report)}")
    return 0 if all(r[f"t{t}"]["same_rows"] for r in rows for t in threads) else 1


if __name__ == "__main__":
    sys.exit(main())
