"""Adaptive-resolution particle simulations: the workflow of §3.2.2 (Reboux et al. 2012).

A field f is carried by particles that move with a velocity u and change by an elliptic operator, here
diffusion nu * Laplacian, discretized with DC-PSE (the non-conservative form df/dt + u . grad f = nu lap f,
Eqs. 4.2, 4.7, 4.10)::

    dx_p/dt = u(x_p, t, f_p),      df_p/dt = nu (lap_h f)_p.

Each step:

1. the step size: dt given, or ``min(cfl h_min / max|u|, h_min^2 / (4 nu))`` with h_min the smallest distance
   between two particles (§4.3);
2. advection: the exact flow map if one is given (``flow``), else forward Euler or RK4 on dx/dt = u;
3. every ``reorganize_every`` steps, re-organization (step 4): DC-PSE gradient on the old particles, monitor
   ``D~ = D0 / sqrt(1 + |grad f|^2)`` (or, with ``monitor="fourth"``, Eq. B.13 from DC-PSE fourth derivatives),
   D_p by Eq. 2.9, adaptation by :func:`arpy.self_organize`, then one DC-PSE factorisation per new particle (old
   particles as sources) for both the interpolating kernel and the Laplacian (variant (ii) of §2.2): f is
   interpolated old -> new and, with forward Euler, the right-hand side is taken from the old values at the new
   particles (step 5);
4. f advances by forward Euler or RK4 (each RK4 stage assembles the Laplacian at the stage positions; a stage
   whose particles have not moved since the last one, as without a flow, uses its operators again).

Other equations, wall conditions and conserved densities: :mod:`arpy.equations` (what is solved; the operators
of :class:`arpy.dcpse.operators.Operators` are assembled once per stage and shared by every term). One process
is P = 1: the particles live in an :class:`arpy.particles.Particles`, and the same code runs on the ranks of a
communicator (``comm``), bitwise the same for every rank count.

Boundaries come from the particles' :class:`arpy.Domain`: periodic axes give periodic images as DC-PSE sources,
walls mirror images (homogeneous Neumann, §2.4); particles that leave a walled box are put back on its walls at
the next re-organization. Every DC-PSE operator is built with the repair policy :data:`arpy.dcpse.domain.REPAIR`
(failed stencils widened, wild ones rebuilt), or, with ``stencil_rule="displace"``, without repair on particles
that each re-organization displaced or inserted until every stencil was valid (the paper's rule,
:func:`arpy.dcpse.displace.displace_until_valid`; the log gains ``displaced`` and ``inserted``). Particles still
without a stencil get no update in that step (new particles: the value of the nearest old one), and the log
counts them (``degenerate``). With ``bounded=True`` the interpolation old -> new is limited to the range of each
stencil's old values (:meth:`arpy.dcpse.domain.DomainDCPSE.interpolate`): no new extrema at steep fronts, at the
price of clipping true peaks.
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Collection, Mapping

import numpy as np

from ._validate import check_count
from .domain import as_domain
from .dcpse.boundary import Condition
from .equations import STABILITY, Equations, StabilityError, check_finite, rk4_step, unstable
from .reorganization import reorganize, settle
from .distributed import DistributedDCPSE, agree
from .distributed.balance import CostBalance
from .distributed.kept import KeptGhosts, reused_lists
from .particles import Particles, log_arrays, of_particles
from .state import Records, Run, Shares, State, read_state, run_identity, write_state
from .adapt.organize import DEFAULT_SEED, MAX_PARTICLES
from .adapt.resolution import check_monitor, check_reach, check_reading
from .dcpse.displace import repair_for
from .dcpse.domain import DomainDCPSE
from .dcpse.operators import Reused
from .lists.reuse import ReusedLists

if TYPE_CHECKING:
    from .distributed import Comm, Decomposition

__all__ = ["Simulation", "rk4_step"]

INTEGRATORS = ("euler", "rk4")
#: Wall-time phases of a step in the log (s): the monitor (DC-PSE gradient and Eq. 2.9),
#: self-organization (its neighbour lists, the rest), DC-PSE old -> new (interpolation and the
#: right-hand side at a re-organization), and the right-hand side at the other steps / RK4 stages.
PHASES = ("t_monitor", "t_organize_lists", "t_organize_rest", "t_interpolate", "t_rhs")
#: The entries of every step's log (:meth:`Simulation.history`), with the type of their values.
STEP_KEYS: dict[str, type] = dict(step=int, t=float, dt=float, reorganized=bool, so_iterations=int, n=int, D_min=float,
                                  D_max=float, degenerate=int, heavy=int, dt_stable=float, t_reorganize=float,
                                  **dict.fromkeys(PHASES, float), t_step=float)


class Simulation:
    """An adaptive-resolution simulation of df/dt + u . grad f = nu lap f, or of any right-hand side,
    on self-organizing particles.

    Parameters
    ----------
    particles : Particles
        The initial particles, e.g. from :func:`arpy.self_organize` (its domain is the
        simulation's): the whole set, or with ``comm`` on several ranks this rank's share of it.
    f : array (n,), callable, or mapping of names to them
        Initial values at the particles, or a callable of positions; a mapping ``{name: values}``
        for several fields (a system), whose rates ``rhs`` gives.  One field is named "f".
    rhs : callable, optional
        ``rhs(t, x, fields, ops) -> {name: rate (n,)}``: the rates of the fields at the particles x
        (n, d) at time t, from ``fields`` (a dict of arrays (n,)) and the DC-PSE operators ``ops``
        (:class:`arpy.dcpse.operators.Operators`: ``ops.laplacian("u")``, ``ops.gradient("u")``,
        ``ops.diffusion(k, "u")``, ``ops.divergence(v)``, ``ops.derivative(alpha, "u")``); a field
        it leaves out does not change (besides ``conservative``).  With one field it may return the
        array.  None: ``nu lap f``.
    velocity : callable, optional
        ``(x (n, d), t, f) -> (n, d)`` with f the field (n,), or the dict of fields of a system;
        None: no motion.
    flow : callable, optional
        Exact flow map ``(x, t, dt) ->`` positions at t + dt (the paper computes the rigid-body
        rotation of §4.3 exactly).
    nu : float
        Diffusivity (>= 0) of the built-in right-hand side ``nu lap f`` (of every field); with ``rhs``, the largest
        diffusivity of its terms: the default step and the stability bound of the Laplacians it applies.
    boundary : condition, mapping, or None
        Conditions at the walls (:mod:`arpy.dcpse.boundary`): for one field a
        :class:`~arpy.dcpse.boundary.Dirichlet` value or :class:`~arpy.dcpse.boundary.Neumann` flux for every
        wall, or a mapping of faces (``"x-"``, ``"x+"``, ``"y-"``, ...) to them; for a system a
        mapping of field names to such.  Unnamed walls and fields: homogeneous Neumann.  Particles
        closer than :data:`~arpy.equations.SNAP` times their core size to a Dirichlet face are moved onto it (at the
        start, after every step and every re-organization: such a particle's one-sided stencil has
        a boundary particle almost on top of it and weights of either sign far above 1 / eps^2,
        which makes the time stepping unstable), their values interpolated from where they were
        (initial values given as callables are evaluated there), and the particles on it carry its
        value.
    conservative : bool
        The fields are densities carried by the flow (Eq. 2.3b): every rate gains ``-f div u``, with
        div u the DC-PSE divergence of the velocity at the particles (ghosts: the slip-wall image).
    monitor_fields : sequence of str, optional
        The fields the monitor follows (the finest resolution any of them asks for); None: all.
    D0, Dmin : float
        The monitor function's coarsest and finest resolution (Dmin optional).
    monitor : {"gradient", "fourth"}
        "gradient" (Eq. 2.8, the paper's) or "fourth" (Appendix B's Eq. B.13
        for m = 4, from DC-PSE fourth derivatives of the old values; see
        :func:`arpy.adapt.resolution.field_resolution`).  Eq. 2.8 leaves the flanks of a
        front at about D0, which caps the convergence of the maximum error.
    potential : str
        Self-organization potential (see :func:`arpy.self_organize`).
    order : int
        DC-PSE order.
    reach : float
        Factor on the ball of Eq. 2.9 (1: the paper's; see :func:`arpy.self_organize`).
    reading : {"implicit", "explicit", "pointwise"}
        The reading of Eq. 2.9 (see :func:`arpy.adapt.resolution.graded_resolution`).
    stencil_rule : {"repair", "displace"}
        Stencils the moment conditions cannot use: repaired (arpy's rules, :data:`arpy.dcpse.domain.REPAIR`)
        or, at each re-organization, removed by displacing and inserting particles (the paper's §2.2,
        :func:`arpy.dcpse.displace.displace_until_valid`; the initial set is taken as given).  Not with
        Dirichlet walls (their one-sided rows are a repair).
    integrator : {"euler", "rk4"}
        The time integrator.
    dt : float, optional
        Fixed step; None: ``min(cfl h_min / max|u|, h_min^2 / (4 nu), max_dt)``.  Every step is checked
        against the stability bound of the operators its right-hand side used, at every assembly (each
        RK stage, at the stage positions): with rho a bound on their spectral radius from the row sums
        of their matrices (Gershgorin; ``nu max_p sum_q |L_pq|`` for ``nu lap f``; for an ``rhs``, what
        :meth:`arpy.equations.Equations.spectral_radius` covers), the bound is 2 / rho (Euler) or 2.785 /
        rho (RK4), logged as ``dt_stable``.  A default step above it is undone and taken again at the
        bound; a fixed step above it is undone and refused (:class:`arpy.StabilityError`).  Before that,
        each assembly rebuilds the rows of the Laplacian at the particles that alone would make the step
        unstable, ``sum_q |L_pq| > STABILITY / (nu dt)`` (:func:`arpy.dcpse.rows.wild_rows`; the log counts
        them, ``heavy``).  Non-finite fields, rates or positions stop the run (:class:`arpy.NonFiniteError`).
    cfl : float
        The CFL number of the default step.
    max_dt : float, optional
        The largest default step (time; with ``dt=None``): a step the simulation takes again at the
        stability bound where that is lower, as an ``rhs`` whose stiffness grows during the run needs.
    reorganize_every : int
        Steps between re-organizations; 0: never, the fixed-particle stepping of any number of ranks
        (the particles keep their keys and D, and move only with ``velocity`` or ``flow``).
    seed : int, optional
        Seed of the insertion positions (default: :data:`arpy.adapt.organize.DEFAULT_SEED`, 1, as in
        :func:`arpy.self_organize` and the cases; None: a fresh random seed).
    max_iter : int
        Most adaptation iterations per re-organization.  A re-organization starts from an adapted set
        and settles in a few (at most 10 in the pulse's run at the defaults); one that has not by then
        mostly cycles, its insertions and fusions balancing, and more iterations would not settle it.
        One that stops unconverged warns (:class:`arpy.NotConvergedWarning`, saying which it does).
    max_particles : int
        A re-organization that would make more particles raises RuntimeError (a bound on runaway
        refinement; see :func:`arpy.self_organize`).
    bounded : bool
        Limit the interpolation old -> new to each stencil's range of old
        values (for fields that must stay in their range, e.g. a saturation).
    verlet_skin : float
        The operators' sources and neighbour lists are kept across RK stages and steps (Verlet
        lists with a skin of this fraction of the smallest core size, rebuilt once a particle has
        moved half of it or the particles change; on ranks also when a particle changes rank); 0:
        new lists at every stage.  In a box they are the ghost layer and the rows
        (:class:`arpy.distributed.kept.KeptGhosts`, on any number of ranks): the results are bitwise
        those of ``verlet_skin=0``.  In free space (one process) :class:`arpy.lists.reuse.ReusedLists`
        numbers its ghosts as the wider build made them, so results differ by rounding from
        ``verlet_skin=0`` there.
    cache_order : bool
        Put the new particles of every re-organization in cache order (along the Morton curve,
        :func:`arpy.cache_order`) before anything is built on them, so that neighbour lists,
        DC-PSE assembly and the operators' products read memory in order.  The particle set is
        rebuilt at a re-organization anyway; only the numbering changes, which moves results by
        rounding (sums in another order) and changes which random draws the next adaptation's
        insertions take (they are keyed on particle indices).
    allow_unstable_dt : bool
        Take a fixed ``dt`` above the stability bound anyway, with a warning (once).
    comm : Comm, optional
        The ranks of a communicator (:mod:`arpy.distributed`; ``MPIComm()`` under ``mpiexec``);
        default: this process alone, P = 1.  A simulation is the same code at every rank count: its
        particles live in an :class:`arpy.particles.Particles` (:attr:`particles`: every rank passes
        the same ``particles`` and initial values and keeps those its box owns; or each its share of a set
        spread over the ranks, e.g. of :func:`arpy.self_organize` with ``keys=``, and initial values of it:
        no rank holds the whole set, the keys become their places in key order), the operators are built over
        each rank's particles and ghosts with rows summed in key order, stage positions
        stay beside the box, the particles migrate after each step, and re-organizations number the
        new particles by key over all ranks, so the fields, by key, are bitwise the same for every
        rank count.  ``x``, ``D``, ``F`` and ``keys`` (at the start: the indices into ``particles``)
        are this rank's particles; :meth:`gather` gives the whole set; the log's figures are global;
        :meth:`save_state` and :meth:`load_state` work on any number of ranks; so do ``verlet_skin``,
        ``stencil_rule="displace"`` (:func:`arpy.dcpse.displace.displace_on_ranks`) and Dirichlet walls
        (each rank makes the boundary particles of its particles and ghosts, keyed by face and their
        particle's key; :class:`arpy.distributed.DistributedDCPSE`).  On several ranks not yet with
        ``cache_order`` (one process takes it).

    Examples
    --------
    A blob carried by a uniform flow and diffused in a periodic box, starting from uniform
    particles; the first step re-organizes them around the blob:

    >>> import numpy as np
    >>> import arpy
    >>> box = arpy.Domain([1.0, 1.0], periodic=True)
    >>> def uniform(p):
    ...     return np.full(len(p), 0.1)
    >>> ps = arpy.self_organize(np.random.default_rng(0).random((200, 2)), uniform, domain=box, seed=0)
    >>> def blob(p):
    ...     return np.exp(-40 * ((p - 0.5) ** 2).sum(1))
    >>> def u(x, t, f):
    ...     return np.ones_like(x)
    >>> sim = arpy.Simulation(ps, blob, velocity=u, nu=0.01, D0=0.1, Dmin=0.04, reorganize_every=5)
    >>> sim = sim.run(0.02)
    >>> round(sim.t, 12), sim.n > ps.n
    (0.02, True)
    >>> history = sim.history()
    >>> len(history["t"]) == sim.steps, bool(history["reorganized"][0])
    (True, True)

    A reaction-diffusion system (two fields, their own diffusivities, a reaction term) in a box
    whose wall x = 0 lets u flow in (du/dn = -1: n points out of the box) and holds v = 0 at y = 1:

    >>> from arpy.dcpse.boundary import Dirichlet, Neumann
    >>> walls = arpy.Domain([1.0, 1.0])
    >>> ps = arpy.self_organize(np.random.default_rng(0).random((200, 2)), uniform, domain=walls, seed=0)
    >>> def rates(t, x, f, ops):
    ...     r = f["u"] * f["v"] ** 2
    ...     return {"u": 1e-3 * ops.laplacian("u") - r, "v": 5e-4 * ops.laplacian("v") + r - 0.1 * f["v"]}
    >>> sim = arpy.Simulation(ps, {"u": np.ones(ps.n), "v": blob(ps.x)}, rhs=rates, dt=0.1, D0=0.1,
    ...                       reorganize_every=0, boundary={"u": {"x-": Neumann(-1.0)},
    ...                                                         "v": {"y+": Dirichlet(0.0)}})
    >>> sim = sim.run(1.0)
    >>> sorted(sim.fields), sim.steps
    (['u', 'v'], 10)
    """

    def __init__(self, particles: Particles,
                 f: np.ndarray | Callable[[np.ndarray], np.ndarray] | Mapping[str, np.ndarray | Callable], *,
                 rhs: Callable | None = None, velocity: Callable | None = None, flow: Callable | None = None,
                 nu: float = 0.0, boundary: Condition | Mapping | None = None, conservative: bool = False,
                 monitor_fields: tuple[str, ...] | list[str] | None = None,
                 D0: float, Dmin: float | None = None, potential: str = "V2", order: int = 4,
                 reach: float = 1.0, reading: str = "implicit", stencil_rule: str = "repair", monitor: str = "gradient",
                 integrator: str = "euler", dt: float | None = None, cfl: float = 0.5, max_dt: float | None = None,
                 reorganize_every: int = 10, seed: int | None = DEFAULT_SEED, max_iter: int = 100,
                 max_particles: int = MAX_PARTICLES,
                 bounded: bool = False, verlet_skin: float = 0.0, cache_order: bool = False,
                 allow_unstable_dt: bool = False, comm: "Comm | None" = None) -> None:
        if not isinstance(particles, Particles):
            raise TypeError("particles must be an arpy.Particles (e.g. from arpy.self_organize)")
        if particles.parallel and (comm is None or (comm.size, comm.rank) != (particles.comm.size, particles.comm.rank)):
            raise ValueError("particles on several ranks (a share of a set) need comm= of those ranks")
        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
        if not (np.isfinite(nu) and nu >= 0):
            raise ValueError("nu must be a finite number >= 0")
        for name, v in (("dt", dt), ("max_dt", max_dt)):
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0")
        if dt is not None and max_dt is not None:
            raise ValueError("give dt (a fixed step) or max_dt (the largest default step), not both")
        if int(reorganize_every) != reorganize_every or reorganize_every < 0:
            raise ValueError("reorganize_every must be an integer >= 0")
        if not (np.isfinite(cfl) and cfl > 0):
            raise ValueError(f"cfl must be a finite number > 0, got {cfl!r}")
        check_count("max_iter", max_iter)
        check_count("max_particles", max_particles)
        if not (np.isfinite(verlet_skin) and verlet_skin >= 0):
            raise ValueError(f"verlet_skin must be a finite number >= 0, got {verlet_skin!r}")
        check_reach(reach)
        check_reading(reading)
        self._repair = repair_for(stencil_rule)
        check_monitor(monitor, order)
        if nu == 0 and velocity is None and flow is None and dt is None and max_dt is None:
            raise ValueError("nothing sets the time step: give dt, max_dt, a velocity or nu > 0")
        x_given = np.array(particles.x, dtype=np.float64)
        self.rstar, self.domain = particles.rstar, as_domain(particles.domain, x_given.shape[1], name="particles.domain")
        #: The communicator given (None: one process); the particles' own is ``particles.comm``.
        self.comm = comm
        options = dict(domain=self.domain, rstar=self.rstar, rhs=rhs, velocity=velocity, flow=flow, nu=nu,
                       boundary=boundary, conservative=conservative, monitor_fields=monitor_fields, D0=D0, Dmin=Dmin,
                       potential=potential, order=order, reach=reach, reading=reading, stencil_rule=stencil_rule,
                       monitor=monitor, integrator=integrator, dt=dt, cfl=cfl, reorganize_every=reorganize_every,
                       seed=seed, max_iter=max_iter, max_particles=max_particles, bounded=bounded,
                       verlet_skin=verlet_skin, cache_order=cache_order, **({} if max_dt is None else {"max_dt": max_dt}))
        agree(comm, "Simulation(comm=)", **options)
        if comm is not None and comm.size > 1:
            if cache_order:
                raise NotImplementedError("a distributed Simulation (comm=) takes cache_order=False (each rank "
                                          "keeps its particles in cache order anyway)")
            if not self.domain.bounded:
                raise ValueError("a distributed Simulation (comm=) needs a box (a Domain with walls or periodic axes)")
        #: What is solved: the fields, their right-hand side, the motion, the walls' conditions.
        self.eq = Equations(f, self.domain, rhs=rhs, velocity=velocity, flow=flow, nu=nu, boundary=boundary,
                            conservative=conservative)
        self.names = self.eq.names
        #: The particles: this rank's share of the set (one process: all of it), keyed by their indices in
        #: ``particles`` (a share given: their places in key order), with the fields, domain, comm and boxes.
        D_given, F_given = np.array(particles.D, dtype=np.float64), self.eq.initial(x_given)
        if particles.parallel:
            self.particles = Particles.from_shares(x_given, D_given, F_given, self.names, particles.keys,
                                                   domain=self.domain, rstar=self.rstar, comm=particles.comm)
        else:
            self.particles = Particles.dealt(x_given, D_given, F_given, self.names, domain=self.domain,
                                             rstar=self.rstar, comm=comm)
        self._balance = CostBalance(self.particles.comm)    # (the steps' work: boxes cut anew when uneven)
        watched = self.names if monitor_fields is None else tuple(monitor_fields)
        unknown = sorted(set(watched) - set(self.names))
        if unknown or not watched:
            raise ValueError(f"monitor_fields must name some of the fields {list(self.names)}, got {monitor_fields!r}")
        self._watched = [self.names.index(w) for w in watched]
        self.D0, self.Dmin, self.potential, self.order, self.reach = D0, Dmin, potential, int(order), float(reach)
        self.integrator, self.fixed_dt, self.cfl, self.max_dt = integrator, dt, float(cfl), max_dt
        self.reorganize_every, self.max_iter = int(reorganize_every), int(max_iter)
        self.max_particles = int(max_particles)
        self.bounded, self.monitor, self.reading = bool(bounded), monitor, reading
        self.cache_order, self.stencil_rule = bool(cache_order), stencil_rule
        if stencil_rule != "repair" and self.eq.walls:
            raise ValueError("stencil_rule='displace' does not take Dirichlet walls (their one-sided rows are a "
                             "repair): use stencil_rule='repair'")
        if verlet_skin > 0 and self.eq.walls:
            raise ValueError("verlet_skin > 0 does not take Dirichlet walls: use verlet_skin=0")
        self._skin_fraction = float(verlet_skin)
        self._lists, self._held = reused_lists(self.domain, self._skin_fraction, self._over_ghosts), Reused()
        self.rng = np.random.default_rng(seed)
        #: The run's identity (:func:`arpy.state.run_identity`), stored and checked with its states.
        p = self.particles
        self.identity = run_identity({"fields": self.names, **options}, p.x, p.D, p.F, self.rng, comm=p.comm, keys=p.keys)
        self.t, self.steps = 0.0, 0
        self._max_row_sum: float | None = None  # (_nu: the largest diffusivity known, nu or an rhs's diffusion terms')
        self._degenerate, self._heavy, self._rho, self._nu = 0, 0, 0.0, self.eq.nu
        self.allow_unstable_dt, self._warned = bool(allow_unstable_dt), False
        self._phase = dict.fromkeys(PHASES, 0.0)
        self.log: list[dict] = []
        if self.eq.walls:
            self.x, self.F = settle(self, self.x, self.F, 0.0, self.eq.given)
        self._known_bound = np.inf            # (the last stability bound of a step: see _checked_step)
        if dt is not None and self.eq.moves:
            self._known_bound = self._initial_bound()
            if dt > self._known_bound and not self.allow_unstable_dt:
                raise StabilityError.refusing(unstable(f"dt = {dt:.3g} at the initial particles", self.integrator,
                                                       self._known_bound), self._known_bound)

    def __repr__(self) -> str:
        flow = "flow map" if self.eq.flow is not None else ("velocity" if self.eq.velocity is not None else "no motion")
        fields = "" if self.eq.single else f"fields={list(self.names)}, "
        return (f"Simulation(n={self.n}, {fields}t={self.t:.6g}, steps={self.steps}, nu={self.eq.nu:g}, {flow}, "
                f"{self.integrator}, D0={self.D0:g}, monitor={self.monitor!r}, {self.domain!r})")

    # ------------------------------------------------------------------ the particles' state
    x = of_particles("x", "This rank's positions, (n, d).")
    D = of_particles("D", "Their resolution D_p, (n,).")
    keys = of_particles("keys", "Their global keys (at the start: their indices in the ``particles`` given), int64 (n,).")
    F = of_particles("F", "Their fields, one column per name, (n, k).")

    # ------------------------------------------------------------------ helpers
    @property
    def n(self) -> int:
        return self.particles.n

    @property
    def eps(self) -> np.ndarray:
        """Core sizes = cutoff radii r* D_p, shape (n,)."""
        return self.rstar * self.D

    @property
    def f(self) -> np.ndarray:
        """The field at the particles, (n,) (a simulation of one field; a system: :attr:`fields`)."""
        if not self.eq.single:
            raise AttributeError(f"this simulation has the fields {list(self.names)}: use .fields[name]")
        return self.F[:, 0]

    @property
    def fields(self) -> dict[str, np.ndarray]:
        """The fields at the particles by name, arrays (n,) (views of :attr:`F`, (n, k))."""
        return self.eq.named(self.F)

    def _rhs(self, x: np.ndarray, F: np.ndarray, t: float, u: np.ndarray | None = None) -> np.ndarray:
        """The rates (n, k) at the particles x with the fields F at time t (DC-PSE with core sizes
        r* D); u: the velocity at x (for the conservative term)."""
        if not self.eq.moves:
            return np.zeros_like(F)
        t0 = time.perf_counter()

        skin, comm = self._skin(x), self.particles.comm
        # (particles that did not move since the last stage, on every rank: its operator sets again; with a
        # flow or a velocity they move at every stage, and the sets are not kept beyond this one)
        held = self._held.at((x, self.eps, self.keys), (skin, self._max_row_sum), lambda same: not comm.sum(int(not same))) \
            if self.eq.flow is None and self.eq.velocity is None else Reused()

        def build(wanted, bc):
            if self._over_ghosts:
                kept = self._lists if isinstance(self._lists, KeptGhosts) else None
                return DistributedDCPSE(comm, self.particles.decomposition, x, self.eps, self.keys,
                                        domain=self.domain, order=self.order, skin=skin, strict=False,
                                        operators=wanted, reorder=False, lists=kept, max_row_sum=self._max_row_sum,
                                        dirichlet=bc, **self._repair)
            lists = self._lists if isinstance(self._lists, ReusedLists) else None
            return DomainDCPSE(x, self.eps, domain=self.domain, order=self.order, strict=False,
                               operators=wanted, lists=lists, dirichlet=bc, max_row_sum=self._max_row_sum,
                               **self._repair)

        def op_of(wanted, bc):
            return held.get((repr(wanted), id(bc)), lambda: build(wanted, bc))

        if self.eq.conservative and u is None:
            u = self.eq.u(x, t, F)
        F = self.eq.pin(F, x, t)
        ops = self.eq.operators(op_of, t, x, F, x, F)
        out = self.eq.pin(self.eq.rates(ops, F, u), x, t, rates=True)
        self._rho, self._nu = max(self._rho, self.eq.spectral_radius(ops)), max(self._nu, ops.diffusivity)
        for op in ops.built:
            self._degenerate = max(self._degenerate, self.particles.total(op.failed.size))
            self._heavy += op.heavy.size
        self._phase["t_rhs"] += time.perf_counter() - t0
        return out

    @property
    def _over_ghosts(self) -> bool:
        """Whether the operators at the particles are built over this rank's particles and ghosts
        (:class:`arpy.distributed.DistributedDCPSE`, at every rank count): in a box.  The stages of a step
        then stay beside the box (unwrapped), as on every rank.  Else (free space: one process only)
        :class:`arpy.DomainDCPSE` over the particles, the stages wrapped into the box."""
        return self.domain.bounded

    def _skin(self, x: np.ndarray) -> float:
        """How far the positions x of a stage lie from the particles at the start of the step, at most
        (over the ranks): the reach the ghost layer needs beyond the boxes."""
        if x is self.x:
            return 0.0
        return self.particles.gmax(np.sqrt(((x - self.x) ** 2).sum(axis=1)).max(initial=0.0))

    def _near(self, x: np.ndarray, start: np.ndarray) -> np.ndarray:
        """Positions x (wrapped) as the periodic images nearest the positions ``start``."""
        return x - self.domain.whole_periods(x - start)

    @property
    def decomposition(self) -> "Decomposition":
        """The ranks' boxes (:class:`arpy.distributed.Decomposition`; one process: one box)."""
        return self.particles.decomposition

    def gather(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The whole particle set on every rank, in key order: (keys, x (n, d), D (n,), F (n, k)).
        Collective."""
        return self.particles.gather()

    def time_step(self) -> float:
        """The step size for the current particles (see the class docstring)."""
        if self.fixed_dt is not None:
            return self.fixed_dt
        h = self.particles.h_min()
        dt = np.inf
        if self.eq.nu > 0:
            dt = h * h / (4.0 * self.eq.nu)
        if self.eq.velocity is not None and self.eq.flow is None:
            umax = self.particles.gmax(np.sqrt((self.eq.u(self.x, self.t, self.F) ** 2).sum(axis=1)).max(initial=0.0))
            if umax > 0:
                dt = min(dt, self.cfl * h / umax)
        dt = dt if self.max_dt is None else min(dt, self.max_dt)
        if not np.isfinite(dt):
            raise ValueError("cannot choose a time step (no diffusion and no motion): give dt")
        if not dt > 0:
            raise ValueError(f"cannot choose a time step: the smallest particle spacing is {h:g} (coincident particles)")
        return float(dt)

    # ------------------------------------------------------------------ steps
    def reorganize(self) -> dict:
        """Step 4 of §3.2.2: adapt the particles to the fields and interpolate them (old -> new);
        returns the right-hand side at the new particles from the old values (variant (ii)) and the
        adaptation's figures (see :func:`arpy.reorganization.reorganize`)."""
        self._held.clear()
        return reorganize(self)

    def _advect(self, x: np.ndarray, t: float, dt: float, F: np.ndarray) -> np.ndarray:
        if self.eq.flow is not None:
            return self.eq.moved(x, t, dt)
        if self.eq.velocity is None:
            return x
        return x + dt * self.eq.u(x, t, F)

    def step(self, dt: float | None = None) -> dict:
        """Advance by one step (dt: default :meth:`time_step`); returns the step's log entry.

        The step is checked against the stability bound of its right-hand side's operators (see the
        class docstring): a default step above it is taken again at the bound; a given ``dt`` above it
        raises :class:`arpy.StabilityError` (``allow_unstable_dt``: a warning), changing nothing."""
        return self._checked_step(self.time_step() if dt is None else float(dt), given=dt is not None)

    def _checked_step(self, dt: float, given: bool) -> dict:
        """:meth:`_step`, undone and taken again at the stability bound (0.9^k of it at the k-th retake)
        while the bound of its own operators lies below dt (a given dt: refused); fields and positions
        checked finite."""
        given = given or self.fixed_dt is not None
        for attempt in range(8):
            saved, rng = dict(vars(self.particles)), self.rng.bit_generator.state
            entry = self._step(dt)
            bound = entry["dt_stable"]
            if np.isfinite(bound):
                self._known_bound = bound
            elif given:                 # (an Euler re-organization: the last bound known stands for it)
                bound = self._known_bound
            where = f"step {entry['step']} (t = {entry['t']:.6g} -> {entry['t'] + dt:.6g}, dt = {dt:.3g})"
            check_finite(self.x, "the positions are", where, self.x, self.keys)
            check_finite(self.F, "the field(s)", where, self.x, self.keys, self.names)
            if dt <= bound:
                break
            why = unstable(where, self.integrator, bound)
            if given and self.allow_unstable_dt:
                if not self._warned:
                    warnings.warn(f"{why}; taken anyway (allow_unstable_dt=True)", RuntimeWarning, stacklevel=3)
                    self._warned = True
                break
            self.particles.__dict__.update(saved)               # undo the step
            self.rng.bit_generator.state = rng
            self.t, self.steps = entry["t"], entry["step"] - 1
            self.log.pop()
            self._lists = reused_lists(self.domain, self._skin_fraction, self._over_ghosts)
            if given:
                raise StabilityError.refusing(why, bound)
            if attempt == 7:
                raise RuntimeError(f"{why}: the bound kept falling below the step taken again at it")
            dt = bound * (1 - 1e-9) * 0.9 ** attempt     # (at the bound; below it if the bound fell again)
        return entry

    def _initial_bound(self) -> float:
        """The stability bound of the right-hand side's operators at the initial particles (one
        assembly; an ``rhs`` new to the simulation is called twice, first to learn its operators; the
        reused lists, if any, are not touched).  Collective."""
        lists, self._lists = self._lists, None
        try:
            # (an rhs's first call tells which operators it uses; the second assembles and weighs them)
            for _ in range(2 if self.eq.rhs is not None and not self.eq.wanted else 1):
                self._rho, self._max_row_sum = 0.0, self._row_limit(self.fixed_dt)
                self._rhs(self.x, self.F, self.t)
        finally:
            self._lists = lists
        rho = self.particles.gmax(self._rho)
        return STABILITY[self.integrator] / rho if rho > 0 else np.inf

    def _row_limit(self, dt: float | None) -> float | None:
        """The Gershgorin radius ``STABILITY / (nu dt)`` above which a Laplacian row at the particles is
        rebuilt as wild (it alone would make a step dt unstable; nu: the largest diffusivity known); None
        without diffusion or repair."""
        return STABILITY[self.integrator] / (self._nu * dt) if dt and self._nu > 0 and self._repair["widen"] else None

    def _step(self, dt: float) -> dict:
        """One step of size dt (:meth:`step` without its checks)."""
        t0 = time.perf_counter()
        self._rho, self._max_row_sum = 0.0, self._row_limit(dt)
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a finite number > 0, got {dt}")
        if self.t + dt == self.t:
            raise ValueError(f"dt = {dt:g} is below the resolution of the time t = {self.t:g}: the step would not advance")
        reorg = self.reorganize_every > 0 and self.steps % self.reorganize_every == 0
        entry = dict(step=self.steps + 1, t=self.t, dt=dt, reorganized=reorg, so_iterations=0)
        if self.stencil_rule == "displace":
            entry.update(displaced=0, inserted=0)
        self._degenerate, self._heavy = 0, 0
        self._phase = dict.fromkeys(PHASES, 0.0)
        t_reorg = 0.0
        if self.integrator == "euler":
            # 2. advection; 4. re-organization at the advected positions; 5. right-hand side
            self.x = self.domain.wrap(self._advect(self.x, self.t, dt, self.F))
            self.particles.migrate(self._balance)
            t1 = time.perf_counter()
            if reorg:
                info = self.reorganize()
                rhs = info["rhs"]
                entry.update(self._reorganized(info))
                t_reorg = time.perf_counter() - t1
            else:
                rhs = self._rhs(self.x, self.F, self.t)
            self.F = self.F + dt * rhs
        else:
            t1 = time.perf_counter()
            if reorg:
                info = self.reorganize()
                entry.update(self._reorganized(info))
            t_reorg = time.perf_counter() - t1
            self.x, self.F = self._rk4(self.x, self.F, self.t, dt)
            self.particles.migrate(self._balance)
        self.t += dt
        self.steps += 1
        if self.eq.walls:
            self.x, self.F = settle(self, self.x, self.F, self.t)
        comm = self.particles.comm                      # (the global figures: two reductions)
        n, heavy = (int(v) for v in comm.add(np.array([self.n, self._heavy])))
        low, d_max, degenerate, rho = (float(v) for v in comm.max(np.array(
            [-float(self.D.min(initial=np.inf)), float(self.D.max(initial=0.0)), float(self._degenerate), self._rho])))
        entry.update(n=n, D_min=-low, D_max=d_max, degenerate=int(degenerate), heavy=heavy,
                     dt_stable=STABILITY[self.integrator] / rho if rho > 0 else np.inf,
                     t_reorganize=t_reorg, **self._phase, t_step=time.perf_counter() - t0)
        self.log.append(entry)
        return entry

    @staticmethod
    def _reorganized(info: dict) -> dict:
        """The log entries of a re-organization (what :meth:`reorganize` returned)."""
        return dict(so_iterations=info["iterations"], so_converged=info["converged"],
                    **{k: info[k] for k in ("displaced", "inserted") if k in info})

    def _rk4(self, x: np.ndarray, F: np.ndarray, t: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
        if self.eq.flow is not None:
            # exact positions at the stage times; f by RK4 with the operator at those positions
            xh, x1 = self.domain.wrap(self.eq.moved(x, t, dt / 2)), self.domain.wrap(self.eq.moved(x, t, dt))
            # (over ghosts: the stage positions beside the ranks' boxes)
            sh, s1 = (self._near(xh, x), self._near(x1, x)) if self._over_ghosts else (xh, x1)
            k1 = self._rhs(x, F, t)
            k2 = self._rhs(sh, F + dt / 2 * k1, t + dt / 2)
            k3 = self._rhs(sh, F + dt / 2 * k2, t + dt / 2)
            k4 = self._rhs(s1, F + dt * k3, t + dt)
            return x1, F + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

        def rates(xs, Fs, ts):
            u = self.eq.u(xs, ts, Fs)
            # (over ghosts the stage positions stay unwrapped, beside the ranks' boxes)
            return u, self._rhs(xs if self._over_ghosts else self.domain.wrap(xs), Fs, ts, u)

        x_new, F_new = rk4_step(rates, x, F, t, dt)
        return self.domain.wrap(x_new), F_new

    def run(self, T: float, *, progress: bool = False, callback: Callable[["Simulation"], None] | None = None
            ) -> "Simulation":
        """Step until t = T (the last step is shortened to land on T); returns self."""
        if not (np.isfinite(T) and T >= self.t):
            raise ValueError(f"T must be >= the current time {self.t}")
        bar = None
        if progress:
            from tqdm.auto import tqdm
            bar = tqdm(total=float(T - self.t), desc="simulate", unit="t",
                       disable=None if self.particles.comm.rank == 0 else True,
                       bar_format="{l_bar}{bar}| {n:.3g}/{total:.3g} [{elapsed}<{remaining}]")
        while self.t < T * (1 - 1e-12):
            dt = min(self.time_step(), T - self.t)
            entry = self._checked_step(dt, given=False)
            if callback is not None:
                callback(self)
            if bar is not None:
                bar.update(entry["dt"])
                bar.set_postfix(n=entry["n"], dt=f"{entry['dt']:.2g}")
        if bar is not None:
            bar.close()
        return self

    def save_state(self, path: str | Path, records: Records | None = None, *, shares: Shares | None = None,
                   run: Run | None = None) -> Path:
        """Write the state, the run's :attr:`identity`, the caller's ``records`` (rank 0's), ``shares`` (sets
        of rows of each rank, with their keys: in its piece, none gathered) and ``run`` (:mod:`arpy.state`);
        returns the file written.  A Simulation of the same arguments continues it exactly.  Collective."""
        return write_state(path, self.particles, t=self.t, steps=self.steps, rng=self.rng, log=self.log,
                           identity=self.identity, single=self.eq.single, records=records, shares=shares, run=run)

    def load_state(self, path: str | Path | State, *, run: Run | None = None, allow: Collection[str] = ()) -> "Simulation":
        """Continue from a file of :meth:`save_state` (or its contents read by :func:`arpy.state.read_state`),
        on any number of ranks (no rank reads the whole set unless P = 1: :meth:`arpy.state.State.particles`);
        returns self.  A state of another run, or not a state, is refused (:meth:`arpy.state.State.check`).
        Collective."""
        state = (path if isinstance(path, State) else read_state(path)).check(self.identity, run=run, allow=allow)
        self.particles = state.particles(self.particles.comm, self.domain)
        self.t, self.steps, self.log = state.t, state.steps, list(state.log)
        self.rng.bit_generator.state = state.rng
        self._lists = reused_lists(self.domain, self._skin_fraction, self._over_ghosts)
        self._held.clear()
        return self

    def history(self) -> dict[str, np.ndarray]:
        """The per-step log as arrays (one value per step), one per key present in every entry, at least
        :data:`STEP_KEYS` (empty before the first step): ``step``, ``t``, ``dt``, ``dt_stable``, ``n``
        (particles), ``D_min``, ``D_max``, ``degenerate`` (failed stencils), ``reorganized``,
        ``so_iterations`` and the phases' wall times (``t_step``, ``t_rhs``, ``t_reorganize``, ..., s)."""
        return log_arrays(self.log, STEP_KEYS)

