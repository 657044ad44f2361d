"""§4.4 of Reboux et al. (2012): the 2D Burgers equation (Eq. 4.10), u = (f, f), in the doubly
periodic unit square, on adaptive particles (:func:`burgers`) and with the remeshed baseline in
conservative form (Eq. 4.11, :func:`remeshed_burgers`), against a pseudo-spectral reference
(:class:`arpy.reference.burgers.SpectralBurgers`).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Callable, Literal

import numpy as np

from ..adapt.organize import DEFAULT_SEED, self_organize, start_share
from ..distributed import Comm
from ..domain import Domain
from ..plotting import plot_burgers
from ..remesh import RemeshedLPM
from ..simulation import Simulation
from .checkpoint import Checkpoint, case_checkpoint

if TYPE_CHECKING:
    from ..reference.burgers import SpectralBurgers
from .registry import (CHECKPOINT, OUTPUT_EVERY, REMESHED, RESOLUTION, Case, at_least, domain, few_steps, option,
                       reach_option, seed_option, steps_option, time_option)

__all__ = ["CASE", "burgers", "burgers_initial", "burgers_initial_gradient", "burgers_reference", "burgers_velocity",
           "remeshed_burgers"]


def burgers_initial(x: np.ndarray) -> np.ndarray:
    """f(x, y, 0) = sin(2 pi x) cos(2 pi y) (§4.4); x (n, 2) -> (n,)."""
    return np.sin(2 * np.pi * x[:, 0]) * np.cos(2 * np.pi * x[:, 1])


def burgers_initial_gradient(x: np.ndarray) -> np.ndarray:
    """Gradient of :func:`burgers_initial`; x (n, 2) -> (n, 2)."""
    sx, cx = np.sin(2 * np.pi * x[:, 0]), np.cos(2 * np.pi * x[:, 0])
    sy, cy = np.sin(2 * np.pi * x[:, 1]), np.cos(2 * np.pi * x[:, 1])
    return 2 * np.pi * np.stack([cx * cy, -sx * sy], axis=1)


def burgers_velocity(x: np.ndarray, t: float, f: np.ndarray) -> np.ndarray:
    """u = (f, f) (Eq. 4.10); f (n,) -> (n, 2)."""
    return np.stack([f, f], axis=1)


def burgers_reference(Re: float, T: float, n: int = 256) -> SpectralBurgers:
    """The pseudo-spectral solution at T on an n^2 grid (converged to ~1e-8 at Re = 100, T = 0.1 for n = 256).

    Returns the :class:`~arpy.reference.burgers.SpectralBurgers` at T: a callable x (m, 2) -> (m,).
    """
    from ..reference.burgers import SpectralBurgers

    return SpectralBurgers(burgers_initial, n, 1.0 / Re).run(T)


def burgers(Re: float = 100.0, D0: float = 0.1, T: float = 0.1, reorganize_every: int = 10, seed: int = DEFAULT_SEED,
            reach: float = 1.0, reference: Callable[[np.ndarray], np.ndarray] | Literal[False] | None = None,
            progress: bool = False, checkpoint: Checkpoint | None = None, comm: Comm | None = None) -> dict:
    """§4.4: the 2D Burgers equation on adaptive particles (forward Euler, dt from
    the CFL and diffusion limits of h_min), in the periodic unit square.

    Parameters
    ----------
    Re : float
        Reynolds number; the viscosity is 1 / Re.
    D0 : float
        Coarsest resolution (length).
    T : float
        Final time.
    reorganize_every : int
        Time steps between re-organizations.
    seed : int
        Seed of the random initial particles and insertions.
    reach : float
        The factor on the ball of Eq. 2.9 (1: the paper's).
    reference : callable or False, optional
        The reference solution at T, x (m, 2) -> (m,); None: :func:`burgers_reference` on 256^2
        (which resolves Re = 100, not Re = 1000); False: none, the error is NaN.
    progress : bool
        Show a progress bar.
    checkpoint : Checkpoint, optional
        Write the run's state every so many steps, or resume from it (:mod:`arpy.cases.checkpoint`).
    comm : Comm, optional
        Run over the ranks of a communicator (every rank calls this function with the same
        arguments; see :class:`arpy.Simulation`): bitwise the one-process results; each rank adapts its
        share of the random start and keeps its share of the initial set (its checkpoint writes it in
        pieces), the summaries are reductions over the ranks, and no rank gathers the particles.

    Returns
    -------
    dict
        ``error`` (L-infinity at T against the reference), ``N_initial``, ``N``, ``N_max``, ``h`` =
        1 / sqrt(N_max), ``scale_ratio`` (max D / min D at T), ``x``, ``f``, ``D``: the particles at
        T in key order, their keys ``keys`` (with ``comm``: this rank's), ``steps``, ``wall_s``, ``sim``,
        ``particles``: the initial :class:`arpy.Particles` (with ``comm`` on several ranks, this rank's
        share: each rank adapts its share of the random start, :func:`arpy.adapt.organize.start_share`)
        and ``reference``.
    """
    box = [1.0, 1.0]
    x = np.random.default_rng(seed).random((800, 2))
    t0 = time.perf_counter()
    cp = case_checkpoint(checkpoint, T)
    ps = cp.particles(lambda: self_organize(**start_share(x, comm), grad_f=burgers_initial_gradient, D0=D0,
                                            domain=Domain(box, periodic=True), seed=seed, reach=reach, comm=comm))
    sim = Simulation(ps, burgers_initial, velocity=burgers_velocity, nu=1.0 / Re, D0=D0, integrator="euler",
                     reorganize_every=reorganize_every, seed=seed, reach=reach, comm=comm)
    cp.run(sim, T, progress=progress)
    wall = time.perf_counter() - t0
    p = sim.particles
    kT, xT, DT, FT = p.ordered()
    fT = FT[:, 0]
    ref = burgers_reference(Re, T) if reference is None else reference
    err = p.gmax(np.abs(fT - ref(xT)).max(initial=0.0)) if ref is not False else float("nan")
    hist = sim.history()
    n_initial = ps.total(ps.n)
    n_max = int(max(n_initial, hist["n"].max()))
    return dict(Re=Re, D0=D0, T=T, error=err, N_initial=n_initial, N=p.total(p.n), N_max=n_max, h=1 / np.sqrt(n_max),
                scale_ratio=p.gmax(DT.max(initial=-np.inf)) / p.gmin(DT.min(initial=np.inf)), keys=kT, x=xT, f=fT,
                D=DT, steps=sim.steps, wall_s=wall, sim=sim, particles=ps, reference=ref)


def remeshed_burgers(Re: float = 100.0, n_cells: int = 128, T: float = 0.1,
                     reference: Callable[[np.ndarray], np.ndarray] | None = None) -> dict:
    """§4.4 with the remeshed particle method in conservative form (Eq. 4.11): particles
    on the mesh nodes move with u / 2 = (f, f) / 2 (forward Euler, dt = h^2 Re / 4),
    M'4 remeshing, diffusion by centred finite differences.

    ``n_cells``: mesh cells per edge; ``reference`` as in :func:`burgers`.  Returns ``N``, ``h``,
    ``error`` (L-infinity at T), ``steps`` and ``wall_s``.
    """
    t0 = time.perf_counter()
    r = RemeshedLPM(burgers_initial, [1.0, 1.0], 1.0 / n_cells, nu=1.0 / Re, periodic=True,
                    velocity=lambda x, t, f: 0.5 * burgers_velocity(x, t, f)).run(T)
    wall = time.perf_counter() - t0
    ref = burgers_reference(Re, T) if reference is None else reference
    err = float(np.abs(r.f.ravel() - ref(r.nodes)).max())
    return dict(Re=Re, N=r.n, h=r.h, error=err, steps=r.steps, wall_s=wall)


# ---------------------------------------------------------------- arpy run burgers
def run(args: argparse.Namespace, out: Path) -> dict:
    """``arpy run burgers``: prints the error against the pseudo-spectral reference and the cost
    (and the remeshed baseline's with ``--remeshed``); writes burgers.npz, burgers_particles.vtu
    and burgers.png (Fig. 4.6); returns the summary.  Under mpiexec, in pieces as ``arpy run pulse``
    (:meth:`~arpy.cases.registry.Case.save`, :meth:`~arpy.cases.registry.Case.figure`)."""
    comm = getattr(args, "comm", None)
    r = burgers(**CASE.kwargs(args, "burgers"), progress=not args.quiet,
                checkpoint=CASE.checkpoint(args), comm=comm)
    summary = {"t": r["sim"].t, "reference_n": r["reference"].n,
               **{k: r[k] for k in ("Re", "D0", "N_initial", "N", "N_max", "h", "scale_ratio", "steps", "wall_s",
                                    "error")}}
    sim, ref = r["sim"], r["reference"]
    print(f"arpy run burgers: 2D Burgers equation, u = (f, f) (Reboux et al. 2012, Sec. 4.4), Re = {args.re:g}, "
          f"D0 = {r['D0']:g}, T = {args.T:g}")
    print(f"  particles: {r['N_initial']} at t = 0, {r['N']} at t = T (largest {r['N_max']}), "
          f"h = 1/sqrt(N_max) = {r['h']:.4g}; {r['steps']} steps in {r['wall_s']:.1f} s"
          + (f" on {comm.size} MPI ranks" if comm is not None else ""))
    print(f"  fine/coarse scale ratio max D_p / min D_p at T: {r['scale_ratio']:.1f}")
    print(f"  L-infinity error at T against a {ref.n}^2 pseudo-spectral solution: {r['error']:.3e}"
          + ("" if args.re <= 100 else f" (indicative only: {ref.n}^2 is converged for Re <= 100)"))
    if args.remeshed:
        b = remeshed_burgers(Re=args.re, T=args.T, reference=ref, **CASE.kwargs(args, "remeshed_burgers"))
        print(f"  remeshed particle method (conservative form), {b['N']} particles (h = {b['h']:.4g}): "
              f"error {b['error']:.3e}, {b['steps']} steps in {b['wall_s']:.1f} s")
        summary["remeshed"] = {k: b[k] for k in ("N", "h", "error", "steps", "wall_s")}
    x, f, D = r["x"], r["f"], r["D"]
    f_ref = ref(x)
    rows = dict(keys=r["keys"], x=x, f=f, D=D, f_reference=f_ref)
    npz = CASE.save(args, out / "burgers.npz", summary, rows=rows,
                    **{f"history_{k}": v for k, v in sim.history().items()})
    CASE.vtu(args, out / "burgers_particles.vtu", x, f=f, D=D, error=f - f_ref)
    title = f"Re = {args.re:g}, T = {args.T:g} (Fig. 4.6)"
    CASE.figure(args, out / "burgers.png", npz, rows,
                lambda whole, path: plot_burgers(SimpleNamespace(x=whole["x"], f=whole["f"], D=whole["D"]), path,
                                                 title, whole["N"]))
    return summary


#: ``arpy run burgers``.  --reach comes before --D0: the periodic box's check of D0 uses it.
CASE = Case(
    "burgers", "Sec. 4.4: the 2D Burgers equation, u = (f, f), against a pseudo-spectral reference",
    (option(burgers, "Re", "--re", "Reynolds number, dimensionless; the viscosity is 1 / Re",
            at_least(0, strict=True, what=" (the Reynolds number; the viscosity is 1 / Re)"),
            few_steps(lambda v: 1 / v)),
     reach_option(burgers),
     option(burgers, "D0", "--D0", "coarsest resolution D0, a length (the box is the unit square)", *RESOLUTION),
     time_option(burgers),
     steps_option(burgers),
     option(remeshed_burgers, "n_cells", "--remeshed",
            "also run the remeshed-particle baseline with this many mesh cells per edge (0: skip it)", *REMESHED,
            type=int),
     seed_option(burgers), OUTPUT_EVERY, *CHECKPOINT),
    lambda a: domain(1.0, 2, periodic=True, coarsest=a.D0, reach=a.reach), run, seconds=7.4)
