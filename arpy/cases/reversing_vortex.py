"""§4.2 of Reboux et al. (2012): a blob (Eq. 4.3) advected by the reversing vortex (Eq. 4.4) in the
periodic unit square, RK4; the error of Eq. 4.5 at T, when the exact field is the initial one.

The blob's field, its exact derivatives and monitors are also the field of §4.1's blob variant
(:mod:`arpy.cases.convergence`).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Callable, Mapping

import numpy as np
from scipy.special import erf

from .. import fields
from ..distributed import Comm
from ..domain import Domain
from ..adapt.organize import DEFAULT_SEED, MAX_PARTICLES, self_organize, start_share, valid_stencils
from ..particles import Particles
from ..plotting import counted
from ..adapt.resolution import MONITORS, check_monitor, monitor_fourth, monitor_gradient
from ..simulation import Simulation
from .checkpoint import Checkpoint, case_checkpoint
from .registry import (CHECKPOINT, OUTPUT_EVERY, RESOLUTION, Case, domain, option, reach_option, seed_option,
                       steps_option, time_option)

__all__ = ["ADVECTION_D0", "BLOB_MAX_SLOPE", "C1", "C2", "CASE", "X0", "advection", "advection_d0", "advection_exact",
           "blob", "blob_fourth_derivatives", "blob_gradient", "blob_laplacian", "blob_monitor", "vortex"]

#: Eq. 4.3's constants: the blob's steepness C1, radius C2 and centre X0.
C1, C2, X0 = 21.269446, 0.16811704, (0.5, 0.75)
#: ``max |grad f|`` of the blob, at its edge r = C2: sqrt(2)/2 * 2/sqrt(pi) * C1 (about 17).
BLOB_MAX_SLOPE = np.sqrt(2) / 2 * 2 / np.sqrt(np.pi) * C1
#: The coarsest resolution D0 of :func:`advection` per monitor when none is given (about as many
#: particles with either).
ADVECTION_D0 = {"gradient": 0.2, "fourth": 0.25}


def _blob_images(x: np.ndarray):
    """Offsets (n, 2) of x from the blob's centre X0 and its 8 periodic images, with their lengths r (n,)."""
    for i in (-1, 0, 1):
        for j in (-1, 0, 1):
            dx = np.stack([x[:, 0] - X0[0] + i, x[:, 1] - X0[1] + j], axis=1)
            yield dx, np.sqrt((dx ** 2).sum(1))


def blob(x: np.ndarray) -> np.ndarray:
    """Eq. 4.3: a smooth blob of radius about C2 at X0 with its periodic images; x (n, 2) -> (n,)."""
    return sum(np.sqrt(2) / 2 * (erf(C1 * (C2 - r)) + 1) for _, r in _blob_images(x))


def blob_gradient(x: np.ndarray) -> np.ndarray:
    """Gradient of :func:`blob`; x (n, 2) -> (n, 2)."""
    g = np.zeros_like(x)
    for dx, r in _blob_images(x):
        dfdr = -BLOB_MAX_SLOPE * np.exp(-(C1 * (C2 - r)) ** 2)
        g += (dfdr / np.maximum(r, 1e-300))[:, None] * dx
    return g


def blob_laplacian(x: np.ndarray) -> np.ndarray:
    """Laplacian of :func:`blob`; x (n, 2) -> (n,): f'' + f'/r summed over the images, with
    f' = -A exp(-s^2), f'' = -2 A C1 s exp(-s^2), s = C1 (C2 - r).  (The blob has a
    tiny cusp at its centre, f' = -A exp(-(C1 C2)^2) = -5e-5 at r = 0, so the
    Laplacian has a weak 1/r singularity there.)"""
    out = np.zeros(x.shape[0])
    for _, r in _blob_images(x):
        s = C1 * (C2 - r)
        e = np.exp(-s * s)
        out += -BLOB_MAX_SLOPE * e * (2 * C1 * s + 1 / np.maximum(r, 1e-300))
    return out


def blob_fourth_derivatives(x: np.ndarray) -> np.ndarray:
    """The fourth partial derivatives of :func:`blob`; x (n, 2) -> (n, 5): d^4/dx^4,
    d^4/dx^3dy, d^4/dx^2dy^2, d^4/dxdy^3, d^4/dy^4 (summed over the images).

    For a radial f(r) (see :func:`arpy.fields.radial_fourth`), with D = (1/r) d/dr,
    D^2 f = f2/r^2 - f1/r^3, D^3 f = f3/r^3 - 3 f2/r^4 + 3 f1/r^5 and
    D^4 f = f4/r^4 - 6 f3/r^5 + 15 f2/r^6 - 15 f1/r^7 (fk: the k-th radial
    derivative; those of erf are Hermite polynomials times exp(-s^2), s = C1 (C2 - r)).
    Eq. B.13 of the paper builds its optimal resolution for m = 4 interpolation from these.
    (The blob's cusp at its centre, f' = -5e-5 at r = 0, makes them grow like
    1/r^3 within about 0.005 of it.)
    """
    out = np.zeros((x.shape[0], 5))
    for dx, r in _blob_images(x):
        r = np.maximum(r, 1e-12)
        s = C1 * (C2 - r)
        e = BLOB_MAX_SLOPE * np.exp(-s * s)
        f1, f2, f3, f4 = -e, -e * 2 * s * C1, -e * (4 * s * s - 2) * C1 ** 2, -e * (8 * s ** 3 - 12 * s) * C1 ** 3
        dd = (f2 / r ** 2 - f1 / r ** 3,
              f3 / r ** 3 - 3 * f2 / r ** 4 + 3 * f1 / r ** 5,
              f4 / r ** 4 - 6 * f3 / r ** 5 + 15 * f2 / r ** 6 - 15 * f1 / r ** 7)
        out += fields.radial_fourth_all(dx, dd)
    return out


def blob_monitor(x: np.ndarray, D0: float, kind: str = "gradient") -> np.ndarray:
    """The target resolution D~ (n,) of the blob at x (n, 2): "gradient" -- Eq. 2.8,
    ``D0 / sqrt(1 + |grad f|^2)``; "fourth" -- Eq. B.13 for m = 4 interpolation,
    regularised the same way: ``D0 (1 + max over |beta| = 4 of |d^beta f|)^(-1/4)``."""
    if kind == "gradient":
        return monitor_gradient(blob_gradient(x), D0, None)
    if kind == "fourth":
        return monitor_fourth(blob_fourth_derivatives(x), D0)
    raise ValueError(f"kind must be 'gradient' or 'fourth', got {kind!r}")


def vortex(T: float) -> Callable[..., np.ndarray]:
    """Eq. 4.4: the reversing vortex of period 2T in [0, 1]^2 (divergence free).

    Returns the velocity u(x, t, f=None): x (n, 2) -> (n, 2).
    """

    def u(x: np.ndarray, t: float, f: np.ndarray | None = None) -> np.ndarray:
        s = 2 * np.cos(np.pi * t / T)
        sx, cx = np.sin(np.pi * x[:, 0]), np.cos(np.pi * x[:, 0])
        sy, cy = np.sin(np.pi * x[:, 1]), np.cos(np.pi * x[:, 1])
        return s * np.stack([-sx ** 2 * sy * cy, sy ** 2 * sx * cx], axis=1)

    return u


def advection_exact(x: np.ndarray, t: float, T: float = 2.5, step: float = 0.00625) -> np.ndarray:
    """The exact field of §4.2 at time t, f(x, t) = blob(X): X is where the
    characteristic through (x, t) starts, traced back to 0 in the vortex of
    period 2T by RK4 with steps of at most ``step`` (4th order; about 2e-8
    in f at the default); x (n, 2) in the unit square -> (n,)."""
    x = np.array(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 2:
        raise ValueError("x must have shape (n, 2)")
    if not (np.isfinite(t) and t >= 0) or not step > 0:
        raise ValueError("need t >= 0 and step > 0")
    u = vortex(T)
    n = int(np.ceil(t / step - 1e-9))
    h, s = (-t / n if n else 0.0), float(t)
    for _ in range(n):
        k1 = u(x, s)
        k2 = u(x + h / 2 * k1, s + h / 2)
        k3 = u(x + h / 2 * k2, s + h / 2)
        k4 = u(x + h * k3, s + h)
        x, s = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4), s + h
    return blob(x)


def advection_d0(monitor: str, D0: float | None = None) -> float:
    """The coarsest resolution of :func:`advection`: ``D0``, or :data:`ADVECTION_D0` of the monitor if None."""
    check_monitor(monitor, 4)
    return ADVECTION_D0[monitor] if D0 is None else D0


def advection(D0: float | None = None, T: float = 2.5, dt: float = 0.025, reorganize_every: int = 4, seed: int = DEFAULT_SEED,
              reach: float = 1.0, bounded: bool = True, monitor: str = "gradient", error_history: bool = False,
              reading: str = "implicit", stencil_rule: str = "repair", max_particles: int = MAX_PARTICLES,
              progress: bool = False, checkpoint: Checkpoint | None = None, comm: Comm | None = None) -> dict:
    """§4.2: the blob advected by the vortex (doubly periodic unit square, RK4); the exact
    solution at T is the initial field.

    Parameters
    ----------
    D0 : float, optional
        Coarsest resolution (length); None: :data:`ADVECTION_D0` of the monitor (0.2 with
        "gradient", 0.25 with "fourth").  The same D0 gives several times more particles with
        "fourth".
    T : float
        Final time; the vortex reverses at T / 2 (Eq. 4.4 with period 2T).
    dt : float
        Time step of RK4.
    reorganize_every : int
        Time steps between re-organizations.
    seed : int
        Seed of the random initial particles and insertions.
    reach : float
        The factor on the ball of Eq. 2.9 (1: the paper's).
    bounded : bool
        Interpolate f old -> new with the local min/max limiter (``Simulation(bounded=True)``).
        The blob is flat on top and zero around it, so the limiter changes the smooth parts
        little; without it, an undershoot of one re-organization can refine itself and grow.
    monitor : str
        "gradient" -- the paper's Eq. 2.8; "fourth" -- Eq. B.13 of its Appendix B (the initial set
        from the blob's exact fourth derivatives, the re-organizations from DC-PSE estimates; see
        :class:`arpy.Simulation`).
    error_history : bool
        After every re-organization, the error of Eq. 4.5 against the exact field at that time
        (:func:`advection_exact`; one backward trace of every particle each time).  Between
        re-organizations f is carried exactly, so the history shows when the error at T was made.
    reading : {"implicit", "explicit", "pointwise"}
        The reading of Eq. 2.9 (see :func:`arpy.adapt.resolution.graded_resolution`).
    stencil_rule : {"repair", "displace"}
        See :class:`arpy.Simulation`; with "displace" the initial set is displaced too
        (:func:`arpy.adapt.organize.displace_set`).
    max_particles : int
        See :class:`arpy.Simulation` (a re-organization beyond it raises RuntimeError).
    progress : bool
        Show a progress bar.
    checkpoint : Checkpoint, optional
        Write the run's state every so many steps, or resume from it (:mod:`arpy.cases.checkpoint`).
    comm : Comm, optional
        Run over the ranks of a communicator (every rank calls this function with the same
        arguments; see :class:`arpy.Simulation`): bitwise the one-process results; the errors are
        reductions over the ranks and nothing is gathered: each rank adapts its share of the random start
        and keeps its own particles of the initial set (its checkpoint writes it in pieces), at T and
        at T/2 (the half-time snapshot, which its checkpoints write in its piece of the state).

    Returns
    -------
    dict
        ``error``: Eq. 4.5 (L-infinity over the particles) and ``median_error``; ``N`` (final) and
        ``N_max``; ``h`` = 1 / sqrt(N_max); ``half``: the particles at T/2 in key order, dict(keys, x, f,
        D) (with ``comm``: this rank's); ``x``, ``f``, ``D``: the particles at T in key order, their keys
        ``keys`` (with ``comm``: this rank's); ``steps``; ``wall_s`` (seconds, without
        the history's traces); ``sim``; ``particles``: the initial :class:`arpy.Particles` (with ``comm``
        on several ranks, this rank's share: each rank adapts its share of the random start,
        :func:`arpy.adapt.organize.start_share`); with ``error_history``, ``history`` = dict(t, N, max,
        median), arrays with one entry per re-organization.
    """
    D0 = advection_d0(monitor, D0)
    domain = Domain([1.0, 1.0], periodic=True)
    x = np.random.default_rng(seed).random((800, 2))
    cp = case_checkpoint(checkpoint, T)
    # (on several ranks each adapts its share of the start and keeps its share of the result)
    ps = cp.particles(lambda: valid_stencils(self_organize(**start_share(x, comm),
                                                           resolution=lambda p: blob_monitor(p, D0, monitor),
                                                           domain=domain, seed=seed, reach=reach, reading=reading,
                                                           comm=comm),
                                             stencil_rule, seed))
    sim = Simulation(ps, blob, velocity=vortex(T), D0=D0, integrator="rk4", dt=dt,
                     reorganize_every=reorganize_every, seed=seed, reach=reach, bounded=bounded, monitor=monitor,
                     reading=reading, stencil_rule=stencil_rule, max_particles=max_particles, comm=comm)
    half: dict = {}
    rows: list = []
    wall = 0.0

    def at_step(s: Simulation) -> None:
        nonlocal wall
        if not half and s.t >= T / 2 - 1e-9:                   # (this rank's particles, in key order)
            ks, xs, Ds, Fs = s.particles.ordered()
            half.update(keys=ks.copy(), x=xs.copy(), f=Fs[:, 0].copy(), D=Ds.copy())
        if error_history and s.log[-1]["reorganized"]:
            t1 = time.perf_counter()
            e = errors(s.particles, advection_exact(s.x, s.t, T))
            rows.append((s.t, s.particles.total(s.n), s.particles.gmax(e.max(initial=0.0)), s.particles.gmedian(e)))
            wall += time.perf_counter() - t1

    def errors(p: Particles, exact: np.ndarray, f: np.ndarray | None = None) -> np.ndarray:
        """Eq. 4.5 at this rank's particles (f: theirs, default ``p.F[:, 0]``; ``exact`` there): |f - exact|
        over the largest |exact| of every rank.  Collective."""
        return np.abs((p.F[:, 0] if f is None else f) - exact) / p.gmax(np.abs(exact).max(initial=0.0))

    def records() -> dict[str, np.ndarray]:
        return {"rows": np.array(rows, dtype=np.float64).reshape(-1, 4)}

    def restore(stored: Mapping[str, np.ndarray]) -> None:
        rows[:] = [(t, int(n), e, m) for t, n, e, m in stored["rows"]]
        half.update(cp.shares(["half"]).get("half", {}))

    t0 = time.perf_counter()
    cp.run(sim, T, progress=progress, callback=at_step, records=records, restore=restore,
           shares=lambda: {"half": half} if half else {})
    p = sim.particles
    kT, xT, DT, FT = p.ordered()
    fT = FT[:, 0]
    e = errors(p, blob(xT), fT)
    n = sim.history()["n"]
    n_max = int(max(n.max(), ps.total(ps.n)))
    out = dict(error=p.gmax(e.max(initial=0.0)), median_error=p.gmedian(e), N=p.total(p.n), N_max=n_max,
               h=1 / np.sqrt(n_max), steps=sim.steps, wall_s=time.perf_counter() - t0 - wall, half=half, sim=sim,
               particles=ps, keys=kT, x=xT, f=fT, D=DT)
    if error_history:
        out["history"] = dict(zip(("t", "N", "max", "median"), (np.array(c) for c in zip(*rows))))
    return out


# ---------------------------------------------------------------- arpy run advection
def _plot(r: dict, path: Path) -> None:
    """The particles coloured by f at T/2 and at T."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    for ax, (x, f, n, title) in zip(axes, [(r["half"]["x"], r["half"]["f"], r["half"].get("N"), "t = T/2"),
                                           (r["x"], r["f"], r.get("N"), "t = T")]):
        sc = ax.scatter(x[:, 0], x[:, 1], c=f, s=1, cmap="viridis")
        ax.set_aspect("equal")
        ax.set_title(f"{title}, {counted(len(x), n)}")
    fig.colorbar(sc, ax=axes, label="f")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace, out: Path) -> dict:
    """``arpy run advection``: prints the error of Eq. 4.5 and the cost; writes advection.npz (with the
    particles at T/2 as ``half_x``, ``half_f``, ``half_D``), advection_particles.vtu and advection.png;
    returns the summary.  Under mpiexec nothing is gathered: the particles at T and at T/2 in pieces, as
    ``arpy run pulse`` (:meth:`~arpy.cases.registry.Case.save` with ``sets``), and the figure drawn by rank
    0 from the pieces read back (:meth:`~arpy.cases.registry.Case.figure`)."""
    comm = getattr(args, "comm", None)
    r = advection(**CASE.kwargs(args, "advection"), progress=not args.quiet,
                  checkpoint=CASE.checkpoint(args), comm=comm)
    sim = r["sim"]
    print(f"arpy run advection: a blob in the reversing vortex (Reboux et al. 2012, Sec. 4.2), RK4, dt = 0.025, "
          f"D0 = {args.D0:g}, monitor {args.monitor}")
    print(f"  particles: {r['N']} at T (largest {r['N_max']}), h = 1/sqrt(N_max) = {r['h']:.4g}; "
          f"{r['steps']} steps in {r['wall_s']:.1f} s" + (f" on {comm.size} MPI ranks" if comm is not None else ""))
    print(f"  L-infinity error of Eq. 4.5 at T: {r['error']:.3e}")
    summary = {"t": sim.t, **{k: r[k] for k in ("N", "N_max", "h", "steps", "wall_s", "error", "median_error")}}
    rows = {k: r[k] for k in ("keys", "x", "f", "D")}
    sets = {"half": r["half"]} if r["half"] else {}
    npz = CASE.save(args, out / "advection.npz", summary, rows=rows, sets=sets)
    CASE.vtu(args, out / "advection_particles.vtu", r["x"], f=r["f"], D=r["D"])
    CASE.figure(args, out / "advection.png", npz, rows, lambda whole, path: _plot({**r, **whole}, path), sets=sets)
    return summary


#: ``arpy run advection``.  --reach comes before --D0: the periodic box's check of D0 uses it.
CASE = Case(
    "advection", "Sec. 4.2: a blob in the reversing vortex, periodic unit square, RK4",
    (reach_option(advection),
     option(advection, "D0", "--D0", "coarsest resolution D0, a length (the box is the unit square)", *RESOLUTION,
            default_for=lambda a: advection_d0(a.monitor),
            shown=", ".join(f"{v:g} with --monitor {m}" for m, v in ADVECTION_D0.items())),
     time_option(advection),
     steps_option(advection),
     option(advection, "monitor", "--monitor",
            "the monitor: Eq. 2.8 (gradient) or Appendix B's Eq. B.13 from fourth derivatives (exact at t = 0, "
            "DC-PSE estimates at every re-organization)", type=str, choices=MONITORS),
     seed_option(advection), OUTPUT_EVERY, *CHECKPOINT),
    lambda a: domain(1.0, 2, periodic=True, coarsest=a.D0, reach=a.reach), run, seconds=69.8)
