"""Benchmark: how heavy the weights of DC-PSE rows at the particles are, on every case and on a user's system.

The repair at the particles (:func:`arpy.dcpse.rows.wild_rows`) rebuilds a row of a right-hand side's
Laplacian whose Gershgorin radius alone would make the step unstable, ``nu sum_q |L_pq| dt >
STABILITY``.  This benchmark records, at every assembly at the particles (every RK stage), as the
operators are built before that repair (it is switched off while recording, so each run follows the
path of a build without it):

* the weight scales ``eps^2 sum_q |L_pq|`` of the Laplacian rows and ``eps sum_q |G_pq|`` of the first
  derivatives where a set has them (rows on Dirichlet faces left out);
* the criterion's ratio ``nu sum_q |L_pq| dt / STABILITY`` (above 1: the row is wild);

over every ``arpy run`` case at the small sizes of ``benchmarks/equivalence.py`` and at its defaults
(those whose simulation assembles a Laplacian at the particles), the two runs of
``benchmarks/threads.py``, and issue 54's user system (``benchmarks/stability.py``) at D0 = 0.12 and
0.08 on seeds 1-5 with the default step and with the fixed step 0.2 D0 (taken anyway:
``allow_unstable_dt``).  It prints each run's percentiles and maximum and writes them as JSON.

    python benchmarks/row_scales.py            # everything (about 10 CPU minutes)
    python benchmarks/row_scales.py --quick    # two cases, the user system on seed 1 to T = 0.1
"""

from __future__ import annotations

import contextlib
import io
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
#: Percentiles reported.
PERCENTILES = (50, 90, 99, 99.9)


def record_scales():
    """Patch :class:`arpy.DomainDCPSE` so that every build at the particles records the weight scales of
    its rows as :func:`arpy.dcpse.rows.wild_weights` weighs them (rows on Dirichlet faces left out) and
    finds no row wild; returns the list it appends (laplacian, gradient, gradient within a quarter core
    size of a wall, the criterion's ratio) arrays to, and the undo."""
    from arpy.dcpse import domain as dd
    from arpy.dcpse.rows import abs_row_sums, weight_scales

    seen: list[tuple[np.ndarray, ...]] = []
    orig = dd.DomainDCPSE._wild

    def wild(self, op, rows):
        if not self._at_particles or self._max_lebesgue is None:
            return orig(self, op, rows)
        ops = self._operators
        keys = ["laplacian", *(tuple(int(i == j) for j in range(op.d)) for i in range(op.d))] if ops is None else [
            o if isinstance(o, str) else tuple(int(v) for v in o) for o in ops]
        keys = [k for k in keys if k == "laplacian" or (not isinstance(k, str) and sum(k) == 1)]
        if "laplacian" not in keys:
            return None
        if len(rows) == len(self._cx):
            eps, x, dom = self._src_eps[rows], self._cx[rows], self.domain     # (the particles lead the sources)
            free = np.ones(len(rows), dtype=bool) if self._walls is None else self._walls[2].wall_gap(x) > 0
            gap = np.full(len(rows), np.inf)
            for a in (np.flatnonzero(dom.walls) if dom.has_walls else []):
                gap = np.minimum(gap, np.minimum(np.abs(x[:, a] - dom.lo[a]), np.abs(dom.hi[a] - x[:, a])))
            near = gap < 0.25 * eps
            grad = np.zeros(len(rows))
            for k in keys[1:]:
                grad = np.maximum(grad, weight_scales(op, eps, k))
            has = len(keys) > 1
            limit = self._max_row_sum
            ratio = abs_row_sums(op.laplacian())[free] / limit if limit else np.zeros(0)
            seen.append((weight_scales(op, eps)[free], grad[free] if has else np.zeros(0),
                         grad[free & near] if has else np.zeros(0), ratio))
        return np.zeros(len(rows), dtype=bool)

    dd.DomainDCPSE._wild = wild
    return seen, lambda: setattr(dd.DomainDCPSE, "_wild", orig)


def summary(values: np.ndarray) -> dict:
    """Rows, percentiles and maximum of one scale."""
    if values.size == 0:
        return dict(rows=0)
    return dict(rows=int(values.size), **{f"p{p:g}": float(np.percentile(values, p)) for p in PERCENTILES},
                max=float(values.max()))


def measure(name: str, run) -> dict:
    """Runs ``run()`` with the scales recorded; the summary of its rows."""
    seen, undo = record_scales()
    t0 = time.perf_counter()
    end = "done"
    try:
        run()
    except Exception as e:                                  # (the user system's fixed step may blow up)
        end = f"{type(e).__name__}"
        print(f"  {name}: {type(e).__name__}: {e}", flush=True)
    finally:
        undo()
    lap, grad, wall, ratio = (np.concatenate([s[i] for s in seen]) if seen else np.zeros(0) for i in range(4))
    out = dict(name=name, end=end, builds=len(seen), laplacian=summary(lap), gradient=summary(grad),
               gradient_by_walls=summary(wall), ratio=summary(ratio), wild=int(np.sum(ratio > 1)),
               lap_above={f"{t:g}": int(np.sum(lap > t)) for t in (40, 60, 80, 100, 150, 200)},
               grad_above={f"{t:g}": int(np.sum(grad > t)) for t in (10, 20, 30, 50)},
               wall_s=time.perf_counter() - t0)
    return out


#: The cases at their defaults (each ``arpy run`` case whose simulation assembles a Laplacian at the
#: particles: advection (no diffusion), consistency and bud-surface assemble none there).
DEFAULTS = {"pulse (defaults)": ["pulse"], "burgers (defaults)": ["burgers"], "five-spot (defaults)": ["five-spot"],
            "manufactured (defaults)": ["manufactured"]}
#: The user system: (D0, seeds) with T.
USER = dict(D0=(0.12, 0.08), seeds=(1, 2, 3, 4, 5), T=0.5)
USER_QUICK = dict(D0=(0.12,), seeds=(1,), T=0.1)


def case_runs(quick: bool) -> dict:
    """``arpy run`` argument lists: the cases at equivalence.py's small sizes and at their defaults."""
    sys.path.insert(0, str(HERE))
    import equivalence

    runs = dict(equivalence.RUNS)
    if quick:
        return {k: runs[k] for k in ("pulse2d", "manufactured")}
    return {**runs, **DEFAULTS}


def main(argv: list[str] | None = None) -> int:
    import warnings

    from arpy._bench import benchmark_args, run_info, write_result
    from arpy.cli import main as arpy_main

    args = benchmark_args(__doc__, argv, HERE / "results")
    sys.path.insert(0, str(HERE))
    import stability
    import threads

    rows = []
    user = USER_QUICK if args.quick else USER
    for D0 in user["D0"]:
        for seed in user["seeds"]:
            for dt in (None, 0.2 * D0):
                def run_user(D0=D0, seed=seed, dt=dt):
                    sim = stability.simulation(D0, seed, dt)
                    sim.allow_unstable_dt = True
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        sim.run(user["T"])
                rows.append(measure(f"user D0 {D0:g} seed {seed} dt {'default' if dt is None else f'{dt:.3g}'}",
                                    run_user))
                print(_line(rows[-1]), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for name, argv_case in case_runs(args.quick).items():
            def run_case(argv_case=argv_case, name=name):
                with contextlib.redirect_stdout(io.StringIO()):
                    arpy_main(["run", *argv_case, "--quiet", "--out", str(Path(tmp) / name.split()[0])])
            rows.append(measure(name, run_case))
            print(_line(rows[-1]), flush=True)
    if not args.quick:
        for name, run in (("threads advection_run(0.12, 0.05)", lambda: threads.advection_run(0.12, 0.05)),
                          ("threads pulse_run(0.08, 0.07)", lambda: threads.pulse_run(0.08, 0.07))):
            rows.append(measure(name, run))
            print(_line(rows[-1]), flush=True)
    tag = "row_scales_quick" if args.quick else "row_scales"
    write_result(args.out, tag, dict(**run_info(), quick=args.quick, runs=rows), "", gap=False)
    return 0


def _line(r: dict) -> str:
    lap, grad = r["laplacian"], r["gradient"]

    def fmt(s):
        return "no rows" if not s["rows"] else (f"{s['rows']:7d} rows  p50 {s['p50']:6.1f}  p99 {s['p99']:6.1f}  "
                                                f"p99.9 {s['p99.9']:6.1f}  max {s['max']:7.1f}")
    return (f"{r['name']:34s} {r['end']:16s} {r['builds']:4d} builds | lap {fmt(lap)} | grad {fmt(grad)} | "
            f"grad < eps / 4 from a wall: max {r['gradient_by_walls'].get('max', 0):.1f} | "
            f"ratio max {r['ratio'].get('max', 0):.3f} ({r['wild']} rows > 1) | "
            f"{r['wall_s']:.0f} s")


if __name__ == "__main__":
    sys.exit(main())
