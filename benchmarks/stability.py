"""Benchmark: a user's own reaction-diffusion-advection system that must not blow up.

Issue 54's case, written as a user writes it (not one of arpy's cases): two fields u, v in the periodic
unit square, carried by a shearing flow w = (0.6 + 0.4 sin 2πy, 0.4 cos 2πx) that deforms the particle set
between re-organizations, diffusing with Du = 0.02 and Dv = 0.01, reacting by -u v² and u v² - k v
(k = 0.5), with sources made so that the exact fields are the moving waves

    u = 1 + 0.5 sin(2π(x - t)) cos(2πy),      v = 0.5 + 0.25 cos(2π(x + y - t/2)).

RK4, a re-organization every 4 steps, monitor Eq. 2.8 on both fields, Dmin = D0 / 2, T = 0.5.  Each seed
runs with the default step (``dt=None``) and with the fixed step 0.2 D0 (the step arpy's own
manufactured case takes); the table says whether each run reached T, was refused (a given step above
the stability bound, :class:`arpy.StabilityError`) or blew up (:class:`arpy.NonFiniteError`), and gives
its RMS error, the smallest stability bound met and the rows repaired at the particles (those that
alone would have made the step unstable).

    python benchmarks/stability.py            # D0 = 0.12, 0.08, 0.042, seeds 1-5 (minutes)
    python benchmarks/stability.py --quick    # D0 = 0.12, seeds 1-2 (seconds)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
FULL = dict(D0=(0.12, 0.08, 0.042), seeds=(1, 2, 3, 4, 5), T=0.5, reorganize_every=4)
QUICK = dict(D0=(0.12,), seeds=(1, 2), T=0.1, reorganize_every=4)
#: The system's constants: diffusivities, decay rate of v, wave amplitudes.
DU, DV, K, A, B = 0.02, 0.01, 0.5, 0.5, 0.25
TWO_PI = 2 * np.pi


def velocity(x: np.ndarray, t: float, f) -> np.ndarray:
    """The shearing flow w (n, 2) at the points x (n, 2): divergence-free, periodic."""
    return np.stack([0.6 + 0.4 * np.sin(TWO_PI * x[:, 1]), 0.4 * np.cos(TWO_PI * x[:, 0])], axis=1)


def exact(x: np.ndarray, t: float) -> dict[str, np.ndarray]:
    """The exact fields u, v (n,) at the points x (n, 2) and time t."""
    th, ph, ps = TWO_PI * (x[:, 0] - t), TWO_PI * x[:, 1], TWO_PI * (x[:, 0] + x[:, 1] - 0.5 * t)
    return {"u": 1 + A * np.sin(th) * np.cos(ph), "v": 0.5 + B * np.cos(ps)}


def sources(x: np.ndarray, t: float) -> dict[str, np.ndarray]:
    """The sources (n,) that make :func:`exact` solve the system: the material derivative along w of the
    exact fields, less their diffusion and reaction."""
    th, ph, ps = TWO_PI * (x[:, 0] - t), TWO_PI * x[:, 1], TWO_PI * (x[:, 0] + x[:, 1] - 0.5 * t)
    e, w = exact(x, t), velocity(x, t, None)
    u, v = e["u"], e["v"]
    du_t = -TWO_PI * A * np.cos(th) * np.cos(ph)
    du_x, du_y = TWO_PI * A * np.cos(th) * np.cos(ph), -TWO_PI * A * np.sin(th) * np.sin(ph)
    dv_t, dv_xy = np.pi * B * np.sin(ps), -TWO_PI * B * np.sin(ps)
    lap_u, lap_v = -2 * TWO_PI ** 2 * (u - 1), -2 * TWO_PI ** 2 * (v - 0.5)
    react = u * v * v
    return {"u": du_t + w[:, 0] * du_x + w[:, 1] * du_y - DU * lap_u + react,
            "v": dv_t + (w[:, 0] + w[:, 1]) * dv_xy - DV * lap_v - react + K * v}


def rhs(t: float, x: np.ndarray, f: dict, ops) -> dict[str, np.ndarray]:
    """The user's right-hand side: diffusion, reaction and the manufactured sources."""
    s, react = sources(x, t), f["u"] * f["v"] ** 2
    return {"u": DU * ops.laplacian("u") - react + s["u"], "v": DV * ops.laplacian("v") + react - K * f["v"] + s["v"]}


def simulation(D0: float, seed: int, dt: float | None, reorganize_every: int = 4):
    """The system's :class:`arpy.Simulation` at resolution D0 (Dmin = D0 / 2) from particles
    self-organized with ``seed``; ``dt`` None: the default step."""
    import arpy

    box = arpy.Domain([1.0, 1.0], periodic=True)
    n = int(1.5 / D0 ** 2)
    ps = arpy.self_organize(np.random.default_rng(seed).random((n, 2)), lambda p: np.full(len(p), D0), domain=box,
                            seed=seed)
    return arpy.Simulation(ps, {name: (lambda p, name=name: exact(p, 0.0)[name]) for name in ("u", "v")}, rhs=rhs,
                           velocity=velocity, nu=DU, D0=D0, Dmin=D0 / 2, integrator="rk4", dt=dt,
                           reorganize_every=reorganize_every, seed=seed)


def run(D0: float, seed: int, dt: float | None, T: float, reorganize_every: int = 4) -> dict:
    """One run to T: how it ended ("T", "refused", "blew up"), with the message, the time reached, the
    RMS error of u at the end, the smallest stability bound met, the steps and the rows repaired."""
    import arpy

    t0 = time.perf_counter()
    out: dict = dict(D0=D0, seed=seed, dt="default" if dt is None else dt)
    sim = None
    try:
        sim = simulation(D0, seed, dt, reorganize_every)
        sim.run(T)
        out["end"] = "T"
    except getattr(arpy, "StabilityError", ValueError) as e:         # (ValueError: builds before it)
        out.update(end="refused", message=str(e))
    except arpy.NonFiniteError as e:
        out.update(end="blew up", message=str(e))
    if sim is not None and sim.log:
        h = sim.history()
        err = sim.fields["u"] - exact(sim.x, sim.t)["u"]
        out.update(t=sim.t, steps=sim.steps, N=sim.n, rms_u=float(np.sqrt(np.mean(err ** 2))),
                   dt_stable_min=float(np.min(h["dt_stable"])), dt_max=float(np.max(h["dt"])),
                   repaired=int(np.sum(h.get("heavy", 0))))
    out["wall_s"] = time.perf_counter() - t0
    return out


def report(res: dict) -> str:
    """The Markdown page of a result."""
    from arpy._bench import md_table

    lines = ["# A user's reaction-diffusion-advection system: stable steps, or a clear stop", "",
             "`python benchmarks/stability.py` (see its docstring for the system).", ""]
    if res.get("quick"):
        lines += ["**Quick run** (small sizes, for the tests).", ""]
    rows = [[f"{r['D0']:g}", r["seed"], r["dt"] if isinstance(r["dt"], str) else f"{r['dt']:.3g}", r["end"],
             f"{r.get('t', 0):.3g}", r.get("steps", ""), r.get("N", ""),
             f"{r['rms_u']:.2e}" if "rms_u" in r else "", f"{r['dt_stable_min']:.3g}" if "dt_stable_min" in r else "",
             r.get("repaired", "")] for r in res["runs"]]
    lines += md_table(["D0", "seed", "dt", "end", "t", "steps", "N", "RMS u", "min dt_stable", "rows repaired"], rows)
    lines += [""]
    for mode in ("default", "fixed"):
        runs = [r for r in res["runs"] if (r["dt"] == "default") == (mode == "default")]
        ends = {e: sum(r["end"] == e for r in runs) for e in ("T", "refused", "blew up")}
        lines.append(f"- {'`dt=None`' if mode == 'default' else 'the fixed step 0.2 D0'}: {ends['T']} of {len(runs)} "
                     f"runs reach T, {ends['refused']} are refused, {ends['blew up']} blow up.")
    lines += ["- `min dt_stable` is the smallest stability bound of a step (Gershgorin discs of the Laplacians the "
              "rhs applied, times Du, at every RK stage); a fixed step above it is refused (`arpy.StabilityError`) "
              "before that step changes anything, the default step is taken again at it.  Gershgorin's discs bound "
              "the spectral radius from above: a refused run may have been stable.",
              "- `rows repaired`: rows of the Laplacian at the particles that alone would have made the step "
              "unstable (Du sum_q |L_pq| dt > 2.785, `arpy.dcpse.rows.wild_rows`), rebuilt at some stage "
              "(counted at each stage they were found).", "",
              f"Run on {res['machine']} with Python {res['python']}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    from arpy._bench import benchmark_args, run_info, write_page, write_result

    args = benchmark_args(__doc__, argv, HERE / "results")
    p = QUICK if args.quick else FULL
    runs = []
    for D0 in p["D0"]:
        for seed in p["seeds"]:
            for dt in (None, 0.2 * D0):
                r = run(D0, seed, dt, p["T"], p["reorganize_every"])
                runs.append(r)
                print(f"D0 {D0:g} seed {seed} dt {r['dt'] if dt is None else f'{dt:.3g}'}: {r['end']}"
                      f" (t = {r.get('t', 0):.3g}, {r.get('steps', 0)} steps, rms u {r.get('rms_u', np.nan):.2e}, "
                      f"min dt_stable {r.get('dt_stable_min', np.nan):.3g}, {r['wall_s']:.1f} s)"
                      + (f"\n    {r['message']}" if "message" in r else ""), flush=True)
    tag = "stability_quick" if args.quick else "stability"
    result = dict(**run_info(), quick=args.quick, parameters={k: list(v) if isinstance(v, tuple) else v
                                                              for k, v in p.items()}, runs=runs)
    write_result(args.out, tag, result, "", gap=False)
    print(f"wrote {write_page(args.out, tag, report)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
