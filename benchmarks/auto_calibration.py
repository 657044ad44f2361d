"""Benchmark: what ``method="auto"`` chooses, against the uniform ("cell") and AR ("ar") lists.

``neighbor_list(x, rc, method="auto")`` picks one of the two lists from cheap statistics of the
cutoffs and of the particles' box (:func:`arpy.lists.auto.auto_work`): the distance checks each
list would make if the particles were spread evenly over their bounding box.  This benchmark times
both lists and ``auto`` itself on the data users have as well as on the AR paper's benchmark:

  loguniform   uniform positions in the unit box, cutoffs log-uniform over [r, span r]
  bimodal50    uniform positions, half of the cutoffs r, half span r
  bimodal5     uniform positions, 5 % of the cutoffs span r, the others r
  paper        the AR paper's two-resolution benchmark (arpy.ar_benchmark, lambda = span)
  cluster50    clustered particles: half of them in a Gaussian cluster of standard deviation w (the
               set's parameter) at the centre of the unit box, half uniform; each cutoff set from the
               local density so that a particle has about 16 neighbours (small cutoffs where the
               particles crowd, as in adapted sets)
  cluster80    the same with 80 % of the particles uniform
  pulse        (2D, not in --quick) the adapted particles of the Sec. 4.3 pulse
               (arpy.cases.gaussian_pulse, D0 the set's parameter, after its first steps): the sets
               DC-PSE's operators are built on
  pulse_half   (2D, not in --quick) those of them below the median of the first coordinate: the
               share a rank holds on 2 ranks, the sets of the self-organization's lists there

For the random sets r is chosen so that a particle has 16 neighbours on average (the expected
number of pairs under the min rule, boundary effects aside).  Spans 1 to 1000, cluster widths 0.05
to 0.2, d = 2 and 3, N = 1e4 to 1e6, each measured with 2 threads and with 1.  The three methods are timed in turn
(interleaved) and each time is the minimum over the repeats: the machine may be shared, and the
minimum is the figure least disturbed by other work.  A uniform list that would make more than
``MAX_CHECKS`` distance checks (counted from the cells' occupancy) is not run: its time is
estimated from the counted checks and the median time per check of the uniform runs measured.

    python benchmarks/auto_calibration.py            # the sizes above (about 15 minutes)
    python benchmarks/auto_calibration.py --quick    # N = 2000, a few sets (seconds; tests)

Results: ``results/auto_calibration.json`` and ``results/auto_calibration.md`` (generated from the
JSON by :func:`report`).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

import arpy
from arpy._bench import benchmark_args, md_table, run_info, uniform_checks, write_page, write_result
from arpy.lists import auto
from arpy.lists.auto import AUTO_AR_COST, AUTO_AR_WORK, AUTO_CELL_COST, auto_terms, model_times, n_decades
from arpy.threads import num_threads

HERE = Path(__file__).resolve().parent

#: Mean number of neighbours per particle of the random sets.
NEIGHBOURS = 16
#: Uniform lists above this many distance checks are estimated, not run (unless auto picks them).
MAX_CHECKS = 1e9
#: auto may cost at most this many times the faster of the two lists.
TOLERANCE = 1.2
KINDS = ("loguniform", "bimodal50", "bimodal5", "paper", "cluster50", "cluster80", "sparse_loguniform", "sparse_bimodal5")
#: The kinds the cost model is fitted on (:func:`fit`): the issue's random sets and the paper's benchmark;
#: the clustered kinds, the pulse's particles and the sparse kinds test it.
FIT_KINDS = ("loguniform", "bimodal50", "bimodal5", "paper")
#: The sparse kinds: the random kind's set with its cutoffs scaled to SPARSE_NEIGHBOURS neighbours per
#: particle.  Where a level's cells outnumber its particles several times the AR tree hashes the level (or
#: keeps a large, mostly empty dense table), and its list costs several times more per particle.
SPARSE = {"sparse_loguniform": "loguniform", "sparse_bimodal5": "bimodal5"}
#: The sparse kind the costs of the AR tree's tables are fitted on (:func:`fit_tables`); the other tests them.
TABLE_FIT_KINDS = ("sparse_bimodal5",)
SPARSE_NEIGHBOURS = 1.0
#: The clustered kinds: the fraction of the particles spread uniformly, the rest in the cluster.
CLUSTERS = {"cluster50": 0.5, "cluster80": 0.8}
FULL = dict(sizes=(10_000, 100_000, 1_000_000), spans=(1.0, 2.0, 4.0, 10.0, 100.0, 1000.0), widths=(0.05, 0.1, 0.2),
            pulse=(0.08, 0.04, 0.02), repeat={10_000: 7, 100_000: 5, 1_000_000: 2}, threads=(1, 2))
QUICK = dict(sizes=(2_000,), spans=(1.0, 100.0), widths=(0.05,), pulse=(), repeat={2_000: 1}, threads=(1, 2))
#: The time step after which the pulse's particles are taken (its first steps: the set is adapted).
PULSE_T = 0.005


def random_set(kind: str, d: int, n: int, span: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Uniform positions in [0, 1]^d and cutoffs of the given kind, scaled so that the expected
    number of neighbours per particle under the min rule is :data:`NEIGHBOURS`."""
    rng = np.random.default_rng(seed)
    x = rng.random((n, d))
    if kind == "loguniform":
        rc = np.exp(rng.uniform(0.0, np.log(span), n))
    elif kind in ("bimodal50", "bimodal5"):
        rc = np.where(rng.random(n) < (0.5 if kind == "bimodal50" else 0.05), span, 1.0)
    else:
        raise ValueError(f"unknown kind {kind!r}")
    # sum over pairs of min(rc_p, rc_q)^d: the i-th smallest cutoff is the smaller one of n - 1 - i pairs
    r = np.sort(rc) ** d
    pair_volume = float(np.sum(r * np.arange(n - 1, -1, -1))) * (np.pi if d == 2 else 4.0 * np.pi / 3.0)
    scale = (NEIGHBOURS * n / (2.0 * pair_volume)) ** (1.0 / d)
    return x, rc * scale


def cluster_set(d: int, n: int, width: float, uniform: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n particles in [0, 1]^d, the fraction ``uniform`` of them uniform, the others in a Gaussian cluster of
    standard deviation ``width`` at the centre (clipped into the box); each cutoff from the density there
    (cluster and background) so that a particle has about :data:`NEIGHBOURS` neighbours."""
    rng = np.random.default_rng(seed)
    m = int(round(uniform * n))
    x = np.concatenate([np.clip(0.5 + width * rng.standard_normal((n - m, d)), 0.0, 1.0), rng.random((m, d))])
    x = x[rng.permutation(n)]
    r2 = np.sum((x - 0.5) ** 2, axis=1)
    density = (n - m) * np.exp(-0.5 * r2 / width ** 2) / (2.0 * np.pi * width ** 2) ** (d / 2) + m
    ball = np.pi if d == 2 else 4.0 * np.pi / 3.0
    return x, (NEIGHBOURS / (density * ball)) ** (1.0 / d)


def make_set(kind: str, d: int, n: int, span: float) -> tuple[np.ndarray, np.ndarray]:
    """The particles of one set: :func:`random_set`, the paper's benchmark with n particles (lambda =
    span), :func:`cluster_set` (width = span) or the pulse's adapted particles (D0 = span, 2D; n is
    what the pulse makes), all of them or the half below the median of the first coordinate."""
    if kind == "paper":
        return arpy.ar_benchmark(n - 10 ** d, span, d)
    if kind in CLUSTERS:
        return cluster_set(d, n, span, CLUSTERS[kind])
    if kind in SPARSE:
        x, rc = random_set(SPARSE[kind], d, n, span)
        return x, rc * (SPARSE_NEIGHBOURS / NEIGHBOURS) ** (1.0 / d)
    if kind in ("pulse", "pulse_half"):
        from arpy import cases

        ps = cases.gaussian_pulse(d=d, D0=span, T=PULSE_T)["sim"].particles
        x, rc = np.array(ps.x), np.array(ps.rc)
        if kind == "pulse":
            return x, rc
        below = x[:, 0] < np.median(x[:, 0])
        return x[below], rc[below]
    return random_set(kind, d, n, span)


def time_methods(x: np.ndarray, rc: np.ndarray, methods: list[str], repeat: int, rule: str = "min"
                 ) -> tuple[dict, dict, dict]:
    """(minimum wall time in s of each method's list under ``rule`` over ``repeat`` rounds, the methods run in
    turn within a round; minimum CPU time of the process (all threads) likewise; the list of each method
    from the last round).  An untimed round comes first: the first lists of a set can be several times slower
    than the next ones (seen at N = 1e6 on a machine just after other work: 0.6-0.8 s against 0.11 s)."""
    wall = {m: np.inf for m in methods}
    cpu = {m: np.inf for m in methods}
    lists: dict = {m: arpy.neighbor_list(x, rc, method=m, rule=rule) for m in methods}
    for k in range(repeat):
        for m in methods[k % len(methods):] + methods[:k % len(methods)]:     # (each first in turn)
            t0, c0 = time.perf_counter(), time.process_time()
            lists[m] = arpy.neighbor_list(x, rc, method=m, rule=rule)
            wall[m] = min(wall[m], time.perf_counter() - t0)
            cpu[m] = min(cpu[m], time.process_time() - c0)
    return wall, cpu, lists


def time_terms(x: np.ndarray, rc: np.ndarray, repeat: int, rule: str = "min") -> tuple[float, float]:
    """(minimum wall time, minimum CPU time) in s of auto's statistics (:func:`auto_terms`) on the set under
    ``rule``, over at least 10 calls: what ``method="auto"`` adds to the list it builds."""
    wall = cpu = np.inf
    for _ in range(max(10, 3 * repeat)):
        t0, c0 = time.perf_counter(), time.process_time()
        auto_terms(x, rc, rule=rule)
        wall, cpu = min(wall, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
    return wall, cpu


def neighbour_counts(nl: arpy.NeighborList) -> np.ndarray:
    """Every particle's number of neighbours in a half list (the methods store a pair in different rows)."""
    n = len(nl.offsets) - 1
    rows = np.repeat(np.arange(n), np.diff(nl.offsets))
    return np.bincount(rows, minlength=n) + np.bincount(nl.indices, minlength=n)


def measure(kind: str, d: int, n: int, span: float, repeat: int, threads: tuple[int, ...], rule: str = "min",
            sets: Callable[[str, int, int, float], tuple[np.ndarray, np.ndarray]] | None = None) -> dict:
    """One set (``sets(kind, d, n, span)``, default :func:`make_set`): its statistics under ``rule``, auto's
    choice, and the times of the three methods' lists under ``rule`` at each thread count."""
    x, rc = (sets or make_set)(kind, d, n, span)
    terms = auto_terms(x, rc, rule=rule)
    t_cell, t_ar = model_times(len(x), d, *terms, rule=rule)
    checks = uniform_checks(x, 2.0 * rc if rule == "sum" else rc)     # (the uniform list's cells: the largest reach)
    row = dict(kind=kind, d=d, n=len(x), span=span, rc_span=float(rc.max() / rc.min()), terms=list(terms),
               model_cell=t_cell, model_ar=t_ar, checks_cell=checks,
               choice="ar" if t_cell > AUTO_AR_WORK * t_ar else "cell")
    run_cell = checks <= MAX_CHECKS or row["choice"] == "cell"        # (the list auto picks is always run)
    methods = ["cell", "ar", "auto"] if run_cell else ["ar", "auto"]
    for t in threads:
        with num_threads(t):
            wall, cpu, lists = time_methods(x, rc, methods, repeat, rule)
            terms_wall, terms_cpu = time_terms(x, rc, repeat, rule)
        counts = [neighbour_counts(lists[m]) for m in methods]
        same = all(np.array_equal(c, counts[0]) for c in counts)
        row[f"t{t}"] = dict(wall, cpu={m: cpu[m] for m in methods}, same_rows=bool(same), cell_estimated=not run_cell,
                            terms=terms_wall, terms_cpu=terms_cpu)
    row["pairs"] = len(lists["ar"])
    return row


def estimate_skipped(rows: list[dict], threads: tuple[int, ...]) -> float | None:
    """Fill in the wall and CPU time of every uniform list not run: its counted checks times the median
    time per check (at the same thread count) of the uniform lists run with at least 1e7 checks; returns
    that median wall time at the first thread count (ns), None if no such list was run."""
    first = None
    for t in threads:
        run = [r[f"t{t}"] for r in rows if not r[f"t{t}"]["cell_estimated"] and r["checks_cell"] >= 1e7]
        if not run:
            continue
        checks = [r["checks_cell"] for r in rows if not r[f"t{t}"]["cell_estimated"] and r["checks_cell"] >= 1e7]
        wall = float(np.median([m["cell"] / c for m, c in zip(run, checks)]))
        cpu = float(np.median([m["cpu"]["cell"] / c for m, c in zip(run, checks)]))
        first = 1e9 * wall if first is None else first
        for r in rows:
            if r[f"t{t}"]["cell_estimated"]:
                r[f"t{t}"]["cell"] = wall * r["checks_cell"]
                r[f"t{t}"]["cpu"]["cell"] = cpu * r["checks_cell"]
    return first


def sampling() -> dict:
    """The sampling constants of auto's statistics (``arpy.lists.auto.AUTO_*``) in use."""
    return {k: getattr(auto, k) for k in ("AUTO_SAMPLE", "AUTO_SAMPLE_SHARE", "AUTO_SAMPLE_LEAST", "AUTO_FINE_SAMPLE",
                                            "AUTO_FINE_SHARE", "AUTO_FINE_CELLS", "AUTO_CROWD_PAIRS",
                                            "AUTO_CROWD_CELLS", "AUTO_LEVEL_CELLS")}


def terms_cost(rows: list[dict], t: int = 1) -> str:
    """The statistics' time at ``t`` threads (minimum wall time per set; median and range over the sets of
    each N) and its share of the faster list's wall time, as a sentence's clause; '' for rows without it."""
    parts = []
    for n in sorted({r["n"] for r in rows if r["kind"] not in ("pulse", "pulse_half")}):
        at = [r[f"t{t}"] for r in rows if r["n"] == n and "terms" in r.get(f"t{t}", {})]
        if not at:
            continue
        ms = np.array([1e3 * m["terms"] for m in at])
        share = np.array([m["terms"] / min(m.get("cell", np.inf), m["ar"]) for m in at])
        parts.append(f"{np.median(ms):.3g} ms at N = {n:,} ({ms.min():.3g}-{ms.max():.3g}; "
                     f"{100 * np.median(share):.1f} % of the faster list, at most {100 * share.max():.1f} %)")
    return "; ".join(parts)


def cost_line(rows: list[dict], t: int, clock: str, tolerance: float) -> str:
    """The page's sentence on :func:`cost_slowdown` over ``rows`` ('' when no row has the statistics' time)."""
    timed = [r for r in rows if "terms" in r[f"t{t}"]]
    if not timed:
        return ""
    worst = max(timed, key=lambda r: cost_slowdown(r, t, clock))
    ok = sum(cost_slowdown(r, t, clock) <= tolerance for r in timed)
    return (f" The list auto chose plus its statistics (what auto costs, without the noise of a third run): within "
            f"{tolerance:g}x on {ok} of {len(timed)} sets, worst {cost_slowdown(worst, t, clock):.2f}x "
            f"({worst['kind']}, d = {worst['d']}, N = {worst['n']:,}, span {worst['span']:g}).")


def ratio(r: dict) -> float:
    """The model's T_cell / T_ar of row r."""
    return r["model_cell"] / r["model_ar"]


def clock_times(r: dict, t: int, clock: str) -> dict:
    """The times of the methods in row r at t threads by ``clock`` ("wall" or "cpu"), s."""
    return r[f"t{t}"] if clock == "wall" else r[f"t{t}"]["cpu"]


def slowdown(r: dict, t: int, clock: str = "wall") -> float:
    """auto's time over the faster of the two lists in row r at t threads (``clock``: "wall" or "cpu")."""
    m = clock_times(r, t, clock)
    return m["auto"] / min(m["cell"], m["ar"])


def choice_slowdown(r: dict, t: int, clock: str = "wall") -> float:
    """The time of the list auto chose over the faster of the two (no statistics' cost, no noise of a third run)."""
    m = clock_times(r, t, clock)
    return m[r["choice"]] / min(m["cell"], m["ar"])


def cost_slowdown(r: dict, t: int, clock: str = "wall") -> float:
    """What auto costs, the list it chose plus its statistics (each the minimum over the repeats), over the
    faster of the two lists: auto's time without the noise of a third run; nan for rows without the
    statistics' time."""
    terms = r[f"t{t}"].get("terms" if clock == "wall" else "terms_cpu", np.nan)
    c = clock_times(r, t, clock)
    return (c[r["choice"]] + terms) / min(c["cell"], c["ar"])


def features(r: dict) -> tuple[list[float], list[float]]:
    """The columns of the cost model (:func:`arpy.lists.auto.model_times`) of row r: the uniform list's
    (n in 2D, n in 3D, W_cell) and the AR list's (n in 2D, n in 3D, W_own, W_finer, W_look, W_look times
    the decades of n above AUTO_AR_COST["lookup_from"])."""
    n, d = r["n"], r["d"]
    w_cell, w_own, w_finer, w_look, w_hash, w_dense = r["terms"]
    decades = n_decades(n)
    return ([n * (d == 2), n * (d == 3), w_cell],
            [n * (d == 2), n * (d == 3), w_own, w_finer, w_look, w_look * decades])


def table_features(r: dict) -> list[float]:
    """The columns of the AR tree's tables in the model of row r: W_hash, W_hash times the decades of n
    above AUTO_AR_COST["lookup_from"], and the dense cells beyond one per particle."""
    n, w_hash, w_dense = r["n"], r["terms"][4], r["terms"][5]
    return [w_hash, w_hash * n_decades(n), max(w_dense - n, 0.0)]


def fit_rest(use: list[dict], ar: dict, names: tuple[str, ...], columns: Callable[[dict], list[float]]) -> dict:
    """``ar`` with the AR list's costs ``names`` fitted to what the rest of its model (those costs 0; each row
    under its "rule", default the min rule) leaves of the 1-thread CPU times of the AR lists of the rows
    ``use``, ``columns(r)`` being the statistics they multiply (least squares on the relative errors, every
    cost >= 0); ``ar`` itself without rows."""
    from scipy.optimize import nnls

    if not use:
        return dict(ar)
    ta = np.array([r["t1"]["cpu"]["ar"] for r in use]) * 1e9
    rest = np.array([model_times(r["n"], r["d"], *r["terms"], ar=dict(ar, **dict.fromkeys(names, 0.0)),
                                 rule=r.get("rule", "min"))[1] for r in use])
    cost = nnls(np.array([columns(r) for r in use]) / ta[:, None], (ta - rest) / ta)[0]
    return dict(ar, **dict(zip(names, cost.tolist())))


def fit_tables(rows: list[dict], ar: dict) -> dict:
    """``ar`` with the costs of the AR tree's tables ("hashed", "hashed_decade", "empty") fitted on
    TABLE_FIT_KINDS' rows (:func:`fit_rest`)."""
    use = [r for r in rows if r["kind"] in TABLE_FIT_KINDS and "terms" in r]
    return fit_rest(use, ar, ("hashed", "hashed_decade", "empty"), table_features)


def fit(rows: list[dict]) -> tuple[dict, dict]:
    """The costs (ns) that fit the 1-thread CPU times of the rows of FIT_KINDS whose uniform list ran:
    least squares on the relative errors, every cost >= 0 (scipy.optimize.nnls).  Returns
    (cell, ar) in the form of AUTO_CELL_COST and AUTO_AR_COST."""
    from scipy.optimize import nnls

    use = [r for r in rows if r["kind"] in FIT_KINDS and "terms" in r and not r["t1"]["cell_estimated"]]
    fc, fa = zip(*(features(r) for r in use))
    tc = np.array([r["t1"]["cpu"]["cell"] for r in use])
    ta = np.array([r["t1"]["cpu"]["ar"] for r in use])
    c = nnls(np.array(fc, float) / tc[:, None], np.ones(len(use)))[0] * 1e9
    a = nnls(np.array(fa, float) / ta[:, None], np.ones(len(use)))[0] * 1e9
    return ({"particle": {2: c[0], 3: c[1]}, "check": c[2]},
            fit_tables(rows, {"particle": {2: a[0], 3: a[1]}, "own": a[2], "finer": a[3], "lookup": a[4],
                              "lookup_decade": a[5], "lookup_from": AUTO_AR_COST["lookup_from"]}))


def refit_choices(rows: list[dict], cell: dict, ar: dict) -> list[str]:
    """The list the model with costs (cell, ar) picks for each row (under its "rule", default the min rule)."""
    out = []
    for r in rows:
        t_cell, t_ar = model_times(r["n"], r["d"], *r["terms"], cell=cell, ar=ar, rule=r.get("rule", "min"))
        out.append("ar" if t_cell > AUTO_AR_WORK * t_ar else "cell")
    return out


def costs_line(cell: dict, ar: dict) -> str:
    """The costs in one line (ns; the per-particle costs keyed by d, as ints or, read from JSON, strings)."""
    cp = {int(k): v for k, v in cell["particle"].items()}
    ap = {int(k): v for k, v in ar["particle"].items()}
    return (f"uniform list: {cp[2]:.2f} / {cp[3]:.2f} per particle (2D / 3D), "
            f"{cell['check']:.2f} per check; AR list: {ap[2]:.2f} / {ap[3]:.2f} per "
            f"particle, {ar['own']:.2f} per own-level check, {ar['finer']:.2f} per finer-level check, "
            f"{ar['lookup']:.2f} + {ar['lookup_decade']:.2f} per decade of N above {ar['lookup_from']:.0e} "
            f"per stencil cell looked up, {ar.get('hashed', 0.0):.2f} + {ar.get('hashed_decade', 0.0):.2f} per "
            f"decade per cell entered on a hashed level, {ar.get('empty', 0.0):.2f} per dense cell beyond one per "
            "particle")


def report(res: dict) -> str:
    """The Markdown page of a result (``results/auto_calibration.md`` is this of its JSON)."""
    meta, rows = res["meta"], res["rows"]
    threads = meta["threads"]
    refit_cell, refit_ar = fit(rows) if all("terms" in r for r in rows) else (None, None)
    lines = ["# method=\"auto\": calibrated on random polydisperse sets and on the AR paper's benchmark", "",
             "`neighbor_list(x, rc, method=\"auto\")` estimates the time each list would take, `T_cell` and "
             "`T_ar` (`arpy.lists.auto.auto_work`), and picks the AR list when "
             f"`T_cell > {meta['auto_ar_work']:g} T_ar` (`AUTO_AR_WORK`), the uniform list otherwise.", "",
             "    python benchmarks/auto_calibration.py            # this page",
             "    python benchmarks/auto_calibration.py --quick    # N = 2000, seconds",
             "    python benchmarks/auto_calibration.py --fit      # the costs that fit the JSON's times", "",
             "## How the estimate works", "",
             "Both lists test the pairs of particles in neighbouring cells. The uniform list's cells are as wide as "
             "the largest cutoff r_max, so each particle is tested against the particles of the 3^d cells around "
             "its own (half of them, as each pair is tested once): `W_cell = N/2 * occ(r_max, N) * F` checks, where "
             "`occ(c, m)` is the number of m particles spread evenly over the particles' bounding box that fall in "
             "a block of 3^d cells of edge c, and F the mean crowding of a sample of particles: the sampled "
             "particles in the 3^d cells of edge r_max around each, over their evenly spread number (where "
             "particles crowd the uniform list tests the square of their number). The AR list puts a particle of "
             "cutoff r on the level whose cells are the power of two (times the smallest cutoff) just above r; a "
             "pair is found from its coarser particle, which tests the later particles of its own level's stencil, "
             "then the stencils of the finer levels, descending only while they hold finer particles. So it is "
             "charged `W_own`, each sampled particle's sampled neighbours of its own level in the 3^d cells of its "
             "level's edge (counted on a grid over that level's particles: a level that crowds in a cluster crowds "
             "its own cells), `W_finer`, the finer levels' particles in their stencils (evenly spread, times the "
             "particle's crowding), and `W_look`, 3^d cells looked up on each level from the particle's own down "
             "to the finest level held by the particles near it (a coarse particle far from the fine ones does not "
             "descend). And the tree's tables: a level is kept dense (an array over its box) when that box has at "
             "most 4 cells per particle on it or finer, plus 1024, within 4 N + 4096 cells in all, and hashed "
             "otherwise; `W_hash` counts the cells the particles enter on hashed levels (one on their own level "
             "and on each coarser one) and `W_dense` the dense levels' cells. Both grow where the particles are "
             "sparse against their cutoffs. The times are `T_cell = A_d N + B W_cell` and `T_ar = C_d N + E_own "
             "W_own + E_finer W_finer + (E_look + E_decade log10(N / 1e4)) W_look + (E_hash + E_hash_decade "
             "log10(N / 1e4)) W_hash + E_empty max(W_dense - N, 0)` (N >= 1e4; the hashed levels' tables outgrow "
             "the caches as N grows). The core gathers the statistics in one call (`arpy.lists.auto.auto_terms`): one "
             "pass over every particle's cutoff and position, which draws the samples by a hash of the position, "
             "so that the same particles in any order give the same choice, then a few passes over the samples"
             + (f". Measured in this run (wall, {threads[0]} thread{'s' if threads[0] > 1 else ''}): "
                f"{terms_cost(rows, threads[0])}" if terms_cost(rows, threads[0]) else "")
             + (". Sampling constants: " + ", ".join(f"`{k}` = {v:g}" for k, v in meta["sampling"].items())
                if "sampling" in meta else "") + ".", "",
             f"Costs in use (ns, `AUTO_CELL_COST`, `AUTO_AR_COST`): {costs_line(meta['cell_cost'], meta['ar_cost'])}. "
             "They were fitted (`--fit`: least squares on the relative errors, every cost >= 0) on the 1-thread "
             "CPU times of the random sets and the paper's benchmark (`loguniform`, `bimodal50`, `bimodal5`, "
             "`paper`) of the previous run, and the tables' costs (`hashed`, `hashed_decade`, `empty`) on what the "
             "rest of the model leaves of the AR lists' times of the sparse bimodal sets (`sparse_bimodal5`) of "
             "this run; the clustered sets, the pulse's particles and the sparse log-uniform sets were not in the "
             "fit."
             + (f" Refitted on this run's times: {costs_line(refit_cell, refit_ar)}; with those, the chosen list "
                "would be within 1.2x of the faster (1-thread CPU) on "
                f"{sum(r['t1']['cpu'][c] <= meta['tolerance'] * min(r['t1']['cpu']['cell'], r['t1']['cpu']['ar']) for r, c in zip(rows, refit_choices(rows, refit_cell, refit_ar)))}"
                f" of {len(rows)} sets." if refit_cell is not None else ""), "",
             "Why the span alone cannot decide: cutoffs whose large values are rare (the paper's benchmark, "
             "`bimodal5`) make `W_cell` grow like span^d while the AR list's work stays put; when the large cutoffs "
             "are common (`bimodal50`, `loguniform`), the uniform list's extra checks grow slowly with the span while "
             "every coarse particle of the AR list descends through the finer levels near it. With one cutoff both "
             "lists test the same cells; the AR list reads its particles in cell order and costs less per particle "
             "(3D) or about the same (2D).", "",
             "## Set-up", "",
             f"Random sets: uniform positions in the unit box, {meta['neighbours']} neighbours per particle on "
             "average; `loguniform`: cutoffs log-uniform over a factor span; `bimodal50`: half the cutoffs span "
             "times the others; `bimodal5`: 5 % of them; `paper`: `arpy.ar_benchmark` with lambda = span; "
             "`cluster50` and `cluster80`: half or 80 % of the particles uniform, the others in a Gaussian cluster of "
             "standard deviation w (the column span holds w) at the centre, each cutoff from the density there for "
             f"about {meta['neighbours']} neighbours (small cutoffs where the particles crowd); `pulse` (2D): the "
             "adapted particles of the Sec. 4.3 pulse after its first steps (`arpy.cases.gaussian_pulse`, the column "
             "span holds D0), the sets DC-PSE's operators are built on; `pulse_half`: those below the median of "
             "the first coordinate, the share of a rank on 2 ranks (the self-organization's lists there); "
             f"`sparse_loguniform` and `sparse_bimodal5`: those kinds with {meta.get('sparse_neighbours', 1):g} "
             "neighbour per particle instead: cutoffs small against the spacing, where the AR tree hashes its "
             "levels or keeps large, mostly empty dense tables, and its list costs several times more per "
             "particle. "
             f"N = {', '.join(f'{n:,}' for n in meta['sizes'])}; threads: {', '.join(map(str, threads))}. "
             "Times are the minimum over repeats "
             f"({', '.join(f'{v} at N = {int(k):,}' for k, v in meta['repeat'].items())}), the three methods "
             "run in turn in each repeat, each timed by the wall clock and by the process's CPU time (all threads). "
             + (f"The machine was shared with other work during the run (load average {meta['load']:.0f} on "
                f"{meta['cpus']} cores at the start): wall times are inflated and noisy even as minima, so "
                if meta.get("load", 0) >= 0.5 else
                f"The machine was idle at the start (load average {meta.get('load', 0):.1f} on {meta['cpus']} cores); "
                "wall times can still be disturbed, so ")
             + "the choice is judged first on CPU time, which other processes disturb far less (at 1 thread it is the time the list takes on an idle "
             "core, give or take cache effects; at 2 threads it adds up both threads' time, their waits "
             "included, so there only the wall time measures speed, and it is the noisier). `auto` is timed as itself (statistics included). `same rows`: "
             "every particle has as many neighbours in each method's list."
             + (f" `~`: a uniform list of more than {meta['max_checks']:.0e} checks, not run: its counted checks "
                "times the median time per check of the uniform lists run "
                f"({meta['ns_per_check']:.2f} ns wall at {threads[0]} thread{'s' if threads[0] > 1 else ''})."
                if meta.get("ns_per_check") is not None else ""),
             ""]
    if meta.get("note"):
        lines += [meta["note"], ""]
    for again in meta.get("remeasured", []):
        how = [f"{again['repeat']} repeats" if again.get("repeat") else "",
               f"`AUTO_AR_WORK` = {again['auto_ar_work']:g}" if "auto_ar_work" in again else "",
               f"load average {again['load']:.1f} at the start"]
        lines += [f"Measured again on {again['date']} (`--only`, " + ", ".join(h for h in how if h) + "): "
                  + ", ".join(f"`{s}`" for s in again["sets"]) + ".", ""]
    missing = sorted(set(meta["sizes"]) - {r["n"] for r in rows})
    if missing:
        lines += [f"**Not measured in this run:** N = {', '.join(f'{n:,}' for n in missing)} (the run was stopped "
                  "there: on the shared machine it would have taken hours). `python benchmarks/auto_calibration.py` "
                  "measures them.", ""]
    for t in threads:
        lines += [f"## {t} thread{'s' if t > 1 else ''}", ""]
        for clock in ("cpu", "wall"):
            worst = max(rows, key=lambda r: slowdown(r, t, clock))
            worst_choice = max(rows, key=lambda r: choice_slowdown(r, t, clock))
            ok = sum(slowdown(r, t, clock) <= meta["tolerance"] for r in rows)
            lines.append(f"- {clock.upper() if clock == 'cpu' else 'wall'} time: auto within {meta['tolerance']:g}x "
                         f"of the faster list on {ok} of {len(rows)} sets; worst {slowdown(worst, t, clock):.2f}x "
                         f"({worst['kind']}, d = {worst['d']}, N = {worst['n']:,}, span {worst['span']:g}). The "
                         f"list auto chose (without the statistics and the noise of a third run): worst "
                         f"{choice_slowdown(worst_choice, t, clock):.2f}x ({worst_choice['kind']}, d = "
                         f"{worst_choice['d']}, N = {worst_choice['n']:,}, span {worst_choice['span']:g})."
                         + cost_line(rows, t, clock, meta["tolerance"]))
        lines.append("")
        table = []
        for r in rows:
            m = r[f"t{t}"]
            c = m["cpu"]
            est = "~" if m["cell_estimated"] else ""
            table.append([r["kind"], r["d"], f"{r['n']:,}", f"{r['span']:g}", f"{r['pairs'] / r['n']:.1f}",
                          f"{ratio(r):.3g}", r["choice"], f"{est}{1e3 * c['cell']:.2f}",
                          f"{1e3 * c['ar']:.2f}", f"{1e3 * c['auto']:.2f}", f"{est}{c['cell'] / c['ar']:.2f}",
                          f"{slowdown(r, t, 'cpu'):.2f}", f"{est}{1e3 * m['cell']:.2f}", f"{1e3 * m['ar']:.2f}",
                          f"{1e3 * m['auto']:.2f}", f"{slowdown(r, t):.2f}",
                          f"{1e3 * m['terms']:.3f}" if "terms" in m else "",
                          f"{cost_slowdown(r, t):.2f}" if "terms" in m else "", "yes" if m["same_rows"] else "NO"])
        lines += md_table(["set", "d", "N", "span", "pairs / N", "T_cell / T_ar", "auto picks", "cell CPU (ms)",
                           "ar CPU (ms)", "auto CPU (ms)", "cell / ar (CPU)", "auto / faster (CPU)",
                           "cell wall (ms)", "ar wall (ms)", "auto wall (ms)", "auto / faster (wall)",
                           "statistics wall (ms)", "(chosen + statistics) / faster (wall)", "same rows"], table)
        lines.append("")
    lines += ["## Findings", ""]
    for t, clock in [(t, "cpu" if t == 1 else "wall") for t in threads]:
        for label, sel in (("the sets with about 16 neighbours per particle", [r for r in rows if r["kind"] not in SPARSE]),
                           ("the sparse sets", [r for r in rows if r["kind"] in SPARSE])):
            if not sel:
                continue
            ch = [choice_slowdown(r, t, clock) for r in sel]
            lines.append(f"- {t} thread{'s' if t > 1 else ''}, {clock} time, {label}: the chosen list within "
                         f"{meta['tolerance']:g}x of the faster on {sum(v <= meta['tolerance'] for v in ch)} of "
                         f"{len(sel)}, worst {max(ch):.2f}x" + (
                             f"; with its statistics on {sum(cost_slowdown(r, t, clock) <= meta['tolerance'] for r in sel)}"
                             f", worst {max(cost_slowdown(r, t, clock) for r in sel):.2f}x"
                             if all("terms" in r[f"t{t}"] for r in sel) else "") + ".")
    for t in threads:
        for clock in ("cpu", "wall"):
            wrong = [r for r in rows if choice_slowdown(r, t, clock) > meta["tolerance"]]
            lines.append(f"- {t} thread{'s' if t > 1 else ''}, {clock} time: the chosen list is within "
                         f"{meta['tolerance']:g}x of the faster one on {len(rows) - len(wrong)} of {len(rows)} sets"
                         + (": not on " + "; ".join(f"{r['kind']} d = {r['d']} N = {r['n']:,} span {r['span']:g} "
                                                    f"({choice_slowdown(r, t, clock):.2f}x)" for r in wrong)
                            if wrong else "") + ".")
    if any(t > 1 for t in threads) and meta.get("load") and meta["load"] > meta.get("cpus", 1):
        lines.append(f"- With a load average of {meta['load']:.0f} on {meta['cpus']} cores, a thread of a parallel "
                     "region can be descheduled for long stretches while the other waits for it: the 2-thread "
                     "ratios far above 1 (single sets slowed hundreds of times in every repeat) measure that, not "
                     "the lists; only the 1-thread CPU times judge the choice in this run. Rerun on a quiet "
                     "machine for the 2-thread figures.")
    t0 = threads[0]
    cross = sorted(rows, key=ratio)
    lines.append(f"- Estimated T_cell / T_ar -> measured cell / ar (CPU, {t0} thread{'s' if t0 > 1 else ''}), "
                 "sorted by the estimate: "
                 + ", ".join(f"{ratio(r):.2g} -> {r[f't{t0}']['cpu']['cell'] / r[f't{t0}']['cpu']['ar']:.2g}"
                             for r in cross[::max(1, len(cross) // 16)]) + ".")
    lines.append("- Every method found the same rows (row lengths compared) in every run." if all(
        r[f"t{t}"]["same_rows"] for r in rows for t in threads) else "- Some rows differ: see the JSON.")
    lines += ["", f"Run of {meta['date']} on {res['machine']}, Python {res['python']}."]
    return "\n".join(lines) + "\n"


def remeasure(path: Path, sets: list[str], repeat: int | None, threads: tuple[int, ...], tag: str) -> int:
    """Measure the sets named ``KIND:D:N:SPAN`` again (``repeat`` times, default by N) and put their rows in
    place of the same sets' rows of the result at ``path`` (a new set is added), noting the date in its
    meta; rewrite the JSON and the page.  Returns 0 if every method found the same rows."""
    res = json.loads(path.read_text())
    rows, ok = res["rows"], True
    for item in sets:
        kind, d, n, span = item.split(":")
        r = measure(kind, int(d), int(n), float(span), repeat or FULL["repeat"].get(int(n), 7), threads)
        same = [i for i, o in enumerate(rows) if (o["kind"], o["d"], o["span"]) == (kind, int(d), float(span))
                and (o["n"] == r["n"] or kind.startswith("pulse"))]
        if same:
            rows[same[0]] = r
        else:
            rows.append(r)
        ok = ok and all(r[f"t{t}"]["same_rows"] for t in threads)
        print(item, {t: {m: round(1e3 * r[f"t{t}"]["cpu"][m], 3) for m in r[f"t{t}"]["cpu"]} for t in threads})
    res["meta"].setdefault("remeasured", []).append(dict(date=time.strftime("%Y-%m-%d"), sets=sets,
                                                         load=os.getloadavg()[0], repeat=repeat,
                                                         auto_ar_work=AUTO_AR_WORK))
    res["meta"]["auto_ar_work"] = AUTO_AR_WORK
    estimate_skipped(rows, tuple(res["meta"]["threads"]))
    write_result(path.parent, tag, res, f"{tag}.md")
    print(f"wrote {write_page(path.parent, tag, report)}")
    return 0 if ok else 1


def print_fit(path: Path) -> int:
    """Print the costs :func:`fit` finds in the result at ``path`` (rows without the model's terms get
    them from their sets, made again), the costs in use, and how the chosen lists fare with each."""
    res = json.loads(path.read_text())
    rows = res["rows"]
    for r in rows:
        if "terms" not in r:
            x, rc = make_set(r["kind"], r["d"], r["n"], r["span"])
            r["terms"] = list(auto_terms(x, rc))
    cell, ar = fit(rows)
    for label, (c, a) in (("in use", (AUTO_CELL_COST, AUTO_AR_COST)),
                          ("in use, the tables' costs fitted", (AUTO_CELL_COST, fit_tables(rows, AUTO_AR_COST))),
                          ("fitted", (cell, ar))):
        picks = refit_choices(rows, c, a)
        for t in res["meta"]["threads"]:
            slow = [r[f"t{t}"]["cpu"][p] / min(r[f"t{t}"]["cpu"]["cell"], r[f"t{t}"]["cpu"]["ar"]) for r, p in zip(rows, picks)]
            worst = int(np.argmax(slow))
            print(f"{label}, {t} thread(s) CPU: within {TOLERANCE}x on {sum(v <= TOLERANCE for v in slow)} of "
                  f"{len(rows)}, worst {slow[worst]:.2f} ({rows[worst]['kind']} d={rows[worst]['d']} "
                  f"N={rows[worst]['n']} span={rows[worst]['span']:g})")
        print(f"  {costs_line(c, a)}")
    return 0


def main(argv: list[str] | None = None) -> int:
    def extra(parser):
        parser.add_argument("--sizes", type=int, nargs="+", help="these N only (default: 1e4, 1e5, 1e6)")
        parser.add_argument("--only", nargs="+", metavar="KIND:D:N:SPAN",
                            help="measure these sets again (e.g. loguniform:3:1000000:2; pulse:2:0:0.08) and "
                                 "replace their rows in the JSON of the last full run, then rewrite its page")
        parser.add_argument("--repeat", type=int, help="repeats of every set (default: by N, see FULL)")
        parser.add_argument("--fit", action="store_true",
                            help="print the costs that fit the 1-thread CPU times of the JSON of the last run "
                                 "(its random and paper sets) and what the model would pick with them; nothing "
                                 "is measured")

    args = benchmark_args(__doc__, argv, HERE / "results", extra)
    cfg = QUICK if args.quick else FULL
    if args.sizes:
        cfg = dict(cfg, sizes=tuple(args.sizes), repeat={n: cfg["repeat"].get(n, 3) for n in args.sizes})
    threads = tuple(t for t in cfg["threads"] if t <= arpy.threads.max_threads()) or (1,)
    tag = "auto_calibration_quick" if args.quick else "auto_calibration"
    if args.fit:
        return print_fit(args.out / f"{tag}.json")
    if args.only:
        return remeasure(args.out / f"{tag}.json", args.only, args.repeat, threads, tag)
    load = os.getloadavg()[0]
    rows: list[dict] = []
    print(f"{'set':>10s} {'d':>2s} {'N':>9s} {'span':>7s} {'Tc/Ta':>8s} {'pick':>4s} | "
          + " | ".join(f"{t}T: cell, ar, auto (ms)" for t in threads), flush=True)
    todo = [(kind, d, n, p) for n in cfg["sizes"] for d in (2, 3) for kind in KINDS
            for p in (cfg["widths"] if kind in CLUSTERS else cfg["spans"])
            if p != 1.0 or kind in ("loguniform", "paper", "sparse_loguniform")]   # (one cutoff: as loguniform)
    todo += [(kind, 2, 0, d0) for kind in ("pulse", "pulse_half") for d0 in cfg["pulse"]]
    for kind, d, n, span in todo:
        r = measure(kind, d, n, span, args.repeat or cfg["repeat"].get(n, cfg["repeat"][cfg["sizes"][0]]), threads)
        rows.append(r)
        # after every set, so that an interrupted run keeps what it measured
        (args.out / f"{tag}.partial.json").write_text(json.dumps(rows, indent=1))
        times = " | ".join(" ".join(f"{1e3 * r[f't{t}'].get(m, np.nan):9.2f}"
                                    for m in ("cell", "ar", "auto")) for t in threads)
        print(f"{kind:>10s} {d:2d} {r['n']:9d} {r['span']:7.3g} {ratio(r):8.3g} "
              f"{r['choice']:>4s} | {times}", flush=True)
    ns = estimate_skipped(rows, threads)
    meta = dict(date=time.strftime("%Y-%m-%d"), quick=args.quick, load=load, cpus=os.cpu_count(), sizes=list(cfg["sizes"]),
                repeat={str(k): v for k, v in cfg["repeat"].items()}, threads=list(threads), neighbours=NEIGHBOURS,
                tolerance=TOLERANCE, max_checks=MAX_CHECKS, ns_per_check=ns, auto_ar_work=AUTO_AR_WORK,
                cell_cost=AUTO_CELL_COST, ar_cost=AUTO_AR_COST, sampling=sampling(), sparse_neighbours=SPARSE_NEIGHBOURS)
    res = dict(run_info(), meta=meta, rows=rows)
    (args.out / f"{tag}.partial.json").unlink()
    write_result(args.out, tag, res, f"{tag}.md")
    print(f"wrote {write_page(args.out, tag, report)}")
    for t in threads:
        for clock in ("cpu", "wall"):
            print(f"{t} threads, {clock} time: worst chosen / faster = "
                  f"{max(choice_slowdown(r, t, clock) for r in rows):.2f} (target <= {TOLERANCE}); "
                  f"auto / faster = {max(slowdown(r, t, clock) for r in rows):.2f}")
    return 0 if all(r[f"t{t}"]["same_rows"] for r in rows for t in threads) else 1


if __name__ == "__main__":
    sys.exit(main())
