"""Benchmark: DC-PSE operator assembly and application, and convergence orders.

Timing (m = 4).  Sources on a jittered lattice of N particles in the unit
square (cube), collocation points on a second, independent jittered lattice
(the old set -> new set case), core size eps chosen for about 17 (2D) / 30
(3D) neighbours.  In the same run it measures, per particle:

  neighbours     arpy.cross_neighbor_list (AR cell lists, min rule)
  assembly       Laplacian + interpolating kernel from one factorisation (Fortran)
  reference      the same weights from arpy.reference.dcpse (batched NumPy)
  apply          one sparse mat-vec L @ f (scipy CSR), with its effective bandwidth

Convergence (2D and 3D, variable resolution): interpolation, gradient and
Laplacian errors of a smooth function on warped jittered lattices, with the
fitted orders (expected 4, 3, 2), plus the tanh test function of Sec. 4.1
(Eq. 4.1) on adaptive quadtree particles.  Prints tables, writes JSON + PNG.

    python benchmarks/dcpse.py            # N = 1e4..1e6 (2D), 1e4..2e5 (3D)
    python benchmarks/dcpse.py --quick    # small sizes, seconds

Results: ``results/dcpse.json``, ``.png`` and ``.md`` (the page, from the JSON by :func:`report`).
"""

from __future__ import annotations

import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

import arpy
from arpy._bench import benchmark_args, best_time, md_table, write_page
from arpy.cases import slope
from arpy.reference import dcpse as ref

HERE = Path(__file__).resolve().parent
REFERENCE_MAX = {2: 100_000, 3: 50_000}     # the NumPy reference is timed up to these sizes


def jittered_lattice(rng: np.random.Generator, n: int, d: int, jitter: float = 0.3) -> tuple[np.ndarray, float]:
    side = max(2, int(round(n ** (1.0 / d))))
    h = 1.0 / side
    axis = (np.arange(side) + 0.5) * h
    x = np.stack(np.meshgrid(*([axis] * d), indexing="ij"), axis=-1).reshape(-1, d)
    return x + rng.uniform(-jitter, jitter, x.shape) * h, h


def warped_lattice(rng: np.random.Generator, n_side: int, d: int) -> tuple[np.ndarray, np.ndarray]:
    """Lattice on [0, 1]^d whose spacing varies by a factor 5 (x -> (x + 2x^2)/3), jittered by 0.2 h."""
    t = np.linspace(0.0, 1.0, n_side)
    warp, step = (t + 2 * t * t) / 3, (1 + 4 * t) / 3 / (n_side - 1)
    x = np.stack([g.ravel() for g in np.meshgrid(*([warp] * d), indexing="ij")], axis=1)
    h = np.max(np.stack([s.ravel() for s in np.meshgrid(*([step] * d), indexing="ij")], axis=1), axis=1)
    return x + rng.uniform(-0.2, 0.2, x.shape) * h[:, None], h


def timing(n: int, d: int, repeat: int) -> dict:
    rng = np.random.default_rng(n + d)
    src, h = jittered_lattice(rng, n, d)
    col, _ = jittered_lattice(rng, n, d)
    eps = (2.35 if d == 2 else 1.95) * h
    col = 3 * h + (1 - 6 * h) * np.clip(col, 0.0, 1.0)      # away from the boundary of the sources
    t_nl, nl = best_time(lambda: arpy.cross_neighbor_list(col, eps, src, eps), repeat)
    op = arpy.DCPSE(src, eps, col, eps, neighbors=nl)
    _ = op.a                                     # spline radii, computed once

    def assemble():
        op._ops.clear()
        op._mats.clear()
        op._compute(["laplacian", "interpolation"])
    t_asm, _ = best_time(assemble, repeat)
    lap = op.laplacian()
    f = np.sin(3 * src[:, 0]) * np.cos(2 * src[:, 1])
    t_apply, _ = best_time(lambda: lap @ f, max(repeat, 5))
    row = {"d": d, "n": len(col), "n_src": len(src), "neighbours": float(op.n_neighbors.mean()),
           "t_neighbors": t_nl, "t_assembly": t_asm, "t_apply": t_apply,
           "us_assembly": 1e6 * t_asm / len(col), "us_neighbors": 1e6 * t_nl / len(col),
           "ns_apply_per_nnz": 1e9 * t_apply / lap.nnz,
           "apply_GBps": (lap.nnz * 12 + len(col) * 16 + len(src) * 8) / t_apply / 1e9}
    if n <= REFERENCE_MAX[d]:
        t_ref, w = best_time(lambda: ref.dcpse_weights(src, col, op.col_eps, nl.offsets, nl.indices,
                                                       ["laplacian", "interp"], order=4, a=op.a), 1)
        row["t_reference"] = t_ref
        row["speedup_vs_reference"] = t_ref / t_asm
        row["max_rel_diff_vs_reference"] = float(max(
            abs(w.matrix(0) - op.laplacian()).max() / abs(w.matrix(0)).max(),
            abs(w.matrix(1) - op.interpolation()).max() / abs(w.matrix(1)).max()))
    return row


def convergence(d: int, sides: list[int]) -> dict:
    rng = np.random.default_rng(11)
    ez = (lambda p: np.exp(0.5 * p[:, 2])) if d == 3 else (lambda p: 1.0)
    f = lambda p: np.sin(2 * p[:, 0] + 0.5) * np.cos(1.5 * p[:, 1]) * ez(p)
    fx = lambda p: 2 * np.cos(2 * p[:, 0] + 0.5) * np.cos(1.5 * p[:, 1]) * ez(p)
    lapf = lambda p: (-6.25 + (0.25 if d == 3 else 0.0)) * f(p)
    out = {"h": [], "n": [], "interpolation": [], "gradient": [], "laplacian": [],
           "gradient_at_sources": [], "laplacian_at_sources": []}
    for n_side in sides:
        x, h = warped_lattice(rng, n_side, d)
        eps = (3.5 if d == 2 else 2.6) * h
        y = 0.2 + 0.6 * rng.random((500, d))
        off = arpy.DCPSE(x, eps, y)
        on = arpy.DCPSE(x, eps, strict=False)
        inner = np.all((x > 0.2) & (x < 0.8), axis=1)
        ex = (1,) + (0,) * (d - 1)
        out["h"].append(1.0 / (n_side - 1))
        out["n"].append(len(x))
        out["interpolation"].append(float(np.abs(off.interpolation() @ f(x) - f(y)).max()))
        out["gradient"].append(float(np.abs(off.derivative(ex) @ f(x) - fx(y)).max()))
        out["laplacian"].append(float(np.abs(off.laplacian() @ f(x) - lapf(y)).max()))
        out["gradient_at_sources"].append(float(np.abs((on.derivative(ex) @ f(x) - fx(x))[inner]).max()))
        out["laplacian_at_sources"].append(float(np.abs((on.laplacian() @ f(x) - lapf(x))[inner]).max()))
    out["orders"] = {k: slope(out["h"], out[k]) for k in out if k not in ("h", "n")}
    return out


def tanh_case(d0s: list[float]) -> dict:
    f, lap = arpy.fields.tanh_front, arpy.fields.tanh_front_laplacian
    out = {"D0": [], "h": [], "n": [], "interpolation": [], "laplacian": []}

    def adaptive(seed, d0):
        # the monitor of Eq. 2.8 for the front, bounded below by D0 / 16
        def spacing(c):
            return np.maximum(d0 / np.sqrt(1 + (arpy.fields.tanh_front_gradient(c) ** 2).sum(1)), d0 / 16)
        return arpy.quadtree_particles(spacing, seed=seed)

    for d0 in d0s:
        x, h = adaptive(1, d0)
        y, hy = adaptive(2, 0.95 * d0)                    # the next, finer set (Sec. 4.1)
        op = arpy.DCPSE(x, 5.0 * h, np.clip(y, -0.95, 0.95), 5.0 * hy)
        yy = op.col_x
        inner = np.all(np.abs(yy) < 0.8, axis=1)
        out["D0"].append(d0)
        out["h"].append(float(np.sqrt(4.0 / len(x))))
        out["n"].append(len(x))
        out["interpolation"].append(float(np.abs(op.interpolation() @ f(x) - f(yy))[inner].max()))
        out["laplacian"].append(float(np.abs(op.laplacian() @ f(x) - lap(yy))[inner].max()))
    out["orders_last_two"] = {k: slope(out["h"][-2:], out[k][-2:]) for k in ("interpolation", "laplacian")}
    return out


def plot(conv: dict, tanh: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    panels = [(f"{d}D, smooth f, variable resolution", conv[d]) for d in sorted(conv)] + [("tanh (Eq. 4.1), adaptive", tanh)]
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4.2))
    expected = {"interpolation": 4, "gradient": 3, "laplacian": 2, "gradient_at_sources": 3, "laplacian_at_sources": 2}
    for ax, (title, data) in zip(axes, panels):
        h = np.array(data["h"])
        for k, want in expected.items():
            if k in data:
                e = np.array(data[k])
                ax.loglog(h, e, "o-", label=f"{k} (slope {slope(h, e):.2f})")
                ax.loglog(h, e[-1] * (h / h[-1]) ** want, "k:", lw=0.8)
        ax.set_xlabel("h")
        ax.set_ylabel("max error")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("DC-PSE convergence, m = 4 (dotted: expected orders 4, 3, 2)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------ the results page
#: The orders the theory gives for m = 4 (interpolation m, gradient m - 1, Laplacian m - 2); the paper
#: states 4 and 2 for interpolation and Laplacian (Reboux et al. 2012, Sec. 4.1, Fig. 4.1a).
EXPECTED = {"interpolation": 4, "gradient": 3, "laplacian": 2, "gradient_at_sources": 3, "laplacian_at_sources": 2}
PAPER_ORDERS = {"interpolation": 4, "laplacian": 2}
COLUMNS = {"interpolation": "interpolation", "gradient": "gradient", "laplacian": "Laplacian",
           "gradient_at_sources": "gradient at the particles", "laplacian_at_sources": "Laplacian at the particles"}


def report(res: dict) -> str:
    """The Markdown page of a result (results/dcpse.md is this of results/dcpse.json)."""
    meta, timing_rows, conv, tanh = res["meta"], res["timing"], res["convergence"], res["tanh"]
    stem = "dcpse" + ("_quick" if meta.get("quick") else "")
    m = meta["order"]
    dims = sorted(conv, key=int)
    lines = [
        "# DC-PSE operators: assembly speed and convergence orders",
        "",
        f"The DC-PSE kernels of Reboux et al. (2012), Appendix A (order m = {m}, Gaussian weight with c = "
        f"{meta['c']:g}), built from one set of particles to another (old set -> new set) and at the particles "
        "themselves. The paper states fourth-order interpolation and second-order Laplacians for m = 4 (Sec. 4.1, "
        "Fig. 4.1a); it gives no times per point (its cost breakdown, Fig. 4.12, is in [burgers.md](burgers.md)).",
        "",
        "    python benchmarks/dcpse.py           # the sizes below",
        "    python benchmarks/dcpse.py --quick   # one size per dimension, three resolutions, in seconds",
        "",
        "## Assembly and application",
        "",
        "Sources and new points lie on two independent jittered lattices of N points in the unit square "
        "(cube). Per new point: the cross neighbour list (`arpy.cross_neighbor_list`), the assembly of the "
        "Laplacian and interpolation kernels from one Cholesky factorisation per point, and the same weights "
        "from the NumPy reference (`arpy.reference.dcpse`, timed only at the smaller sizes); per nonzero: one "
        "CSR mat-vec `L @ f` (scipy) and its effective bandwidth. "
        + (f"Best of {meta['repeat']} runs (the reference: one run)." if "repeat" in meta else
           "Best of several runs (the reference: one run)."),
        "",
    ]
    table = []
    for r in timing_rows:
        has_ref = "t_reference" in r
        table.append([f"{r['d']}D", f"{r['n']:,}", f"{r['neighbours']:.1f}", f"{r['us_neighbors']:.2f}",
                      f"{r['us_assembly']:.2f}",
                      f"{1e6 * r['t_reference'] / r['n']:.1f}" if has_ref else "-",
                      f"{r['speedup_vs_reference']:.1f}" if has_ref else "-",
                      f"{r['max_rel_diff_vs_reference']:.1e}" if has_ref else "-",
                      f"{r['ns_apply_per_nnz']:.2f}", f"{r['apply_GBps']:.1f}"])
    lines += md_table(["", "N", "neighbours", "lists (us/point)", "assembly (us/point)",
                       "NumPy reference (us/point)", "speed-up", "max relative difference", "apply (ns/nonzero)",
                       "apply (GB/s)"], table)

    lines += ["", "## Convergence on smooth functions", "",
              "A smooth function on lattices whose spacing varies by a factor 5 across the domain (jittered); "
              "errors are maxima over 500 random points in the middle of the domain (old set -> new set) and over "
              "the particles away from the boundary (at the particles). Orders are least-squares slopes of "
              "log(error) against log(h), h = 1 / (lattice points per side - 1).", ""]
    rows = []
    for d in dims:
        c = conv[d]
        rows.append([f"{d}D, arpy", f"{c['n'][0]:,} to {c['n'][-1]:,}"]
                    + [f"{c['orders'][k]:.2f}" for k in EXPECTED])
    rows.append(["expected (m = 4)", ""] + [str(v) for v in EXPECTED.values()])
    rows.append(["paper (Sec. 4.1)", ""] + [str(PAPER_ORDERS.get(k, "-")) if "sources" not in k else "-"
                                             for k in EXPECTED])
    lines += md_table(["", "N"] + [COLUMNS[k] for k in EXPECTED], rows)

    h, n = tanh["h"], tanh["n"]
    step = {k: [f"{slope(h[i:i + 2], tanh[k][i:i + 2]):.2f}" for i in range(len(h) - 1)]
            for k in ("interpolation", "laplacian")}
    lines += ["", "## The tanh front of Eq. 4.1 on adaptive particles", "",
              "f = tanh((x^2 + y^2 - 0.2^2) / 0.01) on [-1, 1]^2, particles from a quadtree with spacing "
              "D0 / sqrt(1 + |grad f|^2) (the monitor of Eq. 2.8, at least D0 / 16), and the new points a second "
              "such set at 0.95 D0; errors are maxima over |x|, |y| < 0.8, h = sqrt(4 / N). "
              "Order: the slope against the row above.", ""]
    lap = [f"{e:.3g}" if e < 1e3 else f"{e:,.0f}" for e in tanh["laplacian"]]
    lines += md_table(["D0", "N", "h", "interpolation error", "order", "Laplacian error", "order"],
                      [[f"{tanh['D0'][i]:g}", f"{n[i]:,}", f"{h[i]:.4f}", f"{tanh['interpolation'][i]:.2e}",
                        "-" if i == 0 else step["interpolation"][i - 1], lap[i],
                        "-" if i == 0 else step["laplacian"][i - 1]] for i in range(len(h))])

    ref = [r for r in timing_rows if "t_reference" in r]
    lines += ["", "## Findings", ""]
    if ref:
        lines.append(f"- The weights agree with the NumPy reference to "
                     f"{max(r['max_rel_diff_vs_reference'] for r in ref):.0e} relative or better; the Fortran "
                     f"assembly is {min(r['speedup_vs_reference'] for r in ref):.1f} to "
                     f"{max(r['speedup_vs_reference'] for r in ref):.1f} times faster.")
    for d in sorted({r["d"] for r in timing_rows}):
        rr = [r for r in timing_rows if r["d"] == d]
        lo, hi = (f"{f(r['us_assembly'] for r in rr):.1f}" for f in (min, max))
        lines.append(f"- {d}D: the assembly takes {lo if lo == hi else f'{lo} to {hi}'} us per point "
                     + (f"at N = {rr[0]['n']:,}" if len(rr) == 1 else f"from N = {rr[0]['n']:,} to {rr[-1]['n']:,}")
                     + f" (about {rr[0]['neighbours']:.0f} neighbours); the mat-vec runs at "
                     + (f"{rr[0]['apply_GBps']:.1f} GB/s." if len(rr) == 1 else
                        f"{rr[0]['apply_GBps']:.1f} GB/s at the smallest N and {rr[-1]['apply_GBps']:.1f} GB/s at "
                        "the largest."))
    worst = max(abs(conv[d]["orders"][k] - v) for d in dims for k, v in EXPECTED.items())
    lines.append(f"- On smooth functions every fitted order is within {worst:.2f} of the expected one, "
                 "the paper's 4 and 2 included.")
    whole = {k: slope(h, tanh[k]) for k in ("interpolation", "laplacian")}
    lines.append(
        "- On the tanh front the errors converge "
        + ("at lower orders than expected" if min(whole[k] - PAPER_ORDERS[k] for k in whole) < -0.5
           else "at about the expected orders")
        + f": fitted over N = {n[0]:,} to {n[-1]:,}, interpolation {whole['interpolation']:.2f} "
        f"and Laplacian {whole['laplacian']:.2f} (expected 4 and 2), with an order that changes from one "
        "refinement to the next. These particles come from a "
        "quadtree, not from self-organization; the paper's Fig. 4.1 itself (particles self-organized to the "
        "front) is reproduced in [simulation.md](simulation.md).")
    lines += ["", f"![Errors against h: smooth function in {' and '.join(d + 'D' for d in dims)}, and the tanh "
                  f"front (dotted: the expected orders)]({stem}.png)", "",
              f"Run of {meta['date']} on {meta['machine']}, Python {meta['python']}, NumPy {meta['numpy']}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = benchmark_args(__doc__, argv, HERE / "results", lambda parser: parser.add_argument(
        "--repeat", type=int, default=3, help="timing repeats; the best is reported"))
    if args.quick:
        sizes = {2: [10_000], 3: [8_000]}
        sides = {2: [17, 25, 33], 3: [9, 11, 13]}
        d0s = [0.1, 0.05]
    else:
        sizes = {2: [10_000, 100_000, 1_000_000], 3: [10_000, 50_000, 200_000]}
        sides = {2: [17, 33, 65, 129], 3: [9, 13, 17, 21]}
        d0s = [0.2, 0.1, 0.05, 0.025, 0.0125]
    repeat = 1 if args.quick else args.repeat

    print(f"{'d':>2s} {'N':>8s} {'nbrs':>6s} | {'lists':>8s} {'assembly':>9s} {'reference':>10s} {'speed-up':>9s}"
          f" {'rel diff':>9s} | {'apply':>9s} {'GB/s':>6s}")
    print(f"{'':>2s} {'':>8s} {'':>6s} | {'us/pt':>8s} {'us/pt':>9s} {'us/pt':>10s} {'':>9s} {'':>9s} | {'ns/nnz':>9s}")
    rows = []
    for d in (2, 3):
        for n in sizes[d]:
            r = timing(n, d, repeat)
            rows.append(r)
            ref_us = f"{1e6 * r['t_reference'] / r['n']:10.2f}" if "t_reference" in r else f"{'-':>10s}"
            spd = f"{r['speedup_vs_reference']:9.1f}" if "t_reference" in r else f"{'-':>9s}"
            rel = f"{r['max_rel_diff_vs_reference']:9.1e}" if "t_reference" in r else f"{'-':>9s}"
            print(f"{d:2d} {r['n']:8d} {r['neighbours']:6.1f} | {r['us_neighbors']:8.2f} {r['us_assembly']:9.2f} "
                  f"{ref_us} {spd} {rel} | {r['ns_apply_per_nnz']:9.2f} {r['apply_GBps']:6.2f}")

    conv = {d: convergence(d, sides[d]) for d in (2, 3)}
    tanh = tanh_case(d0s)
    print("\nconvergence orders (fitted slopes; expected interpolation 4, gradient 3, Laplacian 2):")
    for d in (2, 3):
        print(f"  {d}D: " + ", ".join(f"{k} {v:.2f}" for k, v in conv[d]["orders"].items()))
    print("  tanh (Eq. 4.1) on adaptive particles, N = " + ", ".join(str(n) for n in tanh["n"]) + ":")
    print("    interpolation errors " + ", ".join(f"{e:.2e}" for e in tanh["interpolation"]))
    print("    Laplacian errors     " + ", ".join(f"{e:.2e}" for e in tanh["laplacian"]))
    print("    orders over the last refinement: " + ", ".join(f"{k} {v:.2f}" for k, v in tanh["orders_last_two"].items()))

    stem = "dcpse" + ("_quick" if args.quick else "")
    meta = {"python": sys.version.split()[0], "numpy": np.__version__, "machine": platform.machine(),
            "date": time.strftime("%Y-%m-%d"), "c": arpy.dcpse.kernel.DEFAULT_C, "order": 4, "repeat": repeat,
            "quick": args.quick}
    (args.out / f"{stem}.json").write_text(json.dumps({"meta": meta, "timing": rows,
                                                        "convergence": {str(d): conv[d] for d in conv},
                                                        "tanh": tanh}, indent=1))
    write_page(args.out, stem, report)
    plot(conv, tanh, args.out / f"{stem}.png")
    print(f"wrote {args.out / (stem + '.json')}, {stem}.md and {stem}.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
