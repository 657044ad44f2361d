"""Benchmark: the paper's stencil rule against arpy's repair rules, on Figs. 4.1-4.3.

Where a particle's DC-PSE moment matrix is not invertible, the paper (Reboux et al. 2012, §2.2)
"randomly displace[s] or insert[s] particles until V becomes invertible"; arpy by default keeps the
particles and repairs the row (wider stencils, Lebesgue limits, order m - 1; ``arpy.dcpse.domain``).
Both rules run here on the same particle sets (same seeds, same D0, so about equal N):

* Fig. 4.1 (§4.1): the tanh front refined D0 <- 0.95 D0, interpolation and Laplacian from the old
  set to the new (``cases.consistency(stencil_rule=...)``);
* Fig. 4.2 (§4.2): the blob in the reversing vortex (``cases.advection``);
* Fig. 4.3 (§4.3): the pulse at Pe = 1e4 (``cases.gaussian_pulse``), seeds 1-3.

Reported: N, the errors, the rows without a valid stencil before the rule acts and after it
("failed"), and what the paper's rule did (particles displaced and inserted).  Writes JSON, PNG and
the Markdown page (results/stencil_rule.md, see report()) into --out.

    python benchmarks/stencil_rule.py            # about 15 minutes
    python benchmarks/stencil_rule.py --quick    # seconds (used by the tests)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from arpy import TreeDepthError, cases
from arpy._bench import benchmark_args, md_table, run_info, span, write_outputs

HERE = Path(__file__).resolve().parent
RULES = ("repair", "displace")
LABELS = {"repair": "arpy's repair", "displace": "paper's displace/insert"}
FULL = dict(fig41=dict(d0_start=0.4, d0_end=0.1, factor=0.95), fig42=dict(D0=[0.2, 0.16, 0.12], T=2.5),
            fig43=dict(D0=0.1, T=1.0, seeds=[1, 2, 3]))
#: A run of the paper's rule with more than RUNAWAY times the particles of arpy's at the same D0 diverged.
RUNAWAY = 4
QUICK = dict(fig41=dict(d0_start=0.4, d0_end=0.32, factor=0.9, width=0.1), fig42=dict(D0=[0.28], T=0.05),
             fig43=dict(D0=0.4, T=0.002, seeds=[1]))


def _sim_row(r: dict, **extra) -> dict:
    """The figures of one simulation run (cases.advection or cases.gaussian_pulse)."""
    h = r["sim"].history()
    return dict(**extra, N=int(r["N_max"]), error=float(r["error"]), steps=int(r["steps"]), wall_s=float(r["wall_s"]),
                failed=int(h["degenerate"].max()), steps_with_failed=int((h["degenerate"] > 0).sum()),
                displaced=int(h["displaced"].sum()) if "displaced" in h else 0,
                inserted=int(h["inserted"].sum()) if "inserted" in h else 0)


def run_fig41(p: dict) -> dict:
    out = {}
    for rule in RULES:
        t = time.perf_counter()
        r = cases.consistency(**p, stencil_rule=rule)
        out[rule] = dict(D0=r["D0"].tolist(), N=r["N"].tolist(), h=r["h"].tolist(), err_interp=r["err_interp"].tolist(),
                         err_laplacian=r["err_laplacian"].tolist(), median_interp=r["median_interp"].tolist(),
                         median_laplacian=r["median_laplacian"].tolist(), failed=r["failed"].tolist(),
                         failed_before=r["failed_before"].tolist(), displaced=r["displaced"].tolist(),
                         inserted=r["inserted"].tolist(), slope_interp=r["slope_interp"],
                         slope_laplacian=r["slope_laplacian"],
                         slope_median_interp=cases.slope(r["h"], r["median_interp"]),
                         slope_median_laplacian=cases.slope(r["h"], r["median_laplacian"]),
                         wall_s=time.perf_counter() - t)
        o = out[rule]
        print(f"Fig. 4.1, {LABELS[rule]}: {len(o['N'])} sets, N {o['N'][0]}-{o['N'][-1]}, max orders interp "
              f"{o['slope_interp']:.2f}, Laplacian {o['slope_laplacian']:.2f}; failed before {sum(o['failed_before'])}, "
              f"after {sum(o['failed'])}; displaced {sum(o['displaced'])}, inserted {sum(o['inserted'])} "
              f"({o['wall_s']:.0f} s)")
    return out


def _both_rules(run, **extra) -> dict:
    """run(stencil_rule=..., [max_particles=...]) with each rule, arpy's first; a run of the paper's
    rule whose re-organization would make more than RUNAWAY times the particles of arpy's, or whose
    resolution collapses below what the AR tree can hold, is stopped and recorded as diverged (N: the
    bound)."""
    rows, cap = {}, None
    for rule in RULES:
        t0 = time.perf_counter()
        try:
            kw = {} if cap is None else dict(max_particles=cap)
            rows[rule] = _sim_row(run(stencil_rule=rule, **kw), **extra, diverged=False)
        except (RuntimeError, TreeDepthError) as e:
            if rule == "repair":
                raise
            rows[rule] = dict(**extra, diverged=True, N=cap, error=None, reason=type(e).__name__,
                              wall_s=time.perf_counter() - t0)
        cap = RUNAWAY * rows[rule]["N"] if cap is None else cap
    return rows


def _said(fig: str, rule: str, row: dict, what: str) -> None:
    print(f"{fig}, {LABELS[rule]}: {what} " + (
        f"diverged ({row['reason']}; bound {row['N']} particles)" if row["diverged"] else
        f"N {row['N']} error {row['error']:.3e} failed {row['failed']} (in {row['steps_with_failed']} of "
        f"{row['steps']} steps) displaced {row['displaced']} inserted {row['inserted']}") + f" ({row['wall_s']:.0f} s)")


def run_fig42(p: dict) -> dict:
    """Both rules at each D0 (:func:`_both_rules`)."""
    out: dict = {rule: dict(rows=[]) for rule in RULES}
    for d0 in p["D0"]:
        rows = _both_rules(lambda **kw: cases.advection(D0=d0, T=p["T"], **kw), D0=d0)
        for rule in RULES:
            out[rule]["rows"].append(rows[rule])
            _said("Fig. 4.2", rule, rows[rule], f"D0 {d0:g}")
    for rule in RULES:
        rows = [r for r in out[rule]["rows"] if not r["diverged"]]
        h = np.array([1 / np.sqrt(r["N"]) for r in rows])
        out[rule]["order"] = cases.slope(h, np.array([r["error"] for r in rows])) if len(rows) > 1 else None
    return out


def run_fig43(p: dict) -> dict:
    out: dict = {rule: [] for rule in RULES}
    for s in p["seeds"]:
        rows = _both_rules(lambda **kw: cases.gaussian_pulse(d=2, Pe=1e4, D0=p["D0"], T=p["T"], seed=s, **kw), seed=s)
        for rule in RULES:
            out[rule].append(rows[rule])
            _said("Fig. 4.3", rule, rows[rule], f"seed {s}")
    return out


def plot(res: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    for rule, style in zip(RULES, ("o-", "s--")):
        o = res["fig41"][rule]
        axes[0].loglog(o["h"], o["err_interp"], style, ms=3, label=f"interpolation, {LABELS[rule]}")
        axes[0].loglog(o["h"], np.array(o["err_laplacian"]) * 1e-5, style, ms=3, alpha=0.6,
                       label=f"Laplacian x 1e-5, {LABELS[rule]}")
        rows = [r for r in res["fig42"][rule]["rows"] if not r["diverged"]]
        if rows:
            axes[1].loglog([1 / np.sqrt(r["N"]) for r in rows], [r["error"] for r in rows], style, label=LABELS[rule])
    axes[0].set_xlabel("h")
    axes[0].set_ylabel("max error")
    axes[0].set_title("Fig. 4.1: tanh front")
    axes[0].legend(fontsize=7)
    axes[1].set_xlabel("h = 1 / sqrt(N_max)")
    axes[1].set_ylabel("max error at T")
    axes[1].set_title("Fig. 4.2: blob in the reversing vortex")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def report(res: dict) -> str:
    """The Markdown page of a result (results/stencil_rule.md is this of results/stencil_rule.json)."""
    tag = "stencil_rule_quick" if res.get("quick") else "stencil_rule"
    lines = ["# The paper's stencil rule against arpy's repair (Figs. 4.1-4.3)", ""]
    if res.get("quick"):
        lines += ["**Quick run** (small sizes, for the tests).", ""]
    lines += ["`python benchmarks/stencil_rule.py` runs the benchmark and writes `stencil_rule.json`, this page and "
              "`stencil_rule.png` into `benchmarks/results/`; `--quick` writes `stencil_rule_quick.*`.", "",
              "Where a particle's DC-PSE moment matrix is not invertible (too few neighbours, singular or "
              "ill-conditioned moments), the paper (§2.2) randomly displaces or inserts particles until it is; "
              "arpy by default keeps the particles and repairs the row (wider stencils, Lebesgue limits, order "
              "m − 1: `arpy.dcpse.domain`). The paper's rule here (`stencil_rule=\"displace\"`, "
              "`arpy.dcpse.displace.displace_until_valid`): after each adaptation, a particle whose own stencil or whose "
              "interpolation from the old set fails moves to a random point within D_p / 2, or, with fewer "
              "than the N* neighbours a stencil needs, gets a new particle at distance D_p; repeated until no "
              "row fails (at most 20 rounds); the operators are then built without repair. Same seeds and D0 "
              "for both rules, so N is about equal.", ""]
    f41 = res["fig41"]
    lines += ["## Fig. 4.1: interpolation and Laplacian from the old set to the new (tanh front)", "",
              f"{len(f41['repair']['N'])} successive adaptations, N {f41['repair']['N'][0]}–{f41['repair']['N'][-1]}. "
              "Errors: maxima over the new particles, relative to max |f|; failed: summed over the sets, before "
              "the rule acts (the rows from the old set to the new; the paper's rule also checks the new set's "
              "own stencils) and after.", ""]
    rows = []
    for rule in RULES:
        o = f41[rule]
        rows.append([LABELS[rule], f"{o['slope_interp']:.2f}", f"{o['slope_laplacian']:.2f}",
                     f"{o['slope_median_interp']:.2f}", f"{o['slope_median_laplacian']:.2f}",
                     f"{max(o['err_interp']):.2e}", f"{max(o['err_laplacian']):.3g}",
                     f"{sum(o['failed_before'])}", f"{sum(o['failed'])}", f"{sum(o['displaced'])}",
                     f"{sum(o['inserted'])}"])
    lines += md_table(["rule", "order max interp.", "order max Lapl.", "order median interp.", "order median Lapl.",
                       "largest interp. error", "largest Lapl. error", "failed before", "failed after", "displaced",
                       "inserted"], rows) + [""]
    lines += ["## Fig. 4.2: the blob in the reversing vortex", "",
              "N: the largest count of the run; failed: the most rows without a stencil in any step (the paper's "
              "rule acts at re-organizations only; particles moved by the flow in between can lose theirs). A run "
              f"of the paper's rule that would exceed {RUNAWAY} times the particles of arpy's at the same D0 is "
              "stopped (diverged), as is one whose resolution collapses below what the AR tree holds (TreeDepthError).", ""]
    rows = []
    for rule in RULES:
        for r in res["fig42"][rule]["rows"]:
            if r["diverged"]:
                rows.append([LABELS[rule], f"{r['D0']:g}", f"diverged ({r['reason']})", "–", "–", "–", "–",
                             f"{r['wall_s']:.0f}"])
            else:
                rows.append([LABELS[rule], f"{r['D0']:g}", str(r["N"]), f"{r['error']:.3e}", str(r["failed"]),
                             str(r["displaced"]), str(r["inserted"]), f"{r['wall_s']:.0f}"])
    lines += md_table(["rule", "D0", "N", "max error at T", "failed", "displaced", "inserted", "wall (s)"], rows)
    lines += ["", "Orders of the maximum error against 1 / √N: " + ", ".join(
        f"{LABELS[rule]} " + ("–" if res["fig42"][rule]["order"] is None else f"{res['fig42'][rule]['order']:.2f}")
        for rule in RULES) + " (the paper: 4).", "",
        "## Fig. 4.3: the pulse at Pe = 10⁴", ""]
    rows = []
    for rule in RULES:
        for r in res["fig43"][rule]:
            if r["diverged"]:
                rows.append([LABELS[rule], str(r["seed"]), f"diverged ({r['reason']})", "–", "–", "–", "–", "–"])
            else:
                rows.append([LABELS[rule], str(r["seed"]), str(r["N"]), f"{r['error']:.3e}", str(r["failed"]),
                             f"{r['steps_with_failed']} / {r['steps']}", str(r["displaced"]), str(r["inserted"])])
    lines += md_table(["rule", "seed", "N", "max error at T", "failed", "steps with failed rows", "displaced",
                       "inserted"], rows) + [""]
    ratio = [d["error"] / r["error"] for d, r in zip(res["fig43"]["displace"], res["fig43"]["repair"])
             if not d["diverged"]]
    worse = [max(f41["displace"][k]) / max(f41["repair"][k]) for k in ("err_interp", "err_laplacian")]
    lines += ["## Findings", "",
              f"- Fig. 4.1: the paper's rule leaves {sum(f41['displace']['failed'])} rows failing (arpy's: "
              f"{sum(f41['repair']['failed'])}) after moving {sum(f41['displace']['displaced'])} particles and "
              f"inserting {sum(f41['displace']['inserted'])}; its largest errors are {worse[0]:.2g}x (interpolation) "
              f"and {worse[1]:.2g}x (Laplacian) arpy's"
              + (": a moment matrix the rule accepts can still be ill-conditioned or fit through barely enough "
                 "neighbours (a large Lebesgue constant), which arpy's repair rebuilds." if max(worse) > 1 else "."),
              f"- Fig. 4.3: " + (f"error with the paper's rule / arpy's: {span(ratio, lambda v: f'{v:.2f}')} over the "
                                  "seeds" if ratio else "no run of the paper's rule reaches T")
              + "".join(f"; seed {r['seed']} diverged ({r['reason']})" for r in res["fig43"]["displace"] if r["diverged"])
              + "."]
    diverged = [r["D0"] for r in res["fig42"]["displace"]["rows"] if r["diverged"]]
    if diverged:
        lines += [f"- Fig. 4.2: with the paper's rule the run diverges at D0 = {', '.join(f'{d:g}' for d in diverged)}: "
                  "where the blob's edge moves into coarser particles, the new particles are finer than the old, and "
                  "their interpolation rows hold fewer old sources than a stencil needs. No displacement within "
                  "D_p / 2 finds more, so these rows keep the nearest old value, and the rows that are valid but "
                  "ill-conditioned are used as they are; the errors this leaves in f most likely steepen the "
                  "monitor's gradient, so that the next adaptation refines there and the count runs away. arpy's "
                  "repair widens those rows and rebuilds the wild ones."]
    lines += ["",
              f"![Figs. 4.1 and 4.2 with either rule]({tag}.png)", "",
              f"Run on {res['machine']} with Python {res['python']}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = benchmark_args(__doc__, argv, HERE / "results")
    tag = "stencil_rule_quick" if args.quick else "stencil_rule"
    p = QUICK if args.quick else FULL
    result = dict(**run_info(), quick=args.quick, parameters=p, fig41=run_fig41(p["fig41"]),
                  fig42=run_fig42(p["fig42"]), fig43=run_fig43(p["fig43"]))
    write_outputs(args.out, tag, result, plot, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
