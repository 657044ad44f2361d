"""Benchmark: the adaptive simulation cases of Reboux et al. (2012), §4.1-4.3, with the paper's figures.

  fig41  §4.1 consistency: particles adapted to the tanh front (Eq. 4.1) while
         D0 shrinks by 0.95; errors of the interpolation old -> new and of the
         Laplacian (old particles as sources) vs h = sqrt(|Omega| / N);
         the paper: orders 4 and 2, rugged maxima at low resolution.
  fig41b the same with the monitor of Appendix B (Eq. B.13 for m = 4 from the
         exact fourth derivatives of Eq. 4.1); drawn as fig41's panel (b).
  fig42  §4.2 passive scalar: the blob (Eq. 4.3) in the reversing vortex
         (Eq. 4.4), doubly periodic, RK4, dt = 0.025 to T = 2.5; L-infinity
         error (Eq. 4.5) vs h = 1 / sqrt(N_max) (the paper: order 4) and the
         field at T / 2, with the paper's monitor (Eq. 2.8).
  fig42b the same with the monitor of Appendix B (Eq. B.13 for m = 4, from
         DC-PSE fourth derivatives at every re-organization); drawn into
         fig42's panel (b) next to Eq. 2.8.
  fig42h when the error of fig42 is made: after every re-organization, the
         error against the exact field at that time (characteristics traced
         back, cases.advection_exact), with N(t), for one D0 of each monitor.
  fig42i §4.2's blob without the flow: one interpolation old -> new between
         successive adaptations (D0 <- 0.8 D0), the step every re-organization
         of fig42 repeats; maximum, 99th percentile and median error vs h, the
         D_p and position of the particle with the largest error, and where the
         errors of the finest set sit; with the paper's monitor (Eq. 2.8) and
         with the optimal one of its Appendix B (Eq. B.13, exact 4th derivatives).
  fig43  §4.3 the pulse at Pe = 1e4 after self-organization (the paper: N = 1300)
         and its error at T = 1.
  fig44  §4.3 the Gaussian pulse rotated once and diffused: L-infinity error at
         T = 1 vs h for the adaptive method and the remeshed M'4 baseline,
         (a) 2D, Pe = 1000, h = 2 / sqrt(N); (b) 3D, Pe = 100, h = 3 / N^(1/3)
         (the paper: order 2 for both; in 3D a uniform mesh needs about 50x
         the particles); the ratio of particle counts at equal error, and the
         node count of a uniform mesh as fine as the finest adaptive spacing
         D_min (the paper's finest resolved scale, D0 / max |grad f|); series:
         the paper's monitor (Eq. 2.8) with the ball of Eq. 2.9 (reach 1) and
         twice as wide (reach 2), and Appendix B's monitor (Eq. B.13).
  fig45  §4.3 the relative mass loss (Eq. 4.9) over time for the 2D runs
         (the paper: (D0, N) = (0.04, 8900), (0.06, 3950), (0.08, 2200)),
         with Eq. 2.8 and with Eq. B.13.

Every point (h, N, error, wall time) goes into a JSON, each figure into a PNG, and the results
page (:func:`report`, the JSON next to the paper's values) into Markdown.

    python benchmarks/simulation.py            # full sizes (about two and a half hours)
    python benchmarks/simulation.py --quick    # about 20 s on one core (used by the tests)
    python benchmarks/simulation.py --only fig44 fig45
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from arpy import Domain, cases
from arpy._bench import benchmark_args, md_table, run_info, span, write_page
from arpy.domain import nearest

HERE = Path(__file__).resolve().parent
FIGURES = ("fig41", "fig41b", "fig42", "fig42b", "fig42h", "fig42i", "fig43", "fig44", "fig45")
PAPER_FIG45 = {0.08: 2200, 0.06: 3950, 0.04: 8900}

FULL = dict(
    consistency=dict(d0_start=0.4, d0_end=0.1, factor=0.95),
    consistency_b13=dict(d0_start=0.4, d0_end=0.1, factor=0.95, monitor="fourth"),
    advection=dict(D0=[0.2, 0.16, 0.12, 0.09, 0.06], T=2.5),
    advection_b13=dict(D0=[0.25, 0.2, 0.16, 0.13, 0.11], T=2.5),
    advection_history=dict(D0=dict(gradient=0.12, fourth=0.2), T=2.5),
    blob_interpolation=dict(gradient=dict(d0_start=0.25, d0_end=0.009, factor=0.8),
                            fourth=dict(d0_start=0.25, d0_end=0.026, factor=0.8)),
    pe1e4=dict(D0=0.1, T=1.0),
    pulse2d=dict(T=1.0, mass_every=20, series=[
        dict(monitor="gradient", reach=1.0, D0=[0.08, 0.06, 0.04, 0.03]),
        dict(monitor="gradient", reach=2.0, D0=[0.08, 0.06, 0.04, 0.03]),
        dict(monitor="fourth", reach=1.0, D0=[0.25, 0.2, 0.15, 0.12, 0.1, 0.08])]),
    remeshed2d=dict(n_cells=[64, 128, 256], T=1.0),
    pulse3d=dict(T=1.0, series=[
        dict(monitor="gradient", reach=1.0, D0=[0.3, 0.22, 0.16, 0.12]),
        dict(monitor="gradient", reach=2.0, D0=[0.3, 0.22, 0.16, 0.12]),
        dict(monitor="fourth", reach=1.0, D0=[0.6, 0.45, 0.35, 0.27, 0.22])]),
    remeshed3d=dict(n_cells=[24, 32, 48, 64, 96], T=1.0),
)
#: --quick: the smallest sizes that still run every figure's code path (tests/test_cli_and_benchmarks.py;
#: the orders themselves are tested in tests/test_simulation.py); §4.1 on the milder front W = 0.1.
QUICK = dict(
    consistency=dict(d0_start=0.4, d0_end=0.32, factor=0.9, width=0.1),
    consistency_b13=dict(d0_start=0.4, d0_end=0.32, factor=0.9, width=0.1, monitor="fourth"),
    advection=dict(D0=[0.28, 0.25], T=0.05),
    advection_b13=dict(D0=[0.28, 0.26], T=0.05),
    advection_history=dict(D0=dict(gradient=0.28, fourth=0.28), T=0.125),
    blob_interpolation=dict(gradient=dict(d0_start=0.28, d0_end=0.175, factor=0.8),
                            fourth=dict(d0_start=0.28, d0_end=0.175, factor=0.8)),
    pe1e4=dict(D0=0.4, T=0.002),
    pulse2d=dict(T=0.02, mass_every=0, mass_points=101,
                 series=[dict(monitor="gradient", reach=1.0, D0=[0.2, 0.16]),
                         dict(monitor="gradient", reach=2.0, D0=[0.2, 0.16]),
                         dict(monitor="fourth", reach=1.0, D0=[0.5, 0.4])]),
    remeshed2d=dict(n_cells=[32, 64], T=0.02),
    pulse3d=dict(T=0.02, mass_points=21, series=[dict(monitor="gradient", reach=1.0, D0=[0.8]),
                                                 dict(monitor="fourth", reach=1.0, D0=[1.2])]),
    remeshed3d=dict(n_cells=[16, 24], T=0.02),
)


def _decorate(ax, xlabel: str, ylabel: str, title: str) -> None:
    """Axis labels, title, legend and a log grid of one panel."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)


def run_fig41(p: dict, result: dict) -> None:
    monitor = p.get("monitor", "gradient")
    key = "fig41" if monitor == "gradient" else "fig41b"
    print(f"\nFig. 4.1 (§4.1): interpolation and Laplacian on the tanh front, D0 <- {p['factor']} D0, "
          f"monitor: {MONITORS[monitor]}")
    t = time.perf_counter()
    r = cases.consistency(**p, progress=True)
    wall = time.perf_counter() - t
    rows = [dict(D0=float(r["D0"][k]), N=int(r["N"][k]), h=float(r["h"][k]), err_interp=float(r["err_interp"][k]),
                 err_laplacian=float(r["err_laplacian"][k]), median_interp=float(r["median_interp"][k]),
                 median_laplacian=float(r["median_laplacian"][k]), p99_interp=float(r["p99_interp"][k]),
                 D_at_max=float(r["D_at_max"][k])) for k in range(len(r["N"]))]
    slopes = dict(max_interp=r["slope_interp"], max_laplacian=r["slope_laplacian"],
                  p99_interp=cases.slope(r["h"], r["p99_interp"]),
                  median_interp=cases.slope(r["h"], r["median_interp"]),
                  median_laplacian=cases.slope(r["h"], r["median_laplacian"]))
    result[key] = dict(monitor=monitor, rows=rows, slopes=slopes, wall_s=wall,
                       paper_slopes=dict(interp=4, laplacian=2))
    print(f"{'D0':>7s} {'N':>7s} {'h':>8s} | {'max interp':>10s} {'max lap':>10s} | {'med interp':>10s} "
          f"{'med lap':>10s}")
    shown = rows[:: max(1, len(rows) // 12)]
    for row in shown + ([rows[-1]] if shown[-1] is not rows[-1] else []):
        print(f"{row['D0']:7.4f} {row['N']:7d} {row['h']:8.5f} | {row['err_interp']:10.2e} "
              f"{row['err_laplacian']:10.2e} | {row['median_interp']:10.2e} {row['median_laplacian']:10.2e}")
    print("  fitted orders: " + ", ".join(f"{k} {v:.2f}" for k, v in slopes.items()) + f"  ({wall:.0f} s)")


def run_fig42(p: dict, result: dict, monitor: str = "gradient") -> dict:
    key = "fig42" if monitor == "gradient" else "fig42b"
    print(f"\nFig. 4.2 (§4.2): blob in the reversing vortex, RK4 dt = 0.025, T = {p['T']}, monitor: {MONITORS[monitor]}")
    print(f"{'D0':>6s} {'N_max':>7s} {'N(T)':>7s} {'h':>8s} {'error':>10s} {'median':>10s} {'steps':>6s} {'wall s':>7s}")
    rows, half = [], None
    for d0 in p["D0"]:
        r = cases.advection(D0=d0, T=p["T"], monitor=monitor)
        rows.append(dict(D0=d0, N=r["N"], N_max=r["N_max"], h=r["h"], error=r["error"],
                         median_error=r["median_error"], steps=r["steps"], wall_s=r["wall_s"],
                         degenerate_max=int(r["sim"].history()["degenerate"].max())))
        half = r["half"]
        print(f"{d0:6.3f} {r['N_max']:7d} {r['N']:7d} {r['h']:8.5f} {r['error']:10.3e} {r['median_error']:10.3e} "
              f"{r['steps']:6d} {r['wall_s']:7.1f}")
    h = np.array([r["h"] for r in rows])
    order = cases.slope(h, np.array([r["error"] for r in rows]))
    median_order = cases.slope(h, np.array([r["median_error"] for r in rows]))
    result[key] = dict(monitor=monitor, rows=rows, order=order, median_order=median_order, paper_order=4)
    print(f"  fitted order {order:.2f} of the maximum (paper: 4), {median_order:.2f} of the median")
    return half


MONITORS = {"gradient": "Eq. 2.8 (the paper's monitor)", "fourth": "Eq. B.13 (4th derivatives)"}


def run_fig42h(p: dict, result: dict) -> None:
    print(f"\nFig. 4.2, error history: error of Eq. 4.5 after each re-organization, T = {p['T']}")
    out = {}
    for monitor, d0 in p["D0"].items():
        r = cases.advection(D0=d0, T=p["T"], monitor=monitor, error_history=True)
        t, e = r["history"]["t"], r["history"]["max"]
        reached = float(t[np.argmax(e >= 0.9 * r["error"])])
        out[monitor] = dict(D0=d0, error=r["error"], N_max=r["N_max"], wall_s=r["wall_s"], t_90=reached,
                            **{k: v.tolist() for k, v in r["history"].items()})
        print(f"  {MONITORS[monitor]}, D0 = {d0}: error at T {r['error']:.3e} (N_max {r['N_max']}); 90 % of it "
              f"reached by t = {reached:.3g}; max error at t = T/4, T/2: "
              f"{np.interp(p['T'] / 4, t, e):.2e}, {np.interp(p['T'] / 2, t, e):.2e}")
    result["fig42h"] = out


def run_fig42i(p: dict, result: dict) -> None:
    result["fig42i"] = {}
    for kind, label in MONITORS.items():
        print(f"\nFig. 4.2, without the flow: the blob interpolated between successive adaptations, D0 <- "
              f"{p[kind]['factor']} D0 (errors / max f); monitor {label}")
        result["fig42i"][kind] = _blob_interpolation(p[kind], kind)


def _blob_interpolation(p: dict, kind: str) -> dict:
    t = time.perf_counter()
    r = cases.consistency(**p, field="blob", monitor=kind, progress=True)
    wall = time.perf_counter() - t

    def radius(x):                                   # distance from the blob's centre (its edge: r = C2 = 0.168)
        return nearest(np.array([cases.X0]), y=x, domain=Domain([1.0, 1.0], periodic=True))[0]

    dist = radius(r["x_at_max"])
    rows = [dict(D0=float(r["D0"][k]), N=int(r["N"][k]), h=float(r["h"][k]), err_interp=float(r["err_interp"][k]),
                 median_interp=float(r["median_interp"][k]), p99_interp=float(r["p99_interp"][k]),
                 err_laplacian=float(r["err_laplacian"][k]),
                 median_laplacian=float(r["median_laplacian"][k]), D_at_max=float(r["D_at_max"][k]),
                 r_at_max=float(dist[k]), failed=int(r["failed"][k])) for k in range(len(r["N"]))]
    out = dict(rows=rows, slope_max=r["slope_interp"], slope_p99=cases.slope(r["h"], r["p99_interp"]),
               slope_median=cases.slope(r["h"], r["median_interp"]), wall_s=wall)
    keys = ("err_interp", "p99_interp", "median_interp")
    print(f"{'D0':>7s} {'N':>7s} {'h':>8s} | {'max':>9s} {'order':>6s} {'99 %':>9s} {'order':>6s} {'median':>9s} "
          f"{'order':>6s} | {'D_p at max':>10s} {'r at max':>8s} {'failed':>6s}")
    for k, row in enumerate(rows):
        o = ("", "", "")
        if k:
            lh = np.log(rows[k - 1]["h"] / row["h"])
            o = tuple(f"{np.log(rows[k - 1][key] / row[key]) / lh:6.2f}" for key in keys)
        cols = " ".join(f"{row[key]:9.2e} {oo:>6s}" for key, oo in zip(keys, o))
        print(f"{row['D0']:7.4f} {row['N']:7d} {row['h']:8.5f} | {cols} | {row['D_at_max']:10.4f} "
              f"{row['r_at_max']:8.3f} {row['failed']:6d}")
    print(f"  fitted orders: maximum {out['slope_max']:.2f}, 99th percentile {out['slope_p99']:.2f}, "
          f"median {out['slope_median']:.2f}  ({wall:.0f} s)")
    # where the errors of the finest set sit: bands of distance from the blob's centre
    last, d0 = r["last"], rows[-1]["D0"]
    dist = radius(last["x"])
    d_tilde = cases.blob_monitor(last["x"], d0, kind)
    bands = []
    print(f"  the finest set (D0 = {d0:.4f}) by distance r from the centre:")
    print(f"  {'r':>12s} {'particles':>9s} {'max error':>9s} {'D_p / D0':>8s} {'D_p / D~':>8s}"
          "   (medians of the ratios)")
    for lo, hi in ((0, 0.1), (0.1, 0.14), (0.14, 0.2), (0.2, 0.24), (0.24, 0.3), (0.3, 1.0)):
        m = (dist >= lo) & (dist < hi)
        if m.any():
            bands.append(dict(r_lo=lo, r_hi=hi, n=int(m.sum()), max_error=float(last["err_interp"][m].max()),
                              D_over_D0=float(np.median(last["D"][m] / d0)),
                              D_over_Dtilde=float(np.median(last["D"][m] / d_tilde[m]))))
            b = bands[-1]
            print(f"  {lo:5.2f} - {hi:4.2f} {b['n']:9d} {b['max_error']:9.2e} {b['D_over_D0']:8.3f} "
                  f"{b['D_over_Dtilde']:8.3f}")
    out["bands"] = bands
    return out


def run_fig43(p: dict, result: dict) -> object:
    print(f"\nFig. 4.3 (§4.3): the pulse at Pe = 1e4, D0 = {p['D0']}, run to T = {p['T']}")
    r = cases.gaussian_pulse(d=2, Pe=1e4, D0=p["D0"], T=p["T"], mass_points=11)     # (its mass is not reported)
    result["fig43"] = dict(D0=p["D0"], Pe=1e4, N_initial=r["N_initial"], N_max=r["N_max"], h=r["h"],
                           error=r["error"], T=p["T"], steps=r["steps"], wall_s=r["wall_s"], paper_N=1300)
    print(f"  N after self-organization {r['N_initial']} (paper: 1300), error at T {r['error']:.3e}, "
          f"{r['steps']} steps in {r['wall_s']:.1f} s")
    return r


#: The figures made by one run function each: (function, its entry of QUICK / FULL, further arguments).
RUNS = {"fig41": (run_fig41, "consistency", ()), "fig41b": (run_fig41, "consistency_b13", ()),
        "fig42": (run_fig42, "advection", ()), "fig42b": (run_fig42, "advection_b13", ("fourth",)),
        "fig42h": (run_fig42h, "advection_history", ()), "fig42i": (run_fig42i, "blob_interpolation", ()),
        "fig43": (run_fig43, "pe1e4", ())}


def series_key(monitor: str, reach: float) -> str:
    """The name of a series of adaptive pulse runs: "reach 1" (the paper's Eq. 2.8 and
    Eq. 2.9), "reach 2", "B.13, reach 1" (Appendix B's monitor)."""
    return ("" if monitor == "gradient" else "B.13, ") + f"reach {reach:g}"


def series_label(monitor: str, reach: float) -> str:
    """The legend of a series of adaptive pulse runs (see :func:`series_key`)."""
    label = "adaptive, Eq. " + ("2.8" if monitor == "gradient" else "B.13")
    if reach != 1:
        return label + f", reach {reach:g}"
    return label + (" (the paper's)" if monitor == "gradient" else "")


def run_pulse(d: int, p: dict, q: dict) -> dict:
    """Adaptive runs (p: one series for each monitor and reach of Eq. 2.9) and remeshed
    runs (q) of the pulse in d dimensions; fitted orders and particle ratios at equal error."""
    print(f"{'method':>9s} {'series':>13s} {'D0/cells':>8s} {'N':>7s} {'h':>8s} {'error':>10s} {'mass loss':>10s} "
          f"{'steps':>6s} {'wall s':>7s}")
    edge = 2.0 if d == 2 else 3.0
    remeshed = []
    for m in q["n_cells"]:
        r = cases.remeshed_pulse(d=d, n_cells=m, T=q["T"])
        remeshed.append(dict(n_cells=m, N=r["N"], h=r["h"], error=r["error"], mass_loss=float(r["mass_loss"]),
                             steps=r["steps"], wall_s=r["wall_s"]))
        print(f"{'remeshed':>9s} {'':>13s} {m:8d} {r['N']:7d} {r['h']:8.5f} {r['error']:10.3e} "
              f"{r['mass_loss']:10.2e} {r['steps']:6d} {r['wall_s']:7.1f}")
    nr, er = np.array([r["N"] for r in remeshed], float), np.array([r["error"] for r in remeshed])
    out = dict(remeshed=remeshed, adaptive={}, h_definition=f"{edge:g} / N^(1/{d})", orders={}, particle_ratio={})
    if len(remeshed) >= 2:
        out["orders"]["remeshed"] = cases.slope(edge / nr ** (1 / d), er)
    for series in p["series"]:
        monitor, reach = series["monitor"], series["reach"]
        key = series_key(monitor, reach)
        rows = []
        for d0 in series["D0"]:
            r = cases.gaussian_pulse(d=d, D0=d0, T=p["T"], mass_every=p.get("mass_every", 0), reach=reach,
                                     monitor=monitor, mass_points=p.get("mass_points"))
            d_min = float(r["particles"].D.min())
            uniform = uniform_count(edge, d_min, d)
            rows.append(dict(D0=d0, reach=reach, monitor=monitor, N_initial=r["N_initial"], N=r["N_max"], N_final=r["N"],
                             N_mean=float(r["sim"].history()["n"].mean()), h=r["h"], error=r["error"],
                             steps=r["steps"], wall_s=r["wall_s"], mass_t=r["mass_t"].tolist(),
                             mass_loss=r["mass_loss"].tolist(), D_min=d_min, uniform_N_at_D_min=uniform,
                             paper_N=PAPER_FIG45.get(d0) if d == 2 and key == "reach 1" else None))
            print(f"{'adaptive':>9s} {key:>13s} {d0:8.3f} {r['N_max']:7d} {r['h']:8.5f} {r['error']:10.3e} "
                  f"{r['mass_loss'][-1]:10.2e} {r['steps']:6d} {r['wall_s']:7.1f}   D_min {d_min:.4f}, "
                  f"a mesh of that spacing: {uniform} nodes ({uniform / r['N_max']:.1f}x)")
        out["adaptive"][key] = rows
        na, ea = np.array([r["N"] for r in rows], float), np.array([r["error"] for r in rows])
        if len(rows) >= 2:
            out["orders"][f"adaptive, {key}"] = cases.slope(edge / na ** (1 / d), ea)
            for which in ("N_final", "N_mean"):
                nb = np.array([r[which] for r in rows], float)
                out["orders"][f"adaptive, {key}, h from {which}"] = cases.slope(edge / nb ** (1 / d), ea)
        if len(remeshed) >= 2:
            ratio = cases.equal_error_ratio(nr, er, na, ea)
            for row, x in zip(rows, ratio):
                row["remeshed_N_at_equal_error"] = float(x * row["N"])
                row["particle_ratio"] = float(x)
            out["particle_ratio"][key] = ratio.tolist()
    print("  fitted orders (paper: 2): " + ", ".join(f"{k} {v:.2f}" for k, v in out["orders"].items()))
    for key, ratio in out["particle_ratio"].items():
        print(f"  remeshed particles / adaptive particles at equal error ({key}): "
              + ", ".join(f"{x:.1f}" for x in ratio))
    return out


def uniform_count(edge: float, spacing: float, d: int) -> int:
    """Nodes of a uniform mesh of the box (edge^d) no coarser than ``spacing``,
    counted like the remeshed baseline's: (cells + 1)^d."""
    return int((np.ceil(edge / spacing) + 1) ** d)


def plot_all(result: dict, half: dict | None, pe1e4, tag: str, out: Path) -> list[Path]:
    import matplotlib.pyplot as plt

    from arpy.plotting import plot_particles, save_figure, slope_lines

    written = []

    def save(fig, name):
        path = out / f"{tag}_{name}.png"
        save_figure(fig, path)
        written.append(path)

    panels = [k for k in ("fig41", "fig41b") if k in result]
    if panels:
        fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4.6), squeeze=False, sharex=True,
                                 sharey=True)
        for ax, key, letter in zip(axes[0], panels, "ab"):
            res = result[key]
            rows, sl = res["rows"], res["slopes"]
            h = np.array([r["h"] for r in rows])
            for col, label, style in (("err_laplacian", f"Laplacian, max ({sl['max_laplacian']:.2f})", "o-"),
                                      ("median_laplacian", "Laplacian, median", "o:"),
                                      ("err_interp", f"interpolation, max ({sl['max_interp']:.2f})", "s-"),
                                      ("median_interp", "interpolation, median", "s:")):
                ax.loglog(h, [r[col] for r in rows], style, ms=3, label=label)
            slope_lines(ax, h, np.array([r["err_laplacian"] for r in rows]), [2])
            slope_lines(ax, h, np.array([r["err_interp"] for r in rows]), [4])
            monitor = MONITORS[res.get("monitor", "gradient")].split(" (")[0]
            _decorate(ax, "h = sqrt(|Omega| / N)", "error", f"Fig. 4.1a ({letter}): tanh front, m = 4, {monitor}")
        save(fig, "fig41")

    if "fig42" in result or "fig42b" in result:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.8))
        if half:
            sc = axes[0].scatter(half["x"][:, 0], half["x"][:, 1], c=half["f"], s=2, cmap="viridis")
            fig.colorbar(sc, ax=axes[0], label="f")
            axes[0].set_aspect("equal")
            axes[0].set_title(f"(a) t = T/2, N = {len(half['f'])}")
        for key, color in (("fig42", "C0"), ("fig42b", "C3")):
            if key not in result:
                continue
            res = result[key]
            rows, label = res["rows"], MONITORS[res.get("monitor", "gradient")].split(" (")[0]
            h, e = np.array([r["h"] for r in rows]), np.array([r["error"] for r in rows])
            axes[1].loglog(h, e, "o-", color=color, label=f"{label}: maximum (order {res['order']:.2f})")
            axes[1].loglog(h, [r["median_error"] for r in rows], "s--", color=color, ms=4,
                           label=f"{label}: median (order {res['median_order']:.2f})")
            slope_lines(axes[1], h, e, [4])
        _decorate(axes[1], "h = 1 / sqrt(N_max)", "error of Eq. 4.5", "(b) Fig. 4.2b")
        save(fig, "fig42")

    if "fig42h" in result:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))
        for (monitor, run), color in zip(result["fig42h"].items(), ("C0", "C3")):
            label = f"{MONITORS[monitor].split(' (')[0]}, D0 = {run['D0']}"
            axes[0].semilogy(run["t"], run["max"], "-", color=color, label=f"{label}: maximum")
            axes[0].semilogy(run["t"], run["median"], "--", color=color, label=f"{label}: median")
            axes[1].plot(run["t"], run["N"], "-", color=color, label=label)
        _decorate(axes[0], "t", "error of Eq. 4.5 vs the exact field at t", "(a) error after each re-organization")
        _decorate(axes[1], "t", "N", "(b) particles")
        save(fig, "fig42h")

    if "fig42i" in result:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
        for (kind, label), color in zip(MONITORS.items(), ("C0", "C3")):
            run = result["fig42i"][kind]
            rows = run["rows"]
            h = np.array([r["h"] for r in rows])
            axes[0].loglog(h, [r["err_interp"] for r in rows], "o-", color=color,
                           label=f"{label}: maximum (order {run['slope_max']:.2f})")
            axes[0].loglog(h, [r["p99_interp"] for r in rows], "^-.", color=color, mfc="none",
                           label=f"99th percentile ({run['slope_p99']:.2f})")
            axes[0].loglog(h, [r["median_interp"] for r in rows], "s:", color=color, ms=3,
                           label=f"median ({run['slope_median']:.2f})")
            d0 = np.array([r["D0"] for r in rows])
            axes[1].loglog(d0, [r["D_at_max"] for r in rows], "o-", color=color, label=f"D_p at the max, {label}")
            if kind == "gradient":
                slope_lines(axes[0], h, np.array([r["err_interp"] for r in rows]), [4])
                axes[1].loglog(d0, d0, "k:", label="D0")
                axes[1].loglog(d0, d0 / cases.BLOB_MAX_SLOPE, "k--", label="D0 / max|grad f| (Eq. 2.8's finest)")
        _decorate(axes[0], "h = 1 / sqrt(N)", "interpolation error / max f",
                  "(a) the blob (Eq. 4.3), one interpolation old -> new")
        _decorate(axes[1], "D0", "D_p", "(b) the resolution where the maximum sits")
        save(fig, "fig42i")

    if pe1e4 is not None:
        ps0 = pe1e4["particles"]
        fig, axes = plt.subplots(1, 3, figsize=(15, 4.8))
        f0 = cases.pulse_exact(ps0.x, 0.0, np.array([0.58, 0.02]), 1e4, 2)
        for ax, (c, half_width), name in zip(axes, (((0.0, 0.0), 1.0), ((0.58, 0.02), 0.15), ((0.58, 0.02), 0.05)),
                                             ("a", "b", "c")):
            plot_particles(ps0, ax=ax, color=f0, circles=0, colorbar=False, size=4 if half_width < 1 else 2,
                           title=f"({name}) N = {ps0.n}" if name == "a" else f"({name}) close-up")
            ax.set_xlim(c[0] - half_width, c[0] + half_width)
            ax.set_ylim(c[1] - half_width, c[1] + half_width)
        fig.suptitle(f"Fig. 4.3: pulse at Pe = 1e4 after self-organization (D0 = {result['fig43']['D0']}); "
                     f"L-inf error at T = {result['fig43']['T']}: {result['fig43']['error']:.2e}")
        save(fig, "fig43")

    if "fig44" in result:
        panels = [k for k in ("2d", "3d") if k in result["fig44"]]
        fig, axes = plt.subplots(1, len(panels), figsize=(5.8 * len(panels), 4.6), squeeze=False)
        for ax, key in zip(axes[0], panels):
            r = result["fig44"][key]
            d = 2 if key == "2d" else 3
            edge = 2.0 if d == 2 else 3.0
            series = [(rows, series_label(rows[0]["monitor"], rows[0]["reach"]),
                       "o-" if rows[0]["monitor"] == "gradient" else "^-")
                      for rows in r["adaptive"].values() if rows] + [(r["remeshed"], "remeshed LPM", "s-")]
            for rows, label, style in series:
                if rows:
                    h = edge / np.array([x["N"] for x in rows], float) ** (1 / d)
                    e = np.array([x["error"] for x in rows])
                    ax.loglog(h, e, style, mfc="none" if style != "s-" else None, label=label)
            first = r["adaptive"].get(series_key("fourth", 1.0)) or next(iter(r["adaptive"].values()), [])
            if first:
                h = edge / np.array([x["N"] for x in first], float) ** (1 / d)
                slope_lines(ax, h, np.array([x["error"] for x in first]), [2])
            _decorate(ax, f"h = {r['h_definition']}", "L-infinity error at T",
                      f"Fig. 4.4{'a' if d == 2 else 'b'}: {d}D, Pe = {1000 if d == 2 else 100}")
        save(fig, "fig44")

    if "fig44" in result and "2d" in result["fig44"]:
        runs = result["fig44"]["2d"]["adaptive"]
        panels = [(k, t) for k, t in ((series_key("gradient", 1.0), "Eq. 2.8 (the paper's)"),
                                      (series_key("fourth", 1.0), "Eq. B.13")) if k in runs]
        fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4.4), squeeze=False, sharey=True)
        for ax, (key, title) in zip(axes[0], panels):
            for r in runs[key]:
                ax.plot(r["mass_t"], r["mass_loss"], "o-", ms=2, label=f"D0 = {r['D0']}, N = {r['N']}")
            ax.set_xlabel("t")
            ax.set_ylabel("relative mass loss (Eq. 4.9)")
            ax.set_title(f"Fig. 4.5: 2D pulse, Pe = 1000, {title}")
            ax.legend(fontsize=8)
            ax.grid(True, alpha=0.3)
        save(fig, "fig45")
    return written


# ------------------------------------------------------------------ the results page
#: The paper's published values (Reboux et al. 2012), shown next to arpy's on the results page.
PAPER = dict(
    fig41_orders=dict(interp=4, laplacian=2),   # §4.1 / Fig. 4.1a: interpolation and Laplacian, m = 4
    fig41_d0=(0.4, 0.006), fig41_n=(102, 2e5),  # §4.1: "D0 decreases from 0.4 to 0.006", N "from 102 to 2e5"
    front_radius=0.2,                           # Eq. 4.1: tanh((x^2 + y^2 - 0.2^2) / 0.01)
    fig42_order=4,                              # §4.2 / Fig. 4.2b
    fig43_n=1300,                               # Fig. 4.3: Pe = 1e4
    fig44_order=2,                              # Fig. 4.4a and b
    fig44_ratio=50,                             # §4.3, 3D: a uniform mesh needs "about 50 times" the particles
    fig44_finest=0.23,                          # §4.3: D0 / max|grad f| is "approximately 0.23 D0 for Pe = 100"
    fig45_n=PAPER_FIG45)                        # Fig. 4.5: (D0, N)
#: The results page's name for each series of adaptive pulse runs (see :func:`series_key`).
SERIES = {"reach 1": "Eq. 2.8", "reach 2": "Eq. 2.8, reach 2", "B.13, reach 1": "Eq. B.13"}


def case_settings() -> dict:
    """What the cases run with that this script leaves at their defaults (stored in the JSON)."""
    import inspect

    def defaults(fn):
        return {k: p.default for k, p in inspect.signature(fn).parameters.items()}

    cons, adv, pulse = defaults(cases.consistency), defaults(cases.advection), defaults(cases.gaussian_pulse)
    return dict(consistency_width=cons["width"], advection_dt=adv["dt"], advection_every=adv["reorganize_every"],
                pulse_every=pulse["reorganize_every"], pulse_integrator=pulse["integrator"],
                pulse_pe={str(d): pe for d, pe in cases.PULSE_PE.items()})


def _e(x: float) -> str:
    """An error for the page: 3.17e-3, or 211 between 1 and 1000."""
    if 1 <= abs(x) < 1000:
        return f"{x:.3g}"
    m, ex = f"{x:.2e}".split("e")
    return f"{m}e{int(ex)}"


def _near(order: float, paper: float) -> bool:
    """Whether a fitted order is the paper's (within the tests' tolerance of 0.5)."""
    return abs(order - paper) <= 0.5


def _wall(seconds: float) -> str:
    """A wall time in seconds: 0.03, 7.5, 231."""
    return f"{seconds:.2g}" if seconds < 1 else f"{seconds:.1f}" if seconds < 10 else f"{seconds:.0f}"


def _x(x: float) -> str:
    """A ratio for the page: 12.8 (three figures at most)."""
    return f"{x:.0f}" if abs(x) >= 100 else f"{x:.1f}" if abs(x) >= 10 else f"{x:.2g}" if abs(x) < 1 else f"{x:.1f}"


def _o(x: float) -> str:
    """An order of convergence: 1.24."""
    return f"{x:.2f}"


def _g(x: float) -> str:
    """A parameter: 0.08, 1e+04 -> 10000."""
    return f"{x:g}" if abs(x) < 1e5 else f"{x:.0e}"


def _span(values, fmt=_x) -> str:
    """The range of some values, "a–b" (one value if they agree in print)."""
    return span(values, fmt)


def _table(head: list[str], rows: list[list]) -> str:
    return "\n".join(md_table(head, rows))


def _pairwise(h, e) -> list[float]:
    """The order between each two successive (h, error) points."""
    return [float(np.log(e[k - 1] / e[k]) / np.log(h[k - 1] / h[k])) for k in range(1, len(h))]


def _at(n_ref, e_ref, n: float) -> float | None:
    """e_ref at n, interpolated in log-log between the points (n_ref, e_ref); None outside them."""
    order = np.argsort(n_ref)
    n_ref, e_ref = np.asarray(n_ref, float)[order], np.asarray(e_ref, float)[order]
    if not n_ref[0] <= n <= n_ref[-1]:
        return None
    return float(np.exp(np.interp(np.log(n), np.log(n_ref), np.log(e_ref))))


def _col(rows: list[dict], key: str) -> np.ndarray:
    return np.array([r[key] for r in rows], float)


def _fig(tag: str, name: str, caption: str) -> str:
    return f"![{caption}]({tag}_{name}.png)"


def _head(res: dict, quick: bool, settings: dict) -> str:
    text = ["# Adaptive simulations: Figs. 4.1–4.5 of Reboux et al. (2012)",
            "How closely arpy reproduces §4.1–4.3 of the JCP paper: the consistency of interpolation and "
            "Laplacian (Fig. 4.1), a passive scalar in a reversing vortex (Fig. 4.2) and a Gaussian pulse "
            "rotated and diffused in 2D and 3D (Figs. 4.3–4.5). `python benchmarks/simulation.py` makes "
            "`results/simulation.json`, the figures and this page (full sizes, hours on one core; "
            "`--only fig44 fig45` re-runs some figures and merges them into the JSON). `--quick` runs every "
            "figure at the smallest sizes in a few seconds and writes `simulation_quick.*` (the tests use it). "
            "`python benchmarks/report.py simulation` rewrites this page from the JSON."]
    if quick:
        text.append("**These are the `--quick` sizes.** They run every code path but are far too small for "
                    "the orders and ratios to mean anything; the explanations below are those of the full run.")
    if "machine" in res:
        text.append(f"Machine: {res['machine']}, Python {res.get('python', '?')}. Wall times are as measured there.")
    text.append("In all runs the DC-PSE operators and interpolation have m = 4, as in the paper. Errors are "
                "maxima (L∞) against the exact solutions, unless stated; orders are least-squares slopes of "
                "log(error) against log(h). Two resolution monitors are compared: the paper's Eq. 2.8, "
                "D̃ = D0 / √(1 + |∇f|²), and Eq. B.13 of its Appendix B for m = 4, "
                "D̃ = D0 (1 + max over |β| = 4 of |∂^β f|)^(−1/4), the resolution that equidistributes the "
                "interpolation error. \"reach\" is the factor on the ball of Eq. 2.9 (1: the paper's).")
    return "\n\n".join(text)


def _summary(res: dict) -> str:
    rows = []
    if "fig41" in res:
        b = res.get("fig41b", {}).get("slopes", {})
        for key, name, paper in (("max_interp", "interpolation", "interp"),
                                 ("max_laplacian", "Laplacian", "laplacian")):
            rows.append(["4.1", f"order of the {name}'s maxima", PAPER["fig41_orders"][paper],
                         _o(res["fig41"]["slopes"][key]), _o(b[key]) if key in b else "–"])
    if "fig42" in res:
        rows.append(["4.2", "order of the maximum error (Eq. 4.5)", PAPER["fig42_order"],
                     _o(res["fig42"]["order"]), _o(res["fig42b"]["order"]) if "fig42b" in res else "–"])
    if "fig43" in res:
        rows.append(["4.3", "N after self-organization, Pe = 10⁴", PAPER["fig43_n"], res["fig43"]["N_initial"],
                     "–"])
    for d, fig in (("2d", "4.4a"), ("3d", "4.4b")):
        orders = res.get("fig44", {}).get(d, {}).get("orders", {})
        if orders:
            remeshed = _o(orders["remeshed"]) if "remeshed" in orders else "–"
            rows.append([fig, f"order, {d.upper()} (remeshed: {remeshed})", PAPER["fig44_order"],
                         *(_o(orders.get(f"adaptive, {k}", np.nan)) for k in ("reach 1", "B.13, reach 1"))])
    three = res.get("fig44", {}).get("3d", {}).get("adaptive", {})
    if three:
        cells = []
        for key in ("reach 1", "B.13, reach 1"):
            rs = three.get(key, [])
            eq = [r["particle_ratio"] for r in rs if "particle_ratio" in r]
            fine = [r["uniform_N_at_D_min"] / r["N"] for r in rs]
            cells.append(f"{_span(eq)}× at equal error; {_span(fine)}× at equal finest spacing"
                         if eq and fine else "–")
        rows.append(["4.4b", "uniform-mesh particles / adaptive particles, 3D", f"about {PAPER['fig44_ratio']}×",
                     *cells])
    two = res.get("fig44", {}).get("2d", {}).get("adaptive", {}).get("reach 1", [])
    paper = [(r["D0"], PAPER["fig45_n"][r["D0"]], r["N"]) for r in two if r["D0"] in PAPER["fig45_n"]]
    if paper:
        rows.append(["4.5", "N at D0 = " + ", ".join(_g(d) for d, _, _ in paper),
                     ", ".join(str(p) for _, p, _ in paper), ", ".join(str(n) for _, _, n in paper), "–"])
    if not rows:
        return ""
    return "## Summary\n\n" + _table(["Fig.", "quantity", "paper", "arpy, Eq. 2.8 (the paper's monitor)",
                                      "arpy, Eq. B.13"], rows)


def _fig41(res: dict, tag: str, settings: dict) -> str:
    if "fig41" not in res:
        return ""
    par = res["parameters"]["consistency"]
    width = par.get("width", settings["consistency_width"])
    a, b = res["fig41"], res.get("fig41b")
    ra = a["rows"]
    rb = b["rows"] if b and [r["D0"] for r in b["rows"]] == [r["D0"] for r in ra] else None
    out = ["## Fig. 4.1: consistency on the tanh front (§4.1)",
           f"The front of Eq. 4.1 with W = {_g(width)} on [−1, 1]² with walls. Particles are adapted to it from "
           f"D0 = {_g(par['d0_start'])} down to {_g(par['d0_end'])} by D0 ← {_g(par['factor'])} D0 ({len(ra)} sets); "
           "each set's values are interpolated from the previous set's exact ones, and the Laplacian is applied "
           "with the previous set as sources. Errors are taken at the new particles; h = √(|Ω| / N). The paper "
           f"goes from D0 = {_g(PAPER['fig41_d0'][0])} to {_g(PAPER['fig41_d0'][1])} (N from about "
           f"{PAPER['fig41_n'][0]} to {PAPER['fig41_n'][1]:.0f}). Selected sets (all are in the JSON):"]
    step = max(1, len(ra) // 6)
    picks = sorted(set(range(0, len(ra), step)) | {len(ra) - 1})
    head = ["D0", "N", "max interp.", "max Laplacian", "D_p at the max"]
    if rb:
        head = ["D0", "N, Eq. 2.8", "max interp.", "max Laplacian", "D_p at the max", "N, Eq. B.13", "max interp.",
                "max Laplacian", "D_p at the max"]
    rows = []
    for k in picks:
        row = [f"{ra[k]['D0']:.3f}"]
        for r in (ra, rb) if rb else (ra,):
            row += [r[k]["N"], _e(r[k]["err_interp"]), _e(r[k]["err_laplacian"]), f"{r[k]['D_at_max']:.4f}"]
        rows.append(row)
    out.append(_table(head, rows))
    sa, sb = a["slopes"], b["slopes"] if b else {}
    names = (("max_interp", "interpolation, max", "interp"), ("p99_interp", "interpolation, 99th percentile", None),
             ("median_interp", "interpolation, median", None), ("max_laplacian", "Laplacian, max", "laplacian"),
             ("median_laplacian", "Laplacian, median", None))
    out.append("Fitted orders:\n\n" + _table(["error", "paper", "Eq. 2.8", "Eq. B.13"], [
        [name, PAPER["fig41_orders"][p] if p else "–", _o(sa[key]), _o(sb[key]) if key in sb else "–"]
        for key, name, p in names]))
    find = []
    if b:
        met = (_near(sb["max_interp"], PAPER["fig41_orders"]["interp"])
               and _near(sb["max_laplacian"], PAPER["fig41_orders"]["laplacian"]))
        which = "the paper's orders," if met else "orders"
        find.append(f"With Eq. B.13 the maxima converge at {which} {_o(sb['max_interp'])} for the interpolation "
                    f"and {_o(sb['max_laplacian'])} for the Laplacian (the paper: "
                    f"{PAPER['fig41_orders']['interp']} and {PAPER['fig41_orders']['laplacian']}).")
    find.append(f"With the paper's Eq. 2.8 the median of the interpolation error converges at "
                f"{_o(sa['median_interp'])}. The maxima are rugged, as the paper notes for low resolution, and fit "
                f"at {_o(sa['max_interp'])} (interpolation) and {_o(sa['max_laplacian'])} (Laplacian).")
    if b:
        nb = _col(b["rows"], "N")
        k = int(np.argmin(np.abs(np.log(nb / ra[-1]["N"]))))
        find.append(f"At about equal N (Eq. 2.8's finest set, N = {ra[-1]['N']}; Eq. B.13's set with "
                    f"N = {b['rows'][k]['N']}) the largest interpolation error is {_e(ra[-1]['err_interp'])} with "
                    f"Eq. 2.8 and {_e(b['rows'][k]['err_interp'])} with Eq. B.13.")
        find.append("Why the maxima converge more slowly with Eq. 2.8 than with Eq. B.13: they sit beside the front, "
                    "where |∇f| is already small but the fourth derivatives are still large. There D_p is set by the "
                    "ball of Eq. 2.9, which grades D_p away from the front at the slope 1/r* whatever D0 (the median "
                    "D_p on the flanks falls only like a power of D0 below 1: `monitor_study.md`): D_p at the worst "
                    f"particle stays within {_span(_col(ra, 'D_at_max'), lambda v: f'{v:.3f}')} while D0 falls from "
                    f"{_g(ra[0]['D0'])} to {ra[-1]['D0']:.2f}. With Eq. B.13, D̃ follows the fourth derivatives on "
                    f"the flanks, and D_p at the worst particle falls from {b['rows'][0]['D_at_max']:.4f} to "
                    f"{b['rows'][-1]['D_at_max']:.4f}.")
    # how many particles Eq. 2.8 needs on the front at the coarsest D0 (the paper's coarsest set: ~102)
    r0 = PAPER["front_radius"]
    r = np.linspace(0.0, 1.0, 400_001)
    slope_max = float(np.max(2 * r / width / np.cosh((r ** 2 - r0 ** 2) / width) ** 2))
    d_front = par["d0_start"] / np.sqrt(1 + slope_max ** 2)
    ring = 2 * np.pi * r0 / d_front
    if ring > PAPER["fig41_n"][0]:
        find.append(f"The counts: the paper starts at about {PAPER['fig41_n'][0]} particles for D0 = "
                    f"{_g(PAPER['fig41_d0'][0])}, arpy's first set has {ra[0]['N']} (D0 = {_g(ra[0]['D0'])}). On the "
                    f"front, max |∇f| = {slope_max:.1f}, so Eq. 2.8 asks for D̃ = {d_front:.4f} at D0 = "
                    f"{_g(par['d0_start'])}, and one ring of that spacing around the front (radius {_g(r0)}) "
                    f"alone takes {ring:.0f} particles. {PAPER['fig41_n'][0]} particles cannot follow Eq. 2.8 on "
                    "this front; the paper does not say how its coarsest sets were made.")
    out.append("\n".join(f"- {f}" for f in find))
    out.append(_fig(tag, "fig41", "Fig. 4.1a: errors of interpolation and Laplacian vs h, (a) Eq. 2.8, (b) Eq. B.13"))
    return "\n\n".join(out)


def _fig42(res: dict, tag: str, settings: dict) -> str:
    runs = {k: res[k] for k in ("fig42", "fig42b") if k in res}
    if not runs:
        return ""
    par = res["parameters"]["advection"]
    out = ["## Fig. 4.2: a passive scalar in the reversing vortex (§4.2)",
           f"The blob of Eq. 4.3 advected by the vortex of Eq. 4.4 in the doubly periodic unit square to "
           f"T = {_g(par['T'])}, where the exact field is the initial one; RK4 with dt = "
           f"{_g(settings['advection_dt'])} (the paper's), a re-organization every "
           f"{settings['advection_every']} steps, f interpolated old → new with a local min/max limiter. The error "
           "is Eq. 4.5, relative to max f; h = 1 / √N_max. With Eq. B.13 the first set comes from the exact "
           "fourth derivatives, and every re-organization from DC-PSE estimates of order 6 on the old particles "
           "(the m = 4 operators give no fourth derivatives)."]
    rows = []
    for key, run in runs.items():
        for r in run["rows"]:
            rows.append([SERIES["reach 1" if key == "fig42" else "B.13, reach 1"], _g(r["D0"]), r["N_max"], r["N"],
                         f"{r['h']:.4f}", _e(r["error"]), _e(r["median_error"]), _wall(r["wall_s"])])
    out.append(_table(["monitor", "D0", "N_max", "N at T", "h", "error", "median error", "wall (s)"], rows))
    orows = []
    for key, run in runs.items():
        h, e = _col(run["rows"], "h"), _col(run["rows"], "error")
        orows.append([SERIES["reach 1" if key == "fig42" else "B.13, reach 1"], _o(run["order"]),
                      ", ".join(_o(p) for p in _pairwise(h, e)), _o(run["median_order"])])
    out.append(f"Fitted orders (the paper: {PAPER['fig42_order']}, for the maximum):\n\n"
               + _table(["monitor", "maximum", "maximum, pairwise", "median"], orows))
    find = []
    if len(runs) == 2:
        a, b = runs["fig42"], runs["fig42b"]
        find.append(f"Eq. B.13 converges at order {_o(b['order'])} (the paper: {PAPER['fig42_order']}), the paper's "
                    f"Eq. 2.8 at {_o(a['order'])}. The cause is the one of Fig. 4.1, shown without the flow below.")
        na = _col(a["rows"], "N_max")
        lower, higher = [], []
        for r in b["rows"]:
            ea, ma = _at(na, _col(a["rows"], "error"), r["N_max"]), _at(na, _col(a["rows"], "median_error"), r["N_max"])
            if ea is not None:
                lower.append(ea / r["error"])
                higher.append(r["median_error"] / ma)
        if lower:
            find.append(f"At equal N_max (Eq. 2.8 interpolated in log-log between its runs) the maximum error of "
                        f"Eq. B.13 is {_span(lower)}× lower, its median {_span(higher)}× higher: Eq. B.13 moves "
                        "particles from the blob's edge to its flanks.")
    hist = res.get("fig42h")
    if hist:
        parts, growing = [], True
        for kind, run in hist.items():
            t, n = np.array(run["t"]), np.array(run["N"])
            n90 = int(n[np.argmin(np.abs(t - run["t_90"]))])
            growing &= bool(n90 < n.max())
            parts.append(f"with {SERIES['reach 1' if kind == 'gradient' else 'B.13, reach 1']} (D0 = {_g(run['D0'])}) "
                         f"by t = {run['t_90']:.2f}, when N = {n90} (at most {int(n.max())}, at "
                         f"t = {t[np.argmax(n)]:.2f})")
        find.append("When the error is made (one run per monitor; after each re-organization the error against "
                    "the exact field at that time, from characteristics traced back): between re-organizations f "
                    "is carried exactly, so the error at T is what the interpolations add. 90 % of the final "
                    "maximum is there " + "; ".join(parts) + "."
                    + (" Most of it is added while the set grows and is stretched by the flow." if growing else ""))
    out.append("\n".join(f"- {f}" for f in find))
    out.append(_fig(tag, "fig42", "Fig. 4.2: (a) the field at T/2, (b) error vs h with Eq. 2.8 and Eq. B.13"))
    if hist:
        out.append(_fig(tag, "fig42h", "The error after each re-organization and N over time"))
    return "\n\n".join(out)


def _fig42i(res: dict, tag: str, settings: dict) -> str:
    runs = res.get("fig42i")
    if not runs:
        return ""
    par = res["parameters"]["blob_interpolation"]
    out = ["### The same step without the flow",
           "Every re-organization of Fig. 4.2 interpolates f from the old particles to new ones. This step alone, "
           "on the blob at rest: particles adapted to Eq. 4.3 with D0 ← "
           f"{_g(par['gradient']['factor'])} D0 from {_g(par['gradient']['d0_start'])}, each set interpolated from "
           f"the previous one; Eq. B.13 from the blob's exact fourth derivatives. Errors relative to max f; r is the "
           f"distance from the blob's centre (its edge: r = {cases.C2:.3f}); \"failed\": new particles without any "
           "stencil, which take the nearest old value."]
    rows = []
    for kind, run in runs.items():
        for r in run["rows"]:
            rows.append([SERIES["reach 1" if kind == "gradient" else "B.13, reach 1"], f"{r['D0']:.4f}", r["N"],
                         _e(r["err_interp"]), _e(r["p99_interp"]), _e(r["median_interp"]), f"{r['D_at_max']:.4f}",
                         f"{r['r_at_max']:.3f}", r["failed"]])
    out.append(_table(["monitor", "D0", "N", "max error", "99th percentile", "median", "D_p at the max",
                       "r at the max", "failed"], rows))
    out.append("Fitted orders:\n\n" + _table(["monitor", "maximum", "99th percentile", "median"], [
        [SERIES["reach 1" if kind == "gradient" else "B.13, reach 1"], _o(run["slope_max"]), _o(run["slope_p99"]),
         _o(run["slope_median"])] for kind, run in runs.items()]))
    brows = []
    for kind, run in runs.items():
        total = sum(b["n"] for b in run["bands"])
        for b in run["bands"]:
            brows.append([f"{SERIES['reach 1' if kind == 'gradient' else 'B.13, reach 1']} "
                          f"(D0 = {run['rows'][-1]['D0']:.4f})", f"{_g(b['r_lo'])}–{_g(b['r_hi'])}", b["n"],
                          f"{100 * b['n'] / total:.1f}", _e(b["max_error"]), f"{b['D_over_D0']:.3f}",
                          f"{b['D_over_Dtilde']:.2f}"])
    out.append("The finest set of each monitor by distance r from the centre (medians of the ratios):\n\n"
               + _table(["monitor", "r", "particles", "%", "max error", "D_p / D0", "D_p / D̃"], brows))
    find = []
    g, f4 = runs.get("gradient"), runs.get("fourth")
    if g:
        text = (f"With Eq. 2.8 the maximum converges at {_o(g['slope_max'])} and the median at "
                f"{_o(g['slope_median'])}")
        if "fig42" in res:
            text += (f", without any flow the pattern of Fig. 4.2 itself ({_o(res['fig42']['order'])} and "
                     f"{_o(res['fig42']['median_order'])})")
        find.append(text + f". The 99th percentile converges at {_o(g['slope_p99'])}: the slow maximum is not a "
                    "handful of bad stencils but a zone of about 1 % of the particles.")
        bands = {b["r_lo"]: b for b in g["bands"]}
        edge, graded = bands.get(0.14), [bands[k] for k in (0, 0.24) if k in bands]
        if edge and graded:
            total = sum(b["n"] for b in g["bands"])
            find.append("That zone is where Eq. 2.9 grades D_p on either side of the edge: the plateau inside "
                        f"(r < 0.1) and the outer tail (r = 0.24–0.3), where D_p / D̃ is "
                        f"{_span([b['D_over_Dtilde'] for b in graded], lambda v: f'{v:.2f}')}. In the finest set the "
                        f"edge band holds {100 * edge['n'] / total:.0f} % of the particles at D_p ≈ D0 / "
                        f"{1 / edge['D_over_D0']:.0f}, just as Eq. 2.8 asks (D_p / D̃ = "
                        f"{edge['D_over_Dtilde']:.2f}), and its largest error is "
                        f"{_span([b['max_error'] / edge['max_error'] for b in graded])}× below those of the plateau "
                        f"and the tail. D_p at the worst particle stays within "
                        f"{_span(_col(g['rows'], 'D_at_max'), lambda v: f'{v:.3f}')} while D0 falls from "
                        f"{_g(g['rows'][0]['D0'])} to {g['rows'][-1]['D0']:.3f}: it is set by the distance to the "
                        "fine edge, not by D0.")
        p99 = _pairwise(_col(g["rows"], "h"), _col(g["rows"], "p99_interp"))
        if len(p99) >= 3 and "fig42" in res:
            static = {r["D0"]: r["N"] for r in g["rows"]}
            flow = [(r["N_max"], static[r["D0"]]) for r in res["fig42"]["rows"] if r["D0"] in static]
            text = (f"The 99th percentile reaches order {_span(p99[-3:], _o)} only between the last sets "
                    f"(N ≥ {g['rows'][-4]['N']}).")
            if flow:
                text += (f" With the flow, N_max is {_span([a / s for a, s in flow])}× the particle count at rest "
                         "for the same D0, so the runs of Fig. 4.2 with Eq. 2.8 would need far more particles than "
                         "were run to show order 4.")
            find.append(text)
    if f4:
        inner = [b for b in f4["bands"] if b["r_hi"] <= 0.3]
        text = (f"The monitor is the cause, not Eq. 2.9 or the stencils: with Eq. B.13 the maximum converges at "
                f"{_o(f4['slope_max'])}, the 99th percentile at {_o(f4['slope_p99'])}, the median at "
                f"{_o(f4['slope_median'])}.")
        if inner:
            text += (f" D_p / D̃ is {_span([b['D_over_Dtilde'] for b in inner], lambda v: f'{v:.2f}')} in every "
                     "band of r < 0.3, so almost nothing is graded, and the bands' largest errors lie within "
                     f"{_x(max(b['max_error'] for b in inner) / min(b['max_error'] for b in inner))}× of each "
                     "other.")
        if g:
            n = _col(g["rows"], "N")
            ratios = {key: [] for key in ("err_interp", "p99_interp", "median_interp")}
            for r in f4["rows"]:
                for key, v in ratios.items():
                    e = _at(n, _col(g["rows"], key), r["N"])
                    if e is not None:
                        v.append(e / r[key])
            if ratios["err_interp"]:
                text += (f" At equal N its maximum is {_span(ratios['err_interp'])}× and its 99th percentile "
                         f"{_span(ratios['p99_interp'])}× below those of Eq. 2.8, while its median is "
                         f"{_span([1 / v for v in ratios['median_interp']])}× higher: particles move from the edge "
                         "to the flanks.")
        find.append(text)
        failed = f4["rows"][-1]["failed"]
        if failed:
            find.append(f"In the finest Eq. B.13 set {failed} new particles found no stencil. They sit at the "
                        "blob's centre, where Eq. 4.3 has a tiny cusp whose fourth derivatives grow like 1/r³, so "
                        "Eq. B.13 refines a small spot far below the old particles around it.")
    out.append("\n".join(f"- {f}" for f in find))
    out.append(_fig(tag, "fig42i", "One interpolation old -> new on the blob at rest: (a) errors vs h, "
                                   "(b) D_p of the worst particle"))
    return "\n\n".join(out)


def _fig43(res: dict, tag: str, settings: dict) -> str:
    r = res.get("fig43")
    if not r:
        return ""
    out = ["## Fig. 4.3: the steep pulse (§4.3)",
           f"The 2D pulse of Eq. 4.6 at Pe = {_g(r['Pe'])}: random particles self-organize with D0 = {_g(r['D0'])} "
           f"(the paper does not give its D0), then the pulse is rotated and diffused to T = {_g(r['T'])}.",
           _table(["", "paper", "arpy"], [["N after self-organization", PAPER["fig43_n"], r["N_initial"]],
                                          ["error at T", "–", _e(r["error"])],
                                          ["steps, wall time", "–", f"{r['steps']}, {_wall(r['wall_s'])} s"]]),
           f"arpy's set has {r['N_initial'] / PAPER['fig43_n']:.2f}× the paper's particles.",
           _fig(tag, "fig43", "Fig. 4.3: the pulse at Pe = 1e4 after self-organization, with close-ups")]
    return "\n\n".join(out)


def _pulse_tables(run: dict, d: int) -> list[str]:
    """The runs and the fitted orders of one dimension of Fig. 4.4."""
    edge = 2.0 if d == 2 else 3.0
    rows = []
    for key, series in run["adaptive"].items():
        for r in series:
            rows.append([SERIES.get(key, key), _g(r["D0"]), r["N"], f"{r['h']:.4f}", _e(r["error"]),
                         _e(r["mass_loss"][-1]), r["steps"], _wall(r["wall_s"]), f"{r['D_min']:.4f}",
                         _x(r["uniform_N_at_D_min"] / r["N"]),
                         _x(r["particle_ratio"]) if "particle_ratio" in r else "–"])
    for r in run["remeshed"]:
        rows.append(["remeshed", f"{r['n_cells']}{'²' if d == 2 else '³'} cells", r["N"],
                     f"{edge / r['N'] ** (1 / d):.4f}", _e(r["error"]), _e(r["mass_loss"]), r["steps"],
                     _wall(r["wall_s"]), "", "", ""])
    out = [_table(["method", "D0 / mesh", "N (max)", "h", "error at T", "mass loss at T", "steps", "wall (s)",
                   "D_min", "mesh at D_min / N", "remeshed at equal error / N"], rows)]
    orders = run["orders"]
    orows = [[SERIES.get(key, key), _o(orders[f"adaptive, {key}"]),
              _o(orders.get(f"adaptive, {key}, h from N_final", np.nan)),
              _o(orders.get(f"adaptive, {key}, h from N_mean", np.nan))]
             for key in run["adaptive"] if f"adaptive, {key}" in orders]
    if "remeshed" in orders:
        orows.append(["remeshed", _o(orders["remeshed"]), "", ""])
    if orows:
        out.append(f"Fitted orders (the paper: {PAPER['fig44_order']}), h from N_max, from N at T and from N "
                   "averaged over the steps:\n\n" + _table(["method", "N_max", "N at T", "mean N"], orows))
    return out


def _fig44(res: dict, tag: str, settings: dict) -> str:
    runs = res.get("fig44", {})
    if not runs:
        return ""
    par = res["parameters"]
    pe = settings["pulse_pe"]
    out = ["## Fig. 4.4: the pulse rotated once and diffused (§4.3)",
           "The Gaussian pulse of Eq. 4.6 rotated once about the box's centre and diffused, against Eq. 4.8; "
           "forward Euler with dt = h_min² Pe / 4, the diffusion limit (the paper writes δt = h_min² / 4), a "
           f"re-organization every {settings['pulse_every']} "
           "steps. The baseline is the paper's remeshed particle method: exact rotation, M′4 remeshing onto a "
           "uniform mesh of (cells + 1)^d nodes, second-order finite differences. Columns: D_min, the finest "
           "spacing of the initial particles; \"mesh at D_min / N\", the nodes of a uniform mesh that fine over "
           "the particles; \"remeshed at equal error / N\", the remeshed method's particles at the same error "
           "(from a power-law fit of its runs) over the adaptive particles. Mass loss: Eq. 4.9."]
    two, three = runs.get("2d"), runs.get("3d")
    if two:
        a = two["adaptive"]
        out.append(f"### Fig. 4.4a: 2D, Pe = {_g(pe['2'])}, Ω = [−1, 1]², T = {_g(par['pulse2d']['T'])}, "
                   f"h = {two['h_definition']}")
        out += _pulse_tables(two, 2)
        o = two["orders"]
        find = []
        if all(f"adaptive, {k}" in o for k in SERIES) and "remeshed" in o:
            find.append(f"Eq. B.13 converges at {_o(o['adaptive, B.13, reach 1'])} (the paper: "
                        f"{PAPER['fig44_order']}) and the remeshed method at {_o(o['remeshed'])}; Eq. 2.8 at "
                        f"{_o(o['adaptive, reach 1'])} with the paper's ball (Eq. 2.9) and "
                        f"{_o(o['adaptive, reach 2'])} with one twice as wide. Taking N at T or the mean N instead "
                        "of N_max changes these little: the definition of h is not what is missing.")
        grad, four = a.get("reach 1", []), a.get("B.13, reach 1", [])
        if grad and four and o.get("adaptive, reach 1", 0) < PAPER["fig44_order"] - 0.25:
            p = float(pe["2"])
            find.append(f"Why Eq. 2.8 falls short: the largest error at T sits at the pulse's peak, where ∇f = 0. "
                        f"Eq. 2.8 resolves the flanks in proportion to D0 (D_min / D0 = "
                        f"{grad[0]['D_min'] / grad[0]['D0']:.4f}, its analytic minimum 1 / √(1 + (Pe/2) e⁻¹) = "
                        f"{1 / np.sqrt(1 + p / 2 * np.exp(-1)):.4f}); the peak's D_p is set by the ball of Eq. 2.9 "
                        "around the fine flanks and shrinks only like √D0, so the peak's error falls more slowly "
                        "than h². A wider ball only changes the constant. Eq. B.13 has no such gap: the fourth "
                        "derivatives are largest at the peak, where D̃ = D0 (1 + 3 (Pe/2)²)^(−1/4) = "
                        f"{(1 + 3 * (p / 2) ** 2) ** -0.25:.4f} D0 (measured: "
                        f"{four[0]['D_min'] / four[0]['D0']:.4f} D0). Changing the time stepping (RK4, or "
                        "re-organizing more often) changes Eq. 2.8's error little: the error is spatial.")
            ratios = []
            for r in four:
                e = _at(_col(grad, "N"), _col(grad, "error"), r["N"])
                if e is not None:
                    ratios.append(e / r["error"])
            if ratios:
                find.append(f"At equal N the error of Eq. B.13 is {_span(ratios)}× below that of Eq. 2.8 "
                            "(Eq. 2.8 interpolated in log-log between its runs).")
        eq = {k: [r["particle_ratio"] for r in rows if "particle_ratio" in r] for k, rows in a.items()}
        if all(eq.get(k) for k in SERIES):
            find.append(f"At equal error the remeshed method needs {_span(eq['B.13, reach 1'])}× the particles of "
                        f"Eq. B.13 (the coarsest run: {_x(eq['B.13, reach 1'][0])}×, the finest: "
                        f"{_x(eq['B.13, reach 1'][-1])}×), {_span(eq['reach 1'])}× those of Eq. 2.8 and "
                        f"{_span(eq['reach 2'])}× with reach 2. A uniform mesh as fine as D_min has "
                        f"{_span([r['uniform_N_at_D_min'] / r['N'] for r in grad])}× the particles of the Eq. 2.8 "
                        f"runs and {_span([r['uniform_N_at_D_min'] / r['N'] for r in four])}× those of Eq. B.13.")
        out.append("\n".join(f"- {f}" for f in find))
    if three:
        a = three["adaptive"]
        out.append(f"### Fig. 4.4b: 3D, Pe = {_g(pe['3'])}, Ω = [−1.5, 1.5]³, T = {_g(par['pulse3d']['T'])}, "
                   f"h = {three['h_definition']} (the paper's caption writes 2 / N^(1/3); its general definition, "
                   "(|Ω| / N)^(1/d), gives 3 / N^(1/3) on this box)")
        out += _pulse_tables(three, 3)
        o = three["orders"]
        find = []
        if all(f"adaptive, {k}" in o for k in SERIES) and "remeshed" in o:
            find.append(f"Eq. B.13 converges at {_o(o['adaptive, B.13, reach 1'])}, the remeshed method at "
                        f"{_o(o['remeshed'])}, Eq. 2.8 at {_o(o['adaptive, reach 1'])} (reach 2: "
                        f"{_o(o['adaptive, reach 2'])}); the paper: {PAPER['fig44_order']}.")
        grad, four = a.get("reach 1", []), a.get("B.13, reach 1", [])
        eq = {k: [r["particle_ratio"] for r in rows if "particle_ratio" in r] for k, rows in a.items()}
        if grad and four and eq.get("reach 1") and eq.get("B.13, reach 1"):
            rem, last, b13 = three["remeshed"][-1], four[-1], eq["B.13, reach 1"]
            rising = len(b13) > 1 and all(y > x for x, y in zip(b13, b13[1:]))
            fine = {k: [r["uniform_N_at_D_min"] / r["N"] for r in rows] for k, rows in (("2.8", grad), ("B.13", four))}
            paper = PAPER["fig44_ratio"]
            text = (f"The paper's \"about {paper}×\" read two ways. At equal error, the remeshed method needs "
                    f"{_span(b13)}× the particles of Eq. B.13{', rising with resolution' if rising else ''} (its "
                    f"finest run: error {_e(last['error'])} with N = {last['N']}; the {rem['n_cells']}³ mesh: "
                    f"{_e(rem['error'])} with N = {rem['N']}), but only {_span(eq['reach 1'])}× those of Eq. 2.8")
            if eq.get("reach 2"):
                text += f" (reach 2: {_span(eq['reach 2'])}×)"
            text += (", whose pulse peak is under-resolved as in 2D. At equal finest resolution: the paper gives "
                     f"the finest resolved scale as D0 / max |∇f| ≈ {PAPER['fig44_finest']} D0; arpy's initial "
                     f"D_min / D0 is {_span([r['D_min'] / r['D0'] for r in grad], lambda v: f'{v:.3f}')} with "
                     f"Eq. 2.8, and a uniform mesh that fine has {_span(fine['2.8'])}× the particles of the Eq. 2.8 "
                     f"runs and {_span(fine['B.13'])}× those of Eq. B.13. ")
            within = [k for k, v in fine.items() if min(v) <= paper <= max(v)]
            text += (f"So the paper's {paper}× lies within the ratios at equal finest resolution (Eq. "
                     f"{' and Eq. '.join(within)}); " if within else
                     f"So the paper's {paper}× is not reached at equal finest resolution; ")
            text += (f"at equal error the ratio is {_x(b13[-1])}× at the finest run here"
                     + (" and still growing." if rising else "."))
            find.append(text)
        out.append("\n".join(f"- {f}" for f in find))
    out.append(_fig(tag, "fig44", "Fig. 4.4: error at T vs h, (a) 2D, (b) 3D"))
    return "\n\n".join(out)


def _fig45(res: dict, tag: str, settings: dict) -> str:
    two = res.get("fig44", {}).get("2d", {}).get("adaptive", {})
    series = {k: two[k] for k in ("reach 1", "B.13, reach 1") if two.get(k)}
    if not series:
        return ""
    rows = []
    halves = {}
    for key, runs in series.items():
        for r in runs:
            t, m = np.array(r["mass_t"]), np.array(r["mass_loss"])
            half = float(np.interp(t[-1] / 2, t, m))
            ratio = abs(m[-1] - half) / abs(half - m[0]) if len(t) > 2 and half != m[0] else None
            halves.setdefault(key, []).append(ratio)
            rows.append([SERIES[key], _g(r["D0"]), r["N"], PAPER["fig45_n"].get(r["D0"], "–") if key == "reach 1"
                         else "–", _e(m[-1]), _e(np.abs(m).max()), _x(ratio) if ratio is not None else "–"])
    out = ["## Fig. 4.5: mass loss of the 2D pulse (§4.3)",
           "The relative mass loss of Eq. 4.9 (the particles' f interpolated onto a fine mesh) over the 2D runs of "
           "Fig. 4.4a; a negative loss is a gain.",
           _table(["monitor", "D0", "N (max)", "N, paper", "loss at T", "largest magnitude",
                   "change in the 2nd half / in the 1st"], rows)]
    find = []
    paper = [(r["N"], PAPER["fig45_n"][r["D0"]]) for r in series.get("reach 1", []) if r["D0"] in PAPER["fig45_n"]]
    if paper:
        find.append(f"At the paper's D0 arpy's N is {_span([n / p for n, p in paper], lambda v: f'{v:.2f}')}× the "
                    "paper's.")
    for key, runs in series.items():
        loss = [abs(r["mass_loss"][-1]) for r in runs]
        falls = all(b < a for a, b in zip(loss, loss[1:]))
        find.append(f"With {SERIES[key]} the loss at T {'falls' if falls else 'does not fall steadily'} with D0 "
                    f"(|loss| {_e(loss[0])} at D0 = {_g(runs[0]['D0'])}, {_e(loss[-1])} at {_g(runs[-1]['D0'])})"
                    + (", as in the paper's figure." if falls else ": the under-resolved peak of Fig. 4.4a again."))
    ratios = [v for v in halves.get("B.13, reach 1", []) if v is not None]
    if ratios:
        find.append("The paper: the loss rate decreases with time. With Eq. B.13 the mass changes in the second "
                    f"half of the run by {_span(ratios, lambda v: f'{v:.2f}')} of its change in the first half.")
    rem = res["fig44"]["2d"].get("remeshed", [])
    if rem:
        worst = max(abs(r["mass_loss"]) for r in rem)
        find.append(f"The remeshed method {'conserves mass to round-off' if worst < 1e-9 else 'loses'} "
                    f"(|loss| ≤ {_e(worst)}).")
    out.append("\n".join(f"- {f}" for f in find))
    out.append(_fig(tag, "fig45", "Fig. 4.5: relative mass loss over time, Eq. 2.8 and Eq. B.13"))
    return "\n\n".join(out)


def report(res: dict) -> str:
    """The Markdown page of a result (results/<stem>.md is this of results/<stem>.json)."""
    quick = res.get("quick", res.get("parameters") == json.loads(json.dumps(QUICK)))
    tag = "simulation_quick" if quick else "simulation"
    settings = res.get("settings") or case_settings()
    parts = [_head(res, quick, settings), _summary(res)]
    parts += [fn(res, tag, settings) for fn in (_fig41, _fig42, _fig42i, _fig43, _fig44, _fig45)]
    return "\n\n".join(p for p in parts if p) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = benchmark_args(__doc__, argv, HERE / "results", lambda parser: parser.add_argument(
        "--only", nargs="+", choices=FIGURES, default=list(FIGURES), help="figures to run"))
    tag = "simulation_quick" if args.quick else "simulation"
    p = QUICK if args.quick else FULL
    only = set(args.only)
    if "fig45" in only:
        only.add("fig44")
    result: dict = {**run_info(), "quick": args.quick, "parameters": p, "settings": case_settings()}
    t0 = time.perf_counter()
    returned = {}
    for name, (run, key, extra) in RUNS.items():
        if name in only:
            returned[name] = run(p[key], result, *extra)
    half = returned.get("fig42b", returned.get("fig42"))       # panel (a) of fig42: t = T / 2, last run
    pe1e4 = returned.get("fig43")
    if "fig44" in only:
        result["fig44"] = {}
        print(f"\nFig. 4.4a / 4.5 (§4.3): 2D pulse, Pe = 1000, T = {p['pulse2d']['T']} (adaptive: Euler, k = 10)")
        result["fig44"]["2d"] = run_pulse(2, p["pulse2d"], p["remeshed2d"])
        print(f"\nFig. 4.4b (§4.3): 3D pulse, Pe = 100, T = {p['pulse3d']['T']}")
        result["fig44"]["3d"] = run_pulse(3, p["pulse3d"], p["remeshed3d"])
    result["wall_s"] = time.perf_counter() - t0
    path = args.out / f"{tag}.json"
    if only != set(FIGURES) and path.exists():                  # a partial run updates its figures only
        merged = json.loads(path.read_text())
        merged.update({k: v for k, v in result.items() if k != "parameters"})
        merged.setdefault("parameters", {}).update(p)
        result = merged
    path.write_text(json.dumps(result, indent=1))
    page = write_page(args.out, tag, report)
    shown = set(only)
    for pair in ({"fig41", "fig41b"}, {"fig42", "fig42b"}):          # one figure holds both
        shown |= pair if only & pair else set()
    written = plot_all({k: v for k, v in result.items() if k in shown}, half, pe1e4, tag, args.out)
    print(f"\nwrote {path}, {page.name} and {', '.join(w.name for w in written)} ({result['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
