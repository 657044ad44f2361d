"""§4.3 of Reboux et al. (2012): a Gaussian pulse (Eq. 4.6) rotated and diffused (Eq. 4.7) in 2D or
3D; the L-infinity error against Eq. 4.8 and the relative mass loss (Eq. 4.9) over time, on adaptive
particles (:func:`gaussian_pulse`) and with the remeshed-particle baseline (:func:`remeshed_pulse`).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .. import fields
from ..domain import Domain
from ..distributed import Comm, DistributedDCPSE
from ..adapt.organize import DEFAULT_SEED, MAX_PARTICLES, self_organize, start_share, valid_stencils
from ..particles import Particles
from ..plotting import counted, save_figure
from ..remesh import RemeshedLPM
from ..adapt.resolution import MONITORS, check_monitor, monitor_fourth
from ..simulation import Simulation
from .checkpoint import Checkpoint, case_checkpoint
from .registry import (CHECKPOINT, OUTPUT_EVERY, REMESHED, RESOLUTION, Case, Param, at_least, domain, few_steps,
                       option, reach_option, seed_option, steps_option, time_option)

__all__ = ["CASE", "COLUMNS", "MASS_CHUNK", "MASS_EVERY", "PULSE_D0", "PULSE_PE", "gaussian_pulse", "pulse_d0",
           "pulse_exact", "pulse_pe", "pulse_setup", "remeshed_line", "remeshed_pulse", "report_lines"]

#: The Peclet number per dimension when none is given.
PULSE_PE = {2: 1000.0, 3: 100.0}
#: ``arpy run pulse``'s steps between evaluations of the mass (--mass-every; :func:`gaussian_pulse` takes 0, no
#: cost its callers did not ask for): every other re-organization at the default ``reorganize_every`` (10),
#: always at the same phase of the re-organization cycle (the mass jumps at each re-organization); 9 samples
#: on the default run, which then takes about 40 % more CPU time than with 0.
MASS_EVERY = 20
#: The mesh points of the mass integral each rank interpolates to at once (its memory: about 2 kB a point in
#: 2D; the whole 301^2 mesh at once took 180 MiB).
MASS_CHUNK = 16384
#: The coarsest resolution D0 per (monitor, dimension) when none is given: about as many particles with
#: Eq. 2.8 ("gradient") as with Eq. B.13 ("fourth").
PULSE_D0 = {("gradient", 2): 0.08, ("gradient", 3): 0.5, ("fourth", 2): 0.2, ("fourth", 3): 1.0}


def _check_dimension(d: int) -> None:
    if d not in (2, 3):
        raise ValueError("d must be 2 or 3")


def pulse_pe(d: int, Pe: float | None = None) -> float:
    """The Peclet number of the pulse in ``d`` dimensions: ``Pe``, or :data:`PULSE_PE` if None."""
    _check_dimension(d)
    return PULSE_PE[d] if Pe is None else float(Pe)


def pulse_d0(d: int, monitor: str, D0: float | None = None) -> float:
    """The coarsest resolution of the pulse: ``D0``, or :data:`PULSE_D0` of (monitor, d) if None."""
    _check_dimension(d)
    return PULSE_D0[monitor, d] if D0 is None else float(D0)


def pulse_setup(d: int, Pe: float) -> dict:
    """Domain, centre, velocity and exact solution of the §4.3 pulse.

    Parameters
    ----------
    d : int
        Dimension, 2 or 3.
    Pe : float
        Peclet number; the diffusivity is 1 / Pe.

    Returns
    -------
    dict
        ``box`` (lo, hi), each (d,): the cube [-1, 1]^2 or [-1.5, 1.5]^3; ``x0`` (d,): the initial
        centre; ``centre(t)`` -> (d,); ``flow(x, t, dt)``: the rotation by 2 pi dt, x (n, d) -> (n, d);
        ``exact(x, t)`` -> (n,) (Eq. 4.8); ``grad0(x)`` -> (n, d) and ``fourth0(x)`` -> (n, 5 or 15):
        the gradient and the fourth derivatives at t = 0; ``mass``: the integral of f.
    """
    if d == 2:
        half, x0 = 1.0, np.array([0.58, 0.02])
    elif d == 3:
        half, x0 = 1.5, np.array([0.58, 0.02, 0.02])
    else:
        raise ValueError("d must be 2 or 3")

    def centre(t: float) -> np.ndarray:
        th = 2 * np.pi * t
        c = x0.copy()
        c[0], c[1] = x0[0] * np.cos(th) + x0[1] * np.sin(th), -x0[0] * np.sin(th) + x0[1] * np.cos(th)
        return c

    def flow(x: np.ndarray, t: float, dt: float) -> np.ndarray:
        """Rigid rotation u = 2 pi (y, -x[, 0]) by the angle 2 pi dt, inside the
        cylinder r_xy < half (so that no particle leaves the box; outside it f < 1e-9)."""
        th = 2 * np.pi * dt
        c, s = np.cos(th), np.sin(th)
        y = x.copy()
        y[:, 0], y[:, 1] = x[:, 0] * c + x[:, 1] * s, -x[:, 0] * s + x[:, 1] * c
        inside = x[:, 0] ** 2 + x[:, 1] ** 2 < half ** 2
        return np.where(inside[:, None], y, x)

    def exact(x: np.ndarray, t: float) -> np.ndarray:
        return pulse_exact(x, t, centre(t), Pe, d)

    def grad0(x: np.ndarray) -> np.ndarray:
        r = x - x0
        return (-Pe / 2) * r * np.exp(-Pe * (r ** 2).sum(1) / 4)[:, None]

    def fourth0(x: np.ndarray) -> np.ndarray:
        """The fourth partial derivatives of Eq. 4.6 (n, 5 in 2D, 15 in 3D), ordered as
        :func:`arpy.adapt.resolution.fourth_multi_indices`: f = exp(-a r^2), a = Pe / 4, has
        D^k f = (-2 a)^k f with D = (1/r) d/dr."""
        r = x - x0
        f = np.exp(-Pe * (r ** 2).sum(1) / 4)
        a2 = -Pe / 2
        return fields.radial_fourth_all(r, (a2 ** 2 * f, a2 ** 3 * f, a2 ** 4 * f))

    return dict(box=(-half * np.ones(d), half * np.ones(d)), x0=x0, centre=centre, flow=flow, exact=exact,
                grad0=grad0, fourth0=fourth0, mass=(4 * np.pi / Pe) ** (d / 2))


def pulse_exact(x: np.ndarray, t: float, centre: np.ndarray, Pe: float, d: int) -> np.ndarray:
    """Eq. 4.8 at any t: ``(1 + t)^(-d/2) exp(-Pe |x - c(t)|^2 / (4 (1 + t)))``.

    x (n, d), centre (d,) the centre c(t) at time t; returns (n,).
    """
    return (1 + t) ** (-d / 2) * np.exp(-Pe * ((x - centre) ** 2).sum(1) / (4 * (1 + t)))


def _mass(sim: Simulation, centre: np.ndarray, Pe: float, t: float, points: int) -> float:
    """Integral of f_h: DC-PSE interpolation onto a fine Cartesian mesh around the pulse (6 sigma).
    Collective."""
    d = sim.x.shape[1]
    half = 6 * np.sqrt(2 * (1 + t) / Pe)
    axes = [np.linspace(c - half, c + half, points) for c in centre]
    mesh = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, d)
    lo, hi = sim.domain.lo, sim.domain.hi
    mesh = mesh[np.all((mesh >= lo) & (mesh <= hi), axis=1)]
    cell = (axes[0][1] - axes[0][0]) ** d
    # each rank interpolates to its share of the mesh points (Decomposition.deal: those its box holds,
    # or those of a fuller touching box nearest to its own, with a ghost layer that far wider), MASS_CHUNK at a
    # time (the same number of collective rounds on every rank; a point's value does not depend on the
    # others of its round); col_eps=None: each point takes the core size of its nearest source; the sum
    # is exact, so the mass is the same at every rank count and chunk size.  A point moves at most the
    # largest core size from its owner's box, so the ghost layer is at most that much wider than the
    # layer of the rank's own rows (a dense mesh could otherwise move points far, and the layer with them)
    p = sim.particles
    dealt, skin = p.decomposition.deal(mesh, most=p.gmax(float(p.eps.max(initial=0.0))))
    mine = mesh[dealt == p.comm.rank]
    values = []
    most = int(p.gmax(float(mine.shape[0])))                  # (the rounds: by the rank of the most points)
    for start in range(0, max(most, 1), MASS_CHUNK):
        op = DistributedDCPSE(p.comm, p.decomposition, p.x, p.eps, p.keys, mine[start:start + MASS_CHUNK], None,
                              domain=p.domain, order=sim.order, strict=False, operators=["interpolation"], skin=skin,
                              reorder=False)
        values.append(op.interpolation() @ op.extend(sim.f))
    return p.fsum(np.concatenate(values)) * cell


#: The names of the columns of :func:`gaussian_pulse`'s two-dimensional results.
COLUMNS: dict[str, tuple[str, ...]] = {"error_history": ("t", "error")}
def gaussian_pulse(d: int = 2, Pe: float | None = None, D0: float | None = None, T: float = 1.0,
                   reorganize_every: int = 10, integrator: str = "euler", seed: int = DEFAULT_SEED, mass_every: int = 0,
                   mass_points: int | None = None, reach: float = 1.0, monitor: str = "gradient",
                   reading: str = "implicit", stencil_rule: str = "repair", max_particles: int = MAX_PARTICLES,
                   cache_order: bool = False, progress: bool = False, checkpoint: Checkpoint | None = None,
                   comm: Comm | None = None) -> dict:
    """§4.3: the Gaussian pulse rotated once and diffused, on adaptive particles.

    Forward Euler with dt = h_min^2 Pe / 4 (the diffusion limit), rotation exact.  Eq. 2.8 leaves
    the pulse's peak, where grad f = 0, at a D_p set by the ball of Eq. 2.9 that scales as
    sqrt(D0); Eq. B.13 resolves it in proportion to D0.

    Parameters
    ----------
    d : int
        Dimension, 2 or 3.
    Pe : float, optional
        Peclet number (the diffusivity is 1 / Pe); None: :data:`PULSE_PE` (1000 in 2D, 100 in 3D).
    D0 : float, optional
        Coarsest resolution (length); None: :data:`PULSE_D0` (0.08 in 2D and 0.5 in 3D with
        Eq. 2.8, 0.2 and 1.0 with Eq. B.13: about as many particles).
    T : float
        Final time (1: one rotation).
    reorganize_every : int
        Time steps between re-organizations.
    integrator : str
        Time integrator of :class:`arpy.Simulation`.
    seed : int
        Seed of the random initial particles and insertions.
    mass_every : int
        Time steps between evaluations of the mass (Eq. 4.9), besides the start and the end (0: there
        only; ``arpy run pulse`` takes :data:`MASS_EVERY`).  Each evaluation interpolates f to the mass
        mesh: with the defaults, 0.25 s of a single core.
    mass_points : int, optional
        Mesh points per edge of the mass integral (default 301 in 2D, 61 in 3D).
    reach : float
        The factor on the ball of Eq. 2.9 (1: the paper's).
    monitor : str
        "gradient" -- the paper's Eq. 2.8 (initial particles from the exact gradient);
        "fourth" -- Appendix B's Eq. B.13 for m = 4 (initial particles from the exact fourth
        derivatives, then DC-PSE estimates at each re-organization; see :class:`arpy.Simulation`).
    reading : {"implicit", "explicit", "pointwise"}
        The reading of Eq. 2.9 (see :func:`arpy.adapt.resolution.graded_resolution`).
    stencil_rule : {"repair", "displace"}
        See :class:`arpy.Simulation`; with "displace" the initial set is displaced too
        (:func:`arpy.adapt.organize.displace_set`).
    max_particles : int
        See :class:`arpy.Simulation` (a re-organization beyond it raises RuntimeError).
    cache_order : bool
        Renumber the particles along the Morton curve at each re-organization (see
        :class:`arpy.Simulation`).
    progress : bool
        Show a progress bar.
    checkpoint : Checkpoint, optional
        Write the run's state every so many steps, or resume from it (:mod:`arpy.cases.checkpoint`).
    comm : Comm, optional
        Run over the ranks of a communicator (:mod:`arpy.distributed`; every rank calls this function
        with the same arguments): the initial self-organization, the time steps and the
        re-organizations are distributed, with results bitwise the same for every rank count and
        those of one process.

    Returns
    -------
    dict
        ``error``: the L-infinity error at T; ``N_initial``, ``N``, ``N_max``; ``h`` =
        ``|Omega|^(1/d) / N_max^(1/d)``; ``error_history`` (steps, 2): (t, error), the names of its
        columns in ``columns["error_history"]``; ``mass_t`` and
        ``mass_loss`` (m,): the relative mass loss (Eq. 4.9) over time; ``particles``: the initial
        :class:`arpy.Particles` (with ``comm`` on several ranks, this rank's share); ``sim``: the simulation; ``x``, ``f``, ``D``: the particles at T in
        key order, their keys ``keys`` (with ``comm``: this rank's, none gathered); ``exact``: Eq. 4.8,
        (x, t) -> f.
    """
    check_monitor(monitor, 4)
    Pe, D0 = pulse_pe(d, Pe), pulse_d0(d, monitor, D0)
    setup = pulse_setup(d, Pe)
    lo, hi = setup["box"]
    n0 = 800 if d == 2 else 3000
    x = np.random.default_rng(seed).uniform(lo, hi, (n0, d))
    t0 = time.perf_counter()
    cp = case_checkpoint(checkpoint, T)


    def initial() -> Particles:
        # on several ranks each rank adapts its share of the random start and keeps its share of the
        # result (and of its displacement under "displace"): no rank holds the whole set
        start: dict[str, Any] = dict(**start_share(x, comm), domain=Domain(setup["box"]), seed=seed, reach=reach,
                                     reading=reading, comm=comm)
        if monitor == "fourth":
            return self_organize(resolution=lambda p: monitor_fourth(setup["fourth0"](p), D0), D0=D0, **start)
        return self_organize(grad_f=setup["grad0"], D0=D0, **start)

    ps = cp.particles(lambda: valid_stencils(initial(), stencil_rule, seed))
    sim = Simulation(ps, lambda p: setup["exact"](p, 0.0), flow=setup["flow"], nu=1.0 / Pe, D0=D0,
                     integrator=integrator, reorganize_every=reorganize_every, seed=seed, reach=reach,
                     monitor=monitor, reading=reading, stencil_rule=stencil_rule, max_particles=max_particles,
                     cache_order=cache_order, comm=comm)
    points = mass_points or (301 if d == 2 else 61)
    mass = [] if cp.resume else [(0.0, _mass(sim, setup["centre"](0.0), Pe, 0.0, points))]   # (resumed: restored)
    errors = []

    def record(s: Simulation) -> None:
        local = np.abs(s.f - setup["exact"](s.x, s.t)).max(initial=0.0)
        errors.append((s.t, s.particles.gmax(local)))
        if mass_every and s.steps % mass_every == 0:
            mass.append((s.t, _mass(s, setup["centre"](s.t), Pe, s.t, points)))

    def restore(records: Mapping[str, np.ndarray]) -> None:
        errors[:] = [tuple(row) for row in records["errors"]]
        mass[:] = [tuple(row) for row in records["mass"]]

    cp.run(sim, T, progress=progress, callback=record, restore=restore,
           records=lambda: {"errors": np.array(errors).reshape(-1, 2), "mass": np.array(mass).reshape(-1, 2)})
    if not mass_every or mass[-1][0] < sim.t:
        mass.append((sim.t, _mass(sim, setup["centre"](sim.t), Pe, sim.t, points)))
    wall = time.perf_counter() - t0
    hist = sim.history()
    n_initial = ps.total(ps.n)
    n_max = int(max(n_initial, hist["n"].max()))
    volume = float(np.prod(hi - lo))
    mt, mv = (np.array(c) for c in zip(*mass))
    n_final = int(hist["n"][-1]) if len(hist["n"]) else n_initial
    kT, xT, DT, FT = sim.particles.ordered()
    return dict(d=d, Pe=Pe, D0=D0, monitor=monitor, error=errors[-1][1], N_initial=n_initial, N=n_final, N_max=n_max,
                h=(volume / n_max) ** (1 / d), steps=sim.steps, wall_s=wall,
                error_history=np.array(errors), columns=COLUMNS, mass_t=mt,
                mass_loss=(setup["mass"] - mv) / setup["mass"],
                degenerate_max=int(hist["degenerate"].max()), particles=ps, sim=sim, keys=kT, x=xT, f=FT[:, 0], D=DT,
                exact=setup["exact"])


def remeshed_pulse(d: int = 2, Pe: float | None = None, n_cells: int = 128, T: float = 1.0) -> dict:
    """§4.3 with the remeshed particle method on a uniform mesh.

    Parameters
    ----------
    d : int
        Dimension, 2 or 3.
    Pe : float, optional
        Peclet number; None: :data:`PULSE_PE`.
    n_cells : int
        Mesh cells per edge of the box.
    T : float
        Final time.

    Returns
    -------
    dict
        ``N`` (mesh particles), ``h`` (mesh spacing), ``error`` (L-infinity at T), ``steps``,
        ``wall_s`` (seconds), ``mass_loss`` (Eq. 4.9 at T).
    """
    Pe = pulse_pe(d, Pe)
    setup = pulse_setup(d, Pe)
    lo, hi = setup["box"]
    t0 = time.perf_counter()
    r = RemeshedLPM(lambda p: setup["exact"](p, 0.0), (lo, hi), float(hi[0] - lo[0]) / n_cells, nu=1.0 / Pe,
                    flow=setup["flow"]).run(T)
    err = float(np.abs(r.f.ravel() - setup["exact"](r.nodes, T)).max())
    mass = r.f.sum() * r.h ** d
    return dict(d=d, Pe=Pe, N=r.n, h=r.h, error=err, steps=r.steps, wall_s=time.perf_counter() - t0,
                mass_loss=(setup["mass"] - mass) / setup["mass"])


# ---------------------------------------------------------------- arpy run pulse
def _plot(r: dict, path: Path) -> None:
    """The 2D run's figure: f on the particles, D_p, and (right, one above the other) the error and the
    mass loss over time."""
    import matplotlib.pyplot as plt

    sim = r["sim"]
    fig = plt.figure(figsize=(16, 5.2))
    grid = fig.add_gridspec(2, 3)
    axes = [fig.add_subplot(grid[:, 0]), fig.add_subplot(grid[:, 1])]
    err_ax = fig.add_subplot(grid[0, 2])
    mass_ax = fig.add_subplot(grid[1, 2], sharex=err_ax)
    x, f, D = r["x"], r["f"], r["D"]
    sc = axes[0].scatter(x[:, 0], x[:, 1], c=f, s=2, cmap="viridis")
    fig.colorbar(sc, ax=axes[0], label="f")
    axes[0].set_aspect("equal")
    axes[0].set_xlabel("x")
    axes[0].set_ylabel("y")
    axes[0].set_title(f"f at t = {sim.t:g}\n({counted(x.shape[0], r.get('N'))})")
    Particles(x, D, sim.rstar, 10, sim.domain).plot(
        ax=axes[1], title="D_p (colour)\ncircles of 8 particles: D_p dashed, r_c solid", circles=8)
    axes[1].set_xlabel("x")
    axes[1].set_ylabel("y")
    history = r["error_history"]
    err_ax.semilogy(history[:, 0], history[:, 1], "o-" if len(history) < 3 else "-", ms=3)   # (a step or two: dots)
    err_ax.set_ylabel("L-infinity error")
    err_ax.tick_params(labelbottom=False)
    err_ax.set_title("error against Eq. 4.8 (every step)")
    # the mass loss changes sign: a linear axis, not |.| on a log axis
    mass_ax.plot(r["mass_t"], r["mass_loss"], "o-", color="C1", ms=3)
    mass_ax.axhline(0.0, color="k", lw=0.5)
    mass_ax.set_xlabel("t")
    mass_ax.set_ylabel("relative mass loss")
    mass_ax.set_title(f"mass loss, Eq. 4.9 ({len(r['mass_t'])} samples)")
    save_figure(fig, path)


def report_lines(s: dict) -> list[str]:
    """What ``arpy run pulse`` prints about the adaptive run, from its summary ``s`` (the ``summary`` of
    ``arpy run pulse --json``)."""
    lines = [f"arpy run pulse: Gaussian pulse rotated and diffused (Reboux et al. 2012, Sec. 4.3), d = {s['d']}, "
             f"Pe = {s['Pe']:g}, D0 = {s['D0']:g}, T = {s['T']:g}, monitor {s['monitor']}",
             f"  particles: {s['N_initial']} at t = 0, {s['N']} at t = T (largest {s['N_max']}), "
             f"h = {s['h']:.4g}; {s['steps']} steps in {s['wall_s']:.1f} s"
             + (f" on {s['ranks']} MPI ranks" if s.get("ranks") else ""),
             f"  L-infinity error at T against Eq. 4.8: {s['error']:.3e}",
             f"  relative mass loss (Eq. 4.9) at T: {s['mass_loss']:.3e}"]
    if s["degenerate_max"]:
        lines.append(f"  note: up to {s['degenerate_max']} particles per step had no valid DC-PSE stencil")
    return lines


def remeshed_line(b: dict) -> str:
    """What ``arpy run pulse`` prints about the remeshed baseline, from ``summary["remeshed"]``."""
    return (f"  remeshed particle method, {b['N']} particles (h = {b['h']:.4g}): error {b['error']:.3e}, "
            f"{b['steps']} steps in {b['wall_s']:.1f} s")


def run(args: argparse.Namespace, out: Path) -> dict:
    """``arpy run pulse``: prints the errors, mass loss and cost (and the remeshed baseline's
    with ``--remeshed``); writes pulse.npz, pulse_particles.vtu and, in 2D, pulse.png; returns the
    summary.  Under mpiexec no rank gathers the particles: pulse.npz is the index of one piece per
    rank, pulse_particles.pvtu names one .vtu piece per rank, and rank 0 draws pulse.png from the pieces
    read back (of more than :data:`~arpy.cases.registry.FIGURE_POINTS` particles, a sample;
    :meth:`Case.figure`)."""
    comm = getattr(args, "comm", None)
    r = gaussian_pulse(**CASE.kwargs(args, "gaussian_pulse"), mass_every=args.mass_every, progress=not args.quiet,
                       checkpoint=CASE.checkpoint(args), comm=comm)
    sim = r["sim"]
    summary = {k: r[k] for k in ("d", "Pe", "D0", "monitor", "N_initial", "N", "N_max", "h", "steps", "wall_s",
                                 "error", "degenerate_max")}
    summary.update(T=args.T, t=sim.t, mass_loss=r["mass_loss"][-1], ranks=None if comm is None else comm.size)
    print("\n".join(report_lines(summary)))
    if args.remeshed and (comm is None or comm.rank == 0):
        base = remeshed_pulse(d=r["d"], Pe=r["Pe"], T=args.T, **CASE.kwargs(args, "remeshed_pulse"))
        summary["remeshed"] = {k: base[k] for k in ("N", "h", "error", "steps", "wall_s")}
        print(remeshed_line(summary["remeshed"]))
    x, f, D = r["x"], r["f"], r["D"]
    f_exact = r["exact"](x, sim.t)
    rows = dict(keys=r["keys"], x=x, f=f, D=D, f_exact=f_exact)
    npz = CASE.save(args, out / "pulse.npz", summary, rows=rows, t=sim.t, error_history=r["error_history"],
                    mass_t=r["mass_t"], mass_loss=r["mass_loss"], n_history=sim.history()["n"])
    CASE.vtu(args, out / "pulse_particles.vtu", x, f=f, D=D, error=f - f_exact)
    if r["d"] == 2:
        CASE.figure(args, out / "pulse.png", npz, rows, lambda whole, path: _plot({**r, **whole}, path))
    return summary


def _context(args: argparse.Namespace) -> dict:
    """The pulse's box (:func:`pulse_setup`): a cube of edge 2 in 2D, 3 in 3D."""
    lo, hi = pulse_setup(args.d, 1.0)["box"]
    return domain(float(hi[0] - lo[0]), args.d)


#: ``arpy run pulse``.  --reach comes before --D0: the box's check of D0 uses it.
CASE = Case(
    "pulse", "Sec. 4.3: a Gaussian pulse rotated and diffused, 2D or 3D (the default case)",
    (option(gaussian_pulse, "d", "--d", "dimension", type=int, choices=(2, 3)),
     option(gaussian_pulse, "Pe", "--pe", "Peclet number, dimensionless; the diffusivity is 1 / Pe",
            at_least(0, strict=True, what=" (the Peclet number; the diffusivity is 1 / Pe)"),
            few_steps(lambda v: 1 / v),
            default_for=lambda a: pulse_pe(a.d), shown=", ".join(f"{v:g} in {d}D" for d, v in PULSE_PE.items())),
     reach_option(gaussian_pulse),
     option(gaussian_pulse, "D0", "--D0",
            "coarsest resolution D0, a length (the box: [-1, 1]^2 in 2D, [-1.5, 1.5]^3 in 3D)", *RESOLUTION,
            default_for=lambda a: pulse_d0(a.d, a.monitor),
            shown=", ".join(f"{v:g} in {d}D with --monitor {m}" for (m, d), v in PULSE_D0.items())),
     time_option(gaussian_pulse),
     steps_option(gaussian_pulse),
     option(remeshed_pulse, "n_cells", "--remeshed",
            "also run the remeshed-particle baseline with this many mesh cells per edge (0: skip it)", *REMESHED,
            type=int),
     Param("--mass-every", "time steps between evaluations of the mass (Eq. 4.9) besides the start and the end "
           "(0: there only); each costs about 0.25 s at the defaults", type=int, default=MASS_EVERY,
           checks=(at_least(0, kind="an integer", what=" (0: at the start and the end)"),)),
     option(gaussian_pulse, "monitor", "--monitor",
            "the monitor: Eq. 2.8 (gradient) or Appendix B's Eq. B.13 from fourth derivatives (exact at t = 0, "
            "DC-PSE estimates at every re-organization)", type=str, choices=MONITORS),
     seed_option(gaussian_pulse), OUTPUT_EVERY, *CHECKPOINT),
    _context, run, columns=COLUMNS, seconds=7.9)
