"""A reaction-diffusion system of your own on self-organizing particles, checked against its exact
solution: two fields with a variable diffusivity, a reaction, a compressible flow (-f div w, Eq. 2.3b)
and Dirichlet and Neumann walls or a periodic box, the sources made so that the exact fields are known
(a manufactured solution).  It shows how a right-hand side is written (:class:`arpy.Simulation` with
``rhs``) and measures the order at which the error falls with the resolution.

In the unit square, carried by the velocity w::

    du/dt = div(k grad u) - u div w - u v + S_u,
    dv/dt = D_v lap v     - v div w + u v - v + S_v,    D_v = 0.005,

with d/dt the derivative along the particles' paths.  With walls (w tangential to them)::

    u = 1 + 0.4 sin(pi x + 0.5) cos(2 y + 0.3) exp(-t / 2),   v = 0.6 + 0.3 cos(1.5 x - y + t),
    k = 0.01 (1 + 0.5 sin(x + y)),
    w = (0.1 sin(pi x) cos(pi y), 0.05 sin(pi y) (1 + cos(pi x)));

in the periodic box (q = 2 pi)::

    u = 1 + 0.4 sin(q x + 0.5) cos(q y + 0.3) exp(-t / 2),    v = 0.6 + 0.3 cos(q (x - y) + t),
    k = 0.01 (1 + 0.5 sin(q (x + y))),
    w = (0.05 + 0.05 sin(q x) cos(q y), 0.03 + 0.025 sin(q y) (1 + cos(q x))).

S_u and S_v are computed from the exact fields by fourth-order central differences (error about 1e-10).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Callable

import numpy as np

from ..dcpse.boundary import Dirichlet, Neumann, face_names
from ..domain import Domain
from ..distributed import Comm
from ..dcpse.operators import Operators
from ..adapt.organize import DEFAULT_SEED, self_organize, start_share
from ..plotting import plot_manufactured
from ..simulation import Simulation
from ..timeseries import TimeSeries
from .analysis import slope
from .registry import OUTPUT_EVERY, RESOLUTION, Case, Param, domain, option, seed_option, steps_option, time_option

__all__ = ["CASE", "DEFAULT_D0", "WALLS", "manufactured", "manufactured_exact", "manufactured_rhs"]

#: The boundaries the case takes: u and v held at their exact values (Dirichlet), given their exact
#: fluxes (Neumann), or u held and v given its fluxes (mixed) at the walls of the unit square; or the
#: periodic unit square.
WALLS = ("mixed", "dirichlet", "neumann", "periodic")
Q = 2 * np.pi
D_V = 0.005
#: The resolutions ``arpy run manufactured`` runs by default.
DEFAULT_D0 = (0.1, 0.07, 0.05)


def manufactured_exact(x: np.ndarray, t: float, periodic: bool = False) -> dict[str, np.ndarray]:
    """The exact fields u and v at x (n, 2), time t (the module docstring; ``periodic``: those of the
    periodic box)."""
    if periodic:
        return {"u": 1 + 0.4 * np.sin(Q * x[:, 0] + 0.5) * np.cos(Q * x[:, 1] + 0.3) * np.exp(-t / 2),
                "v": 0.6 + 0.3 * np.cos(Q * (x[:, 0] - x[:, 1]) + t)}
    return {"u": 1 + 0.4 * np.sin(np.pi * x[:, 0] + 0.5) * np.cos(2 * x[:, 1] + 0.3) * np.exp(-t / 2),
            "v": 0.6 + 0.3 * np.cos(1.5 * x[:, 0] - x[:, 1] + t)}


def _velocity(x: np.ndarray, periodic: bool) -> np.ndarray:
    if periodic:
        return np.stack([0.05 + 0.05 * np.sin(Q * x[:, 0]) * np.cos(Q * x[:, 1]),
                         0.03 + 0.025 * np.sin(Q * x[:, 1]) * (1 + np.cos(Q * x[:, 0]))], axis=1)
    q = np.pi
    return np.stack([0.1 * np.sin(q * x[:, 0]) * np.cos(q * x[:, 1]),
                     0.05 * np.sin(q * x[:, 1]) * (1 + np.cos(q * x[:, 0]))], axis=1)


def _k(x: np.ndarray, periodic: bool) -> np.ndarray:
    return 0.01 * (1 + 0.5 * np.sin((Q if periodic else 1.0) * (x[:, 0] + x[:, 1])))


def _d(fun: Callable[[np.ndarray, float], np.ndarray], x: np.ndarray, t: float, axis: int) -> np.ndarray:
    """d fun / d x_axis (axis 2: d / dt) by the fourth-order central difference."""
    h = 1e-4 if axis == 2 else 1e-3
    if axis == 2:
        return (-fun(x, t + 2 * h) + 8 * fun(x, t + h) - 8 * fun(x, t - h) + fun(x, t - 2 * h)) / (12 * h)
    e = np.zeros(x.shape[1])
    e[axis] = h
    return (-fun(x + 2 * e, t) + 8 * fun(x + e, t) - 8 * fun(x - e, t) + fun(x - 2 * e, t)) / (12 * h)


def _field(name: str, periodic: bool = False) -> Callable[[np.ndarray, float], np.ndarray]:
    return lambda x, t: manufactured_exact(x, t, periodic)[name]


def _sources(x: np.ndarray, t: float, periodic: bool) -> dict[str, np.ndarray]:
    """S_u, S_v from the exact fields: f_t + div(w f) (the rate along the paths plus f div w) minus the
    diffusion and the reaction."""
    ex = manufactured_exact(x, t, periodic)
    out = {}
    for name in ("u", "v"):
        f = _field(name, periodic)
        rate = _d(f, x, t, 2)
        for a in range(2):
            rate = rate + _d(_carried(f, a, periodic), x, t, a) - _d(_diffused(name, f, a, periodic), x, t, a)
        out[name] = rate
    uv = ex["u"] * ex["v"]
    return {"u": out["u"] + uv, "v": out["v"] - uv + ex["v"]}


def _carried(f: Callable[[np.ndarray, float], np.ndarray], a: int,
             periodic: bool) -> Callable[[np.ndarray, float], np.ndarray]:
    """(x, t) -> w_a f: the flux of f along axis a."""
    def flux(y: np.ndarray, s: float) -> np.ndarray:
        return _velocity(y, periodic)[:, a] * f(y, s)
    return flux


def _diffused(name: str, f: Callable[[np.ndarray, float], np.ndarray], a: int,
              periodic: bool) -> Callable[[np.ndarray, float], np.ndarray]:
    """(x, t) -> k df/dx_a (u) or D_v df/dx_a (v): the diffusive flux along axis a."""
    def flux(y: np.ndarray, s: float) -> np.ndarray:
        return (_k(y, periodic) if name == "u" else D_V) * _d(f, y, s, a)
    return flux


def _outward(f: Callable[[np.ndarray, float], np.ndarray], face: int) -> Callable[[np.ndarray, float], np.ndarray]:
    """(x, t) -> the outward normal derivative of f on face ``face`` (2 a + side) of the unit square."""
    sign = 1.0 if face % 2 else -1.0

    def flux(w: np.ndarray, t: float) -> np.ndarray:
        return sign * _d(f, w, t, face // 2)
    return flux


def _conditions(walls: str) -> dict | None:
    if walls == "periodic":
        return None
    held = {name: Dirichlet(_field(name)) for name in ("u", "v")}
    fluxes = {name: {face: Neumann(_outward(_field(name), k)) for k, face in enumerate(face_names(2))}
              for name in ("u", "v")}
    if walls == "dirichlet":
        return held
    if walls == "neumann":
        return fluxes
    return {"u": held["u"], "v": fluxes["v"]}


def manufactured_rhs(t: float, x: np.ndarray, f: dict[str, np.ndarray], ops: Operators,
                     periodic: bool = False) -> dict[str, np.ndarray]:
    """The right-hand side of the system (besides -f div w, which ``conservative=True`` adds);
    ``periodic``: that of the periodic box."""
    s = _sources(x, t, periodic)
    uv = f["u"] * f["v"]
    return {"u": ops.diffusion(lambda y, fields: _k(y, periodic), "u") - uv + s["u"],
            "v": D_V * ops.laplacian("v") + uv - f["v"] + s["v"]}


def manufactured(D0: float = 0.07, walls: str = "mixed", T: float = 0.5, reorganize_every: int = 5,
                 seed: int = DEFAULT_SEED, progress: bool = False, series: TimeSeries | None = None,
                 comm: Comm | None = None) -> dict:
    """The manufactured reaction-diffusion system (module docstring) at resolution D0 to time T.

    Parameters
    ----------
    D0 : float
        Coarsest resolution (length; the box is the unit square); the finest is D0 / 2.
    walls : {"mixed", "dirichlet", "neumann", "periodic"}
        The conditions at the walls of the unit square, or the periodic unit square (see :data:`WALLS`).
    T : float
        Final time; RK4 with steps of 0.2 D0, or of the stability bound where that is lower (``max_dt``:
        the bound of the diffusion terms shrinks like D0^2, and below 0.2 D0 from about D0 = 0.035).
    reorganize_every : int
        Time steps between re-organizations (monitor: Eq. 2.8 on both fields).
    seed : int
        Seed of the initial particles and insertions.
    progress : bool
        Show a progress bar.
    series : TimeSeries, optional
        Write the particles over time (:class:`arpy.timeseries.TimeSeries`: u, v and D_p).
    comm : Comm, optional
        Run over the ranks of a communicator (every rank calls this function with the same arguments;
        see :class:`arpy.Simulation`, Dirichlet walls included): bitwise the one-process results.  Each
        rank adapts its share of the random start and keeps its share of the initial set.  The
        errors and N are reductions over the ranks (the rms from the exact sum of the squared errors);
        neither the particles nor their errors are gathered.

    Returns
    -------
    dict
        ``N``, ``h`` = 1 / sqrt(N) at T, ``rms`` and ``max``: the errors of u and v at T ({name: float}; rms =
        sqrt(sum e^2 / N), the sum exact and rounded once, :meth:`arpy.Particles.fsum`),
        ``steps``, ``wall_s``, ``sim``; ``particles``: the initial :class:`arpy.Particles` (with ``comm`` on
        several ranks, this rank's share: each rank adapts its share of the random start,
        :func:`arpy.adapt.organize.start_share`); ``keys``, ``x``, ``D``, ``u``, ``v``: the particles at T
        in key order (with ``comm``: this rank's).
    """
    if walls not in WALLS:
        raise ValueError(f"walls must be one of {WALLS}, got {walls!r}")
    t0 = time.perf_counter()
    periodic = walls == "periodic"
    box = Domain([1.0, 1.0], periodic=periodic)
    start = np.random.default_rng(seed).random((int(1.2 / D0 ** 2), 2))

    def grad(p):                                    # of u at t = 0
        return np.stack([_d(_field("u", periodic), p, 0.0, a) for a in range(2)], axis=1)

    def rhs(t, x, f, ops):
        return manufactured_rhs(t, x, f, ops, periodic)

    ps = self_organize(**start_share(start, comm), grad_f=grad, D0=D0, Dmin=D0 / 2, domain=box, seed=seed, comm=comm)
    initial = {name: (lambda p, name=name: manufactured_exact(p, 0.0, periodic)[name]) for name in ("u", "v")}
    sim = Simulation(ps, initial, rhs=rhs, velocity=lambda x, t, f: _velocity(x, periodic), conservative=True,
                     boundary=_conditions(walls), D0=D0, Dmin=D0 / 2, integrator="rk4", max_dt=0.2 * D0,
                     reorganize_every=reorganize_every, seed=seed, comm=comm)
    if series is not None:
        series.start(sim)
    sim.run(T, progress=progress, callback=series)
    if series is not None:
        series.finish(sim)
    p = sim.particles
    keys, x, D, F = p.ordered()
    exact = manufactured_exact(x, sim.t, periodic)
    err = {name: F[:, j] - exact[name] for j, name in enumerate(("u", "v"))}
    n = p.total(p.n)
    return dict(D0=D0, walls=walls, N=n, h=1 / np.sqrt(n), steps=sim.steps,
                rms={k: float(np.sqrt(p.fsum(e ** 2) / n)) for k, e in err.items()},
                max={k: p.gmax(np.abs(e).max(initial=0.0)) for k, e in err.items()},
                degenerate=int(max((e["degenerate"] for e in sim.log), default=0)),
                wall_s=time.perf_counter() - t0, sim=sim, particles=ps, keys=keys, x=x, D=D, u=F[:, 0], v=F[:, 1])


# ---------------------------------------------------------------- arpy run manufactured
def run(args: argparse.Namespace, out: Path) -> dict:
    """``arpy run manufactured``: one run per D0, the errors and their orders; writes manufactured.npz,
    manufactured_particles.vtu (the finest run) and manufactured.png; returns the summary.  Under
    mpiexec, in pieces as ``arpy run pulse`` (:meth:`~arpy.cases.registry.Case.save`,
    :meth:`~arpy.cases.registry.Case.figure`)."""
    print(f"arpy run manufactured: a reaction-diffusion system with a compressible flow, {args.walls} walls, "
          f"T = {args.T:g}, against its exact solution")
    print("       D0      N   steps |   u rms      u max |   v rms      v max | wall s")
    runs = []
    for D0 in sorted(args.D0, reverse=True):
        r = manufactured(D0, **CASE.kwargs(args, "manufactured"), progress=not args.quiet,
                         series=CASE.series(args, f"_D0_{D0:g}"), comm=getattr(args, "comm", None))
        runs.append(r)
        print(f"  {D0:7.4g} {r['N']:6d} {r['steps']:7d} | {r['rms']['u']:.3e}  {r['max']['u']:.3e} | "
              f"{r['rms']['v']:.3e}  {r['max']['v']:.3e} | {r['wall_s']:6.1f}")
    orders = {}
    if len(runs) > 1:
        h = [r["h"] for r in runs]
        orders = {f"{kind} {name}": slope(np.array(h), np.array([r[kind][name] for r in runs]))
                  for kind in ("rms", "max") for name in ("u", "v")}
        print("  orders (log error against log h, h = 1 / sqrt(N); 2 expected): "
              + ", ".join(f"{k} {v:.2f}" for k, v in orders.items()))
    last = runs[-1]
    summary = {"walls": args.walls, "T": args.T, "orders": orders,
               "runs": [{k: r[k] for k in ("D0", "N", "steps", "rms", "max", "degenerate", "wall_s")} for r in runs]}
    rows = {k: last[k] for k in ("keys", "x", "D", "u", "v")}
    npz = CASE.save(args, out / "manufactured.npz", summary, rows=rows, N=np.array([r["N"] for r in runs]),
                    rms_u=np.array([r["rms"]["u"] for r in runs]), rms_v=np.array([r["rms"]["v"] for r in runs]))
    CASE.vtu(args, out / "manufactured_particles.vtu", last["x"], D=last["D"], u=last["u"], v=last["v"])
    CASE.figure(args, out / "manufactured.png", npz, rows, lambda whole, path: plot_manufactured(runs, path, whole))
    return summary


#: ``arpy run manufactured``.
CASE = Case(
    "manufactured", "your own PDE: a reaction-diffusion system with Dirichlet and Neumann walls, against its exact "
    "solution",
    (Param("--D0", "coarsest resolutions D0, a length each (the box is the unit square); one run each, the "
           "orders fitted over them", default=list(DEFAULT_D0), checks=RESOLUTION, nargs="+"),
     option(manufactured, "walls", "--walls", "the wall conditions: u held and v given its fluxes (mixed), both "
            "held (dirichlet), both given their fluxes (neumann); or a periodic box (periodic)", type=str,
            choices=WALLS),
     time_option(manufactured),
     steps_option(manufactured),
     seed_option(manufactured), OUTPUT_EVERY),
    lambda a: domain(1.0, 2, periodic=a.walls == "periodic", coarsest=max(a.D0)), run, seconds=9.8)
