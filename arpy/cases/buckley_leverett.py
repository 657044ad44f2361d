"""§4.5 of Reboux et al. (2012): the viscous Buckley-Leverett equation (Eqs. 4.12-4.13) in the
stationary five-spot velocity field: water injected at the centre of [-0.5, 0.5]^2, produced at
its four corners.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ..adapt.organize import DEFAULT_SEED, self_organize, start_share
from ..distributed import Comm
from ..domain import Domain
from ..plotting import plot_five_spot
from ..simulation import Simulation
from .checkpoint import Checkpoint, case_checkpoint
from .registry import (CHECKPOINT, OUTPUT_EVERY, RESOLUTION, Case, at_least, domain, few_steps, option,
                       reach_option, seed_option, steps_option, time_option)

__all__ = ["CASE", "FIVE_SPOT_WELLS", "buckley_leverett_flux", "buckley_leverett_speed", "five_spot",
           "five_spot_velocity"]

#: The four production wells at the corners, (4, 2).
FIVE_SPOT_WELLS = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])


def five_spot_velocity(x: np.ndarray, r_well: float = 0.02) -> np.ndarray:
    """``u = -grad p``, ``p = sum_i log|x - c_i| - log|x|`` (§4.5): a source at the origin and
    sinks at the four corners, each regularized as ``log sqrt(|x - c|^2 + r_well^2)``; x (n, 2) -> (n, 2)."""
    u = x / ((x ** 2).sum(1) + r_well ** 2)[:, None]
    for c in FIVE_SPOT_WELLS:
        dx = x - c
        u -= dx / ((dx ** 2).sum(1) + r_well ** 2)[:, None]
    return u


def buckley_leverett_flux(f: np.ndarray, mu: float) -> np.ndarray:
    """g(f) = f^2 / (f^2 + mu (1 - f)^2) (Eq. 4.13); f (n,) -> (n,)."""
    return f * f / (f * f + mu * (1 - f) ** 2)


def buckley_leverett_speed(f: np.ndarray, mu: float) -> np.ndarray:
    """g'(f) = 2 mu f (1 - f) / (f^2 + mu (1 - f)^2)^2, with f clipped to [0, 1]; f (n,) -> (n,)."""
    f = np.clip(f, 0.0, 1.0)
    return 2 * mu * f * (1 - f) / (f * f + mu * (1 - f) ** 2) ** 2


def five_spot(mu: float = 0.5, nu: float = 0.01, D0: float = 0.1, T: float = 0.09, r_well: float = 0.02,
              width: float | None = None, reorganize_every: int = 10, seed: int = DEFAULT_SEED, reach: float = 1.0,
              snapshots: Sequence[float] = (0.0, 0.056, 0.09), bounded: bool = True, progress: bool = False,
              checkpoint: Checkpoint | None = None, comm: Comm | None = None) -> dict:
    """§4.5: the viscous Buckley-Leverett equation df/dt + u . grad g(f) = nu lap f
    (Eqs. 4.12-4.13) in [-0.5, 0.5]^2 with the stationary five-spot velocity.

    In Lagrangian form the particles move with g'(f) u and f changes by diffusion only.  f = 1
    in the initial water disk of radius ``r_well`` and is held there after every step (the
    injection well).  Walls with mirror images.  The paper states neither mu nor nu: mu = 0.5 is
    a viscosity ratio of the classic Buckley-Leverett demonstrations; nu = 0.01 keeps the front
    about as wide as Dmin at D0 = 0.1.

    Parameters
    ----------
    mu : float
        Viscosity ratio of Eq. 4.13.
    nu : float
        Diffusion coefficient (area per time).
    D0 : float
        Coarsest resolution (length).
    T : float
        Final time.
    r_well : float
        Radius over which the wells are regularized, and of the initial water disk (length).
    width : float, optional
        Width over which the disk's edge is smoothed, also the finest resolution Dmin (length;
        default D0 / 10).
    reorganize_every : int
        Time steps between re-organizations.
    seed : int
        Seed of the random initial particles and insertions.
    reach : float
        The factor on the ball of Eq. 2.9 (1: the paper's).
    snapshots : sequence of float
        Times at which to keep x, f and D (at the first step ending at or after each).
    bounded : bool
        Interpolate f old -> new with the local min/max limiter (``Simulation(bounded=True)``);
        without it the interpolation of the steep front undershoots below f = 0.
    progress : bool
        Show a progress bar.
    checkpoint : Checkpoint, optional
        Write the run's state every so many steps, or resume from it (:mod:`arpy.cases.checkpoint`).
    comm : Comm, optional
        Run over the ranks of a communicator (every rank calls this function with the same
        arguments; see :class:`arpy.Simulation`): bitwise the one-process results; nothing is gathered:
        each rank adapts its share of the random start and keeps its own particles from the initial set
        (which its checkpoint writes in pieces) to T and at the snapshots (which its checkpoints write in
        its piece of the state), the summaries are reductions.

    Returns
    -------
    dict
        ``N_initial``, ``N``; ``t`` and ``n`` (steps + 1,): N over time; ``f_min``, ``f_max`` at T;
        ``snapshots``: {time: dict(keys, x, f, D)}, the particles at each in key order (with ``comm``:
        this rank's); ``x``, ``f``, ``D``: the particles at T in key order, their
        keys ``keys`` (with ``comm``: this rank's); ``steps``, ``wall_s``, ``sim``; ``particles``: the initial
        :class:`arpy.Particles` (with ``comm`` on several ranks, this rank's share: each rank adapts its
        share of the random start, :func:`arpy.adapt.organize.start_share`); ``velocity``: the
        five-spot velocity of the run, x (m, 2) -> (m, 2) (:func:`five_spot_velocity` with ``r_well``).
    """
    box = ([-0.5, -0.5], [0.5, 0.5])
    w = D0 / 10 if width is None else float(width)

    def f0(p):
        return 0.5 * (1 - np.tanh((np.sqrt((p ** 2).sum(1)) - r_well) / w))

    def grad_f0(p):
        r = np.maximum(np.sqrt((p ** 2).sum(1)), 1e-300)
        t = np.tanh((r - r_well) / w)
        return (-0.5 * (1 - t * t) / w / r)[:, None] * p

    def velocity(p, t, f):
        return buckley_leverett_speed(f, mu)[:, None] * five_spot_velocity(p, r_well)

    x = np.random.default_rng(seed).uniform(-0.5, 0.5, (400, 2))
    t0 = time.perf_counter()
    cp = case_checkpoint(checkpoint, T)
    ps = cp.particles(lambda: self_organize(**start_share(x, comm), grad_f=grad_f0, D0=D0, Dmin=w, domain=Domain(box),
                                            seed=seed, reach=reach, comm=comm))
    sim = Simulation(ps, f0, velocity=velocity, nu=nu, D0=D0, Dmin=w, reorganize_every=reorganize_every,
                     seed=seed, reach=reach, bounded=bounded, comm=comm)
    shots = {}
    pending = sorted(float(s) for s in snapshots if s <= T)

    def record(s: Simulation) -> None:
        s.f[(s.x ** 2).sum(1) < r_well ** 2] = 1.0                    # the injection well (each rank's own)
        if pending and s.t >= pending[0] - 1e-12:               # (this rank's particles, in key order)
            ks, xs, Ds, Fs = s.particles.ordered()
            while pending and s.t >= pending[0] - 1e-12:
                shots[pending.pop(0)] = dict(keys=ks.copy(), x=xs.copy(), f=Fs[:, 0].copy(), D=Ds.copy())

    def records() -> dict[str, np.ndarray]:
        return {"shot_times": np.array(sorted(shots), dtype=np.float64)}

    def restore(stored: Mapping[str, np.ndarray]) -> None:
        times = stored["shot_times"].tolist()
        got = cp.shares([f"shot{i}" for i in range(len(times))])
        shots.clear()
        shots.update({t: got[f"shot{i}"] for i, t in enumerate(times)})
        pending[:] = [t for t in sorted(float(s) for s in snapshots if s <= T) if t not in shots]

    record(sim)
    cp.run(sim, T, progress=progress, callback=record, records=records, restore=restore,
           shares=lambda: _named(shots))
    hist = sim.history()
    p = sim.particles
    kT, xT, DT, FT = p.ordered()
    fT = FT[:, 0]
    n_initial = ps.total(ps.n)
    return dict(mu=mu, nu=nu, D0=D0, N_initial=n_initial, N=p.total(p.n),
                t=np.concatenate([[0.0], hist["t"] + hist["dt"]]),
                n=np.concatenate([[n_initial], hist["n"]]), f_min=p.gmin(fT.min(initial=np.inf)),
                f_max=p.gmax(fT.max(initial=-np.inf)), keys=kT, x=xT, f=fT, D=DT,
                snapshots=shots, steps=sim.steps, wall_s=time.perf_counter() - t0, sim=sim, particles=ps,
                velocity=lambda p: five_spot_velocity(p, r_well))


# ---------------------------------------------------------------- arpy run five-spot
def run(args: argparse.Namespace, out: Path) -> dict:
    """``arpy run five-spot``: prints N and the saturation range; writes five_spot.npz,
    five_spot_particles.vtu and five_spot.png (Figs. 4.8 and 4.9); returns the summary.  Under mpiexec
    nothing is gathered: the particles at T in pieces as ``arpy run pulse``
    (:meth:`~arpy.cases.registry.Case.save`), with those of the snapshots (``shot<i>``, at ``shot_times``),
    and rank 0 draws the figure from the pieces read back (:meth:`~arpy.cases.registry.Case.figure`)."""
    comm = getattr(args, "comm", None)
    r = five_spot(**CASE.kwargs(args, "five_spot"), progress=not args.quiet,
                  checkpoint=CASE.checkpoint(args), comm=comm)
    print(f"arpy run five-spot: viscous Buckley-Leverett, five-spot wells (Reboux et al. 2012, Sec. 4.5), "
          f"mu = {args.mu:g}, nu = {args.nu:g}, D0 = {r['D0']:g}, T = {args.T:g}")
    print(f"  particles: {r['N_initial']} at t = 0, {r['N']} at t = T (largest {int(r['n'].max())}); "
          f"{r['steps']} steps in {r['wall_s']:.1f} s" + (f" on {comm.size} MPI ranks" if comm is not None else ""))
    print(f"  saturation range at T: [{r['f_min']:.4f}, {r['f_max']:.4f}]")
    summary = {"t": r["sim"].t, "N_max": int(r["n"].max()),
               **{k: r[k] for k in ("mu", "nu", "D0", "N_initial", "N", "steps", "wall_s", "f_min", "f_max")}}
    rows, sets, times = {k: r[k] for k in ("keys", "x", "f", "D")}, _named(r["snapshots"]), sorted(r["snapshots"])
    # (one process draws the snapshots as they are, and its five_spot.npz holds none, as it always has)
    ranks = comm is not None and comm.size > 1
    npz = CASE.save(args, out / "five_spot.npz", summary, rows=rows, sets=sets if ranks else None, t=r["t"], n=r["n"],
                    **({"shot_times": np.array(times)} if ranks else {}))
    CASE.vtu(args, out / "five_spot_particles.vtu", r["x"], f=r["f"], D=r["D"])
    CASE.figure(args, out / "five_spot.png", npz, rows, lambda whole, path: plot_five_spot(
        {**r, "snapshots": {t: whole[f"shot{i}"] for i, t in enumerate(times)}}, path), sets=sets)
    return summary


def _named(shots: dict[float, dict[str, np.ndarray]]) -> dict[str, dict[str, np.ndarray]]:
    """The snapshots {time: rows} by name, ``shot<i>`` in the order of their times."""
    return {f"shot{i}": shots[t] for i, t in enumerate(sorted(shots))}


#: ``arpy run five-spot``.
CASE = Case(
    "five-spot", "Sec. 4.5: the viscous Buckley-Leverett equation in the five-spot wells' flow",
    (option(five_spot, "mu", "--mu", "viscosity ratio mu of Eq. 4.13, dimensionless",
            at_least(0, strict=True, what=" (the viscosity ratio of Eq. 4.13: g(f) = f^2 / (f^2 + mu (1 - f)^2))")),
     option(five_spot, "nu", "--nu", "diffusion coefficient nu (area per time)",
            at_least(0, what=" (the diffusion coefficient)"), few_steps(lambda v: v)),
     reach_option(five_spot),
     option(five_spot, "D0", "--D0", "coarsest resolution D0, a length (the box is [-0.5, 0.5]^2)", *RESOLUTION),
     time_option(five_spot),
     steps_option(five_spot),
     seed_option(five_spot), OUTPUT_EVERY, *CHECKPOINT),
    lambda a: domain(1.0, 2), run, seconds=45.5)
