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

Every point (h, N, error, wall time) goes into a JSON; each figure into a PNG.

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
from arpy._bench import benchmark_args, run_info
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
        return nearest(np.array([cases.X0]), x, domain=Domain([1.0, 1.0], periodic=True))[0]

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
    r = cases.gaussian_pulse(d=2, Pe=1e4, D0=p["D0"], T=p["T"])
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


def main(argv: list[str] | None = None) -> int:
    args = benchmark_args(__doc__, argv, HERE / "results", lambda parser: parser.add_argument(
        "--only", nargs="+", choices=FIGURES, default=list(FIGURES), help="figures to run"))
    tag = "simulation_quick" if args.quick else "simulation"
    p = QUICK if args.quick else FULL
    only = set(args.only)
    if "fig45" in only:
        only.add("fig44")
    result: dict = {**run_info(), "parameters": p}
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
    shown = set(only)
    for pair in ({"fig41", "fig41b"}, {"fig42", "fig42b"}):          # one figure holds both
        shown |= pair if only & pair else set()
    written = plot_all({k: v for k, v in result.items() if k in shown}, half, pe1e4, tag, args.out)
    print(f"\nwrote {path} and {', '.join(w.name for w in written)} ({result['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
