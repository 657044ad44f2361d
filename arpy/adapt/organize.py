"""The self-organizing adaptation loop (Reboux et al. 2012, §2.3.4, §3.1 and §3.2.2 step 4(e)).

Particles p carry a resolution D_p, a cutoff r_c,p = r* D_p and a core size
eps_p = r_c,p.  :func:`self_organize` iterates

  i.   fuse pairs closer than D_pq / 2 (one particle at their midpoint), a matching in the
       order of r_pq / D_pq: each particle fuses at most once per iteration;
  ii.  insert one particle at a random position near every particle with fewer
       than N* neighbours (distance U(0.5, 1) D_p in a random direction; the draws are
       a hash of (seed, iteration, the parent's key, the candidate));
  iii. rebuild the neighbour lists (``|x_p - x_q| <= min(r_c,p, r_c,q)``);
  iv.  D_p at the new positions: from the target field D~ and Eq. 2.9, or
       interpolated from an old particle set (:class:`SampledResolution`);
  v.   r_c,p = eps_p = r* D_p;
  vi.  energy W and gradient (Fortran core, :func:`arpy.adapt.forces.energy`),
       with V shifted by V(r*) so that W is continuous as pairs enter or
       leave the lists (the forces are the paper's);
  vii. a backtracking (Armijo) line search along -grad W, each trial energy
       evaluated with the neighbour lists of the trial positions, so that an
       accepted step never raises W;
  viii. stop when every particle has >= N* neighbours and
        max_p max_q D_pq / r_pq <= d_c; else back to i.

Every sum reads the lists in key order (the particles keep their keys' order) and W is an exact
sum, so the result does not depend on the list method or the thread count.

Boundaries come from an :class:`arpy.Domain`: periodic axes (minimum image,
ghosts for the lists), walls (positions are projected back; mirror images
count as neighbours), or free space, optionally limited to a region
(:class:`Confinement`: particles leaving it are removed, and the neighbour
requirement is waived within r_c + D_p / 2 of its edge).
"""

from __future__ import annotations

import warnings
from typing import Any, Callable

import numpy as np

from .._validate import as_positions, check_count, non_finite_rows
from ..domain import Domain, as_domain
from .forces import POTENTIALS
from ..particles import Particles
from ..distributed.comm import Comm, SerialComm
from ..distributed.inputs import agree
from ..distributed.decomposition import Decomposition, bisect
from ..distributed.ghosts import dealt_share, migrate, owned, scatter
from ..distributed.reductions import gather, key_places
from .adaptation import Adaptation, Target
from .view import EDGE_LAYER, Confinement, View
from .resolution import SampledResolution, check_reach, check_reading, n_star_for, r_star
from ..dcpse.displace import Displaced, check_stencil_rule, displace_on_ranks, displace_until_valid

__all__ = ["DEFAULT_SEED", "EDGE_LAYER", "MAX_ITER", "MAX_PARTICLES", "NotConvergedWarning", "displace_set", "not_converged",
           "self_organize", "start_share", "valid_stencils"]


class NotConvergedWarning(UserWarning):
    """:func:`self_organize` (also in an :class:`arpy.Simulation`'s re-organizations) ran out of
    iterations before its stopping rule held: the particles may not resolve the target resolution
    everywhere (e.g. a region still being filled by insertion, left with a hole)."""

#: The default particle number at which :func:`self_organize` stops with an error.
MAX_PARTICLES = 5_000_000
#: The default most iterations of :func:`self_organize`: a bound on a run that never settles, not the
#: length of one that does.  Insertion fills an empty region from its edge, a few particle spacings an
#: iteration, so from a sparse start the iterations needed grow with the width of the finest region in
#: its own spacings: the pulse at D0 = 0.0045 (5.4e5 particles) settles after 172.  A run that stops
#: here warns (:class:`NotConvergedWarning`).
MAX_ITER = 1000
#: How many of the last iterations :func:`not_converged` reads to tell a run still filling from one
#: that cycles.
RECENT = 10
#: The seed of every random draw of the adaptive method when none is given: :func:`self_organize`,
#: :class:`arpy.Simulation` and every case (``arpy run CASE --seed``) default to it, so a run is the same
#: each time and a hand-built one matches the case with the same parameters; ``seed=None`` asks for a
#: fresh random seed instead (self_organize and Simulation).
DEFAULT_SEED = 1

def self_organize(
    x: np.ndarray | Particles,
    resolution: Callable[[np.ndarray], np.ndarray] | None = None,
    *,
    grad_f: Callable[[np.ndarray], np.ndarray] | None = None,
    D0: float | None = None,
    Dmin: float | None = None,
    potential: str = "V2",
    domain: Domain | None = None,
    region: Callable[[np.ndarray], np.ndarray] | None = None,
    d_c: float = 2.5,
    order: int = 4,
    n_star: int | None = None,
    reach: float = 1.0,
    reading: str = "implicit",
    adapt_number: bool = True,
    max_iter: int = MAX_ITER,
    tol: float = 1e-4,
    seed: int | np.random.Generator | None = DEFAULT_SEED,
    progress: bool = False,
    max_particles: int = MAX_PARTICLES,
    comm: Comm | None = None,
    keys: np.ndarray | None = None,
    decomposition: Decomposition | None = None,
) -> Particles:
    """Adapt particles to a target resolution by fusion, insertion and gradient descent.

    Parameters
    ----------
    x : array (n, d) or Particles
        Initial positions (d = 2 or 3), or a :class:`Particles`.
    resolution : callable, optional
        (m, d) points -> (m,) target resolution D~ (length unit of x), e.g. a function or a
        :class:`~arpy.adapt.resolution.SampledResolution`.  Exactly one of ``resolution`` and
        ``grad_f`` must be given.
    grad_f : callable, optional
        (m, d) points -> (m, d) gradient of the field f; then
        ``D~ = D0 / sqrt(1 + |grad f|^2)`` (the monitor function, Eq. 2.8).
    D0 : float, optional
        Coarsest resolution: required with ``grad_f``; with ``resolution`` an optional upper
        bound on D~.
    Dmin : float, optional
        Lower bound on D~ (bounds the particle number, §2.3.4).
    potential : {"V2", "V1"}
        "V2" (repulsive; finite and periodic boxes) or "V1" (Morse; free space).
    domain : Domain, optional
        Where the particles live (default: free space): periodic axes wrap, walls confine the
        particles (positions are projected back).
    region : callable, optional
        (m, d) -> (m,) bool: particles must stay where it is True (e.g. a narrow band in free
        space).  Needed for free space with ``adapt_number`` (else the edge of the cloud keeps
        growing).  Particles within r_c + :data:`EDGE_LAYER` D_p of its edge need not have N*
        neighbours.
    d_c : float
        The stopping threshold on max D_pq / r_pq (default 2.5, §3.1).
    order : int
        DC-PSE order m; sets N* (:func:`arpy.adapt.resolution.n_star_for`) and r*
        (:func:`arpy.adapt.resolution.r_star`).
    n_star : int, optional
        Override N*.
    reach : float
        Factor on the radius of the ball of Eq. 2.9 (kappa in
        ``D_p = min over |x_q - x_p| <= kappa r* D_p of D~_q``).  1 is the
        paper's; larger values grade D_p more slowly (slope 1 / (kappa r*))
        away from fine features, so that coarse stencils keep their distance
        from them (see :func:`arpy.adapt.resolution.graded_resolution`).
    reading : {"implicit", "explicit", "pointwise"}
        The reading of Eq. 2.9: the ball's radius r* D_p (implicit, arpy's) or r* D~_p (explicit), or
        no ball, D_p = D~(x_p) (pointwise; see :func:`arpy.adapt.resolution.graded_resolution`).
    adapt_number : bool
        True: fuse and insert (§2.3.4).  False: fixed particle number, plain descent, stopping
        when W falls by less than ``tol`` (relative) in an iteration (Fig. 2.3 of the paper).
    max_iter : int
        Most iterations (default :data:`MAX_ITER`); a run that stops here unconverged warns
        (:class:`NotConvergedWarning`, with where it stood against the stopping rule).
    tol : float
        Relative energy decrease that ends a fixed-number run.
    seed : int or numpy.random.Generator, optional
        Seed (an int >= 0, or a Generator to draw one from) of the random insertion positions.
        The draws come from a counter-based generator keyed on (seed, iteration, parent particle,
        candidate): the same seed gives the same result, whatever the list method, thread or
        process count.  Default: :data:`DEFAULT_SEED` (1), as in :class:`arpy.Simulation` and the cases;
        None: a fresh random seed.
    progress : bool
        Show a tqdm progress bar.
    max_particles : int
        The particle number at which to stop with an error (a resolution field asking for far
        more particles than intended, e.g. from a noisy gradient, would otherwise exhaust the
        memory; bound D~ with Dmin).
    comm : Comm, optional
        The ranks that share the work (:mod:`arpy.distributed`; default: this process alone, P = 1).
        Every rank calls with the same arguments but ``x`` and ``keys``; ``seed`` must be an int.
        The result is bitwise the same for every rank count.
    keys : int array (n,), optional
        Given: ``x`` is this rank's share of a set whose particles carry these global keys
        (distinct over the ranks), and the result is this rank's share of the adapted set (with its
        ``keys`` and ``decomposition``).  None: ``x`` is the whole set (the same on every rank),
        dealt to the ranks, adapted there and gathered: every rank gets the whole result
        (:func:`start_share` gives a rank's share of such a set, and the result stays in shares).
    decomposition : Decomposition, optional
        With ``keys``: the ranks' boxes owning the particles given (default: bisected anew).

    Returns
    -------
    Particles
        Positions, D_p, r_c, eps and the iteration log.  When converged, D_p is the resolution
        at the final positions and the stopping rule holds with it; otherwise D_p is the last
        value used.

    Examples
    --------
    Particles in the square [-1, 1]^2 with walls, refined around a Gaussian pulse by the
    monitor function of Eq. 2.8 (the gradient of f given):

    >>> import numpy as np
    >>> import arpy
    >>> def grad_f(p):
    ...     r = p - np.array([0.58, 0.02])
    ...     return -500.0 * r * np.exp(-250.0 * (r ** 2).sum(1))[:, None]
    >>> walls = arpy.Domain(([-1.0, -1.0], [1.0, 1.0]))
    >>> start = np.random.default_rng(1).uniform(-1, 1, (400, 2))
    >>> ps = arpy.self_organize(start, grad_f=grad_f, D0=0.25, domain=walls, seed=1)
    >>> ps.converged
    True
    >>> bool(ps.D.max() <= 0.25 and ps.D.min() < 0.05)
    True
    """
    comm = comm or SerialComm()
    xs = as_positions(x.x if isinstance(x, Particles) else x).copy()
    d = xs.shape[1]
    dom = as_domain(domain, d)
    if comm.size > 1:
        seed = int_seed(seed, "an int >= 0, the same on every rank")
    kw: dict[str, Any] = dict(resolution=resolution, grad_f=grad_f, D0=D0, Dmin=Dmin, potential=potential, domain=dom, region=region,
              d_c=d_c, order=order, n_star=n_star, reach=reach, reading=reading, adapt_number=adapt_number,
              max_iter=max_iter, tol=tol, seed=seed, progress=progress and comm.rank == 0,
              max_particles=max_particles)
    agree(comm, "self_organize(comm=)", **{k: v for k, v in kw.items() if k != "progress"}, d=d, whole_set=keys is None)
    if keys is None:
        if decomposition is not None:
            raise ValueError("decomposition= is for a rank's share of the particles: give their keys= too")
        if comm.size == 1:
            finite = np.all(np.isfinite(xs), axis=1)
            out = adapt(xs, np.arange(xs.shape[0], dtype=np.int64), comm, bisect(xs[finite], 1, domain=dom)[0], **kw)
            return Particles(out.x, out.D, out.rstar, out.n_star, out.domain, out.log, out.converged)
        dec, xs, ks, _ = scatter(comm, xs, domain=dom)
        out = adapt(xs, ks, comm, dec, **kw)
        assert out.keys is not None
        _, xa, Da = gather(comm, out.keys, out.x, out.D)
        return Particles(xa, Da, out.rstar, out.n_star, out.domain, out.log, out.converged)
    ks = np.asarray(keys)
    if ks.shape != (xs.shape[0],) or not np.issubdtype(ks.dtype, np.integer):
        raise ValueError(f"keys must be one integer per particle, shape ({xs.shape[0]},)")
    order = np.argsort(ks, kind="stable")
    xs, ks = xs[order], ks[order].astype(np.int64)
    xs, ks, _, decomposition = owned(comm, dom, xs, ks, decomposition)
    return adapt(xs, ks, comm, decomposition, **kw)


def start_share(x: np.ndarray, comm: Comm | None = None) -> dict[str, Any]:
    """:func:`self_organize`'s ``x`` and ``keys`` for a start ``x`` (n, d) that every rank of ``comm``
    holds whole (e.g. random positions drawn from the run's seed): this rank's share, every P-th point
    from the rank's number keyed by its index (as :func:`~arpy.distributed.scatter` deals a whole set;
    one process, ``comm`` None or of one rank: every point), so that the adapted set is this rank's
    share, no rank holds the whole result (the start itself stays a transient array of every rank), and
    its keys are the same at every rank count.  ``self_organize(**start_share(x, comm), ..., comm=comm)``."""
    if comm is None or comm.size == 1:
        return {"x": x, "keys": np.arange(np.shape(x)[0], dtype=np.int64)}
    mine = dealt_share(comm, np.shape(x)[0])
    return {"x": np.asarray(x)[mine], "keys": mine}


def adapt(xs: np.ndarray, keys: np.ndarray, comm: Comm, dec: Decomposition, *, resolution, grad_f, D0, Dmin,
          potential: str, domain: Domain, region, d_c: float, order: int, n_star: int | None, reach: float,
          reading: str, adapt_number: bool, max_iter: int, tol: float, seed, progress: bool,
          max_particles: int) -> Particles:
    """The work of :func:`self_organize` on this rank's particles ``xs`` with their ``keys``
    (ascending), the ranks of ``comm`` and their boxes ``dec``: the checks, the set-up and the
    iteration.  Returns this rank's particles of the adapted set in key order, with their keys and
    the boxes owning them at the end."""
    _check_arguments(resolution, grad_f, D0, Dmin, potential, d_c, max_iter, max_particles, n_star, tol, reach)
    check_reading(reading)
    n_own, d = xs.shape
    bad = non_finite_rows(xs)
    ns = n_star_for(order, d) if n_star is None else int(n_star)
    rs = r_star(d, ns)
    conf = Confinement(domain, region, rs)
    ctx = View(conf, comm, dec)
    if ctx.total(n_own) == 0:
        raise ValueError("self_organize needs at least one particle")
    if bad.size:
        raise ValueError(f"self_organize: position of particle {keys[bad[0]]} is not finite (NaN or Inf)")
    if not domain.bounded and region is None and adapt_number:
        raise ValueError("free space with adapt_number=True needs a region (else particles keep being "
                         "inserted at the edge of the cloud); give domain=..., region=... or adapt_number=False")
    if not np.all(conf.inside(domain.confine(xs))):
        raise ValueError("initial particles lie outside the region")
    xs = domain.confine(xs)
    if isinstance(resolution, SampledResolution) and not np.array_equal(resolution.domain.period, domain.period):
        raise ValueError("the SampledResolution and self_organize must agree on the periodic axes")
    scale = max(ctx.gmax(float(np.max(np.abs(xs), initial=0.0))),
                float(np.max(np.abs(np.stack([domain.lo, domain.hi]))))
                if domain.lo is not None and domain.hi is not None else 0.0)      # (a box: bounded)
    target = Target(resolution, grad_f, D0, Dmin, reach * rs, domain, scale, reading)
    loop = Adaptation(conf, target, potential, ns, d_c, seed64(seed), max_particles, ctx)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=int(max_iter), desc="self-organize", unit="it", disable=None)
    try:
        x_out, D, k_out, log, converged = loop.run(xs, keys, int(max_iter), adapt_number, tol, bar)
    finally:
        if bar is not None:
            bar.close()
    if not converged and comm.rank == 0:
        warnings.warn(not_converged(log, int(max_iter), adapt_number, d_c, ns), NotConvergedWarning, stacklevel=3)
    return Particles(x_out, D, rs, ns, domain, log, converged, keys=k_out, decomposition=ctx.dec, comm=comm)


def not_converged(log: list[dict], max_iter: int, adapt_number: bool, d_c: float, n_star: int) -> str:
    """What :class:`NotConvergedWarning` says of an adaptation that stopped unconverged after the
    iterations of ``log`` (of at most ``max_iter``): where it stood in its last iteration against the
    stopping rule (``d_c``, ``n_star``), whether its last :data:`RECENT` iterations still added
    particles (a region being filled: more iterations help) or inserted and fused about as many (a
    cycle: they do not), and what to do."""
    last = log[-1] if log else {}
    ran = f"after {len(log)} iteration{'s' if len(log) != 1 else ''}" + (
        f" (max_iter = {max_iter})" if len(log) >= max_iter else " (it stalled: nothing changed any more)")
    if not adapt_number:
        return (f"self_organize: the energy still fell by more than tol {ran}; the particles are not at rest: "
                "give a larger max_iter")
    said = (f"self_organize: the stopping rule does not hold {ran}: N = {last.get('n')}, the last iteration "
            f"inserted {last.get('inserted')} and fused {last.get('fused')} particles; fewest neighbours "
            f"{last.get('min_neighbors')} (N* = {n_star}), largest D_pq / r_pq "
            f"{last.get('max_ratio', float('nan')):.3g} (d_c = {d_c:g}).  ")
    recent = log[-RECENT:]
    grew = int(recent[-1]["n"]) - int(recent[0]["n"]) + int(recent[0]["inserted"]) - int(recent[0]["fused"]) \
        if recent else 0
    churn = sum(int(e["inserted"]) + int(e["fused"]) for e in recent)
    if grew > churn // 4:
        return said + (f"It still added {grew} particles in its last {len(recent)} iterations (a region being "
                       "filled, with a hole until it is): give a larger max_iter")
    return said + (f"Its last {len(recent)} iterations inserted and fused about as many particles ({churn} in all, "
                   f"N changed by {grew}): it cycles, and more iterations will not settle it; the target may ask "
                   "for what N* neighbours cannot give somewhere (reading='pointwise' can): bound it (Dmin) or smooth it")


def seed64(seed: int | np.random.Generator | None) -> int:
    """The 64-bit seed of the insertion draws: an int >= 0 as it is (mod 2**64), one drawn from a
    Generator, or a fresh one."""
    if seed is None or isinstance(seed, np.random.Generator):
        gen = seed if seed is not None else np.random.default_rng()
        return int(gen.integers(0, 2 ** 63))
    return int_seed(seed, "an int >= 0, a numpy Generator or None")


def int_seed(seed: object, accepted: str = "an int >= 0") -> int:
    """An int seed >= 0 (mod 2**64), else ValueError naming what is ``accepted``."""
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be {accepted}, got {seed!r}")
    return int(seed) & 0xFFFFFFFFFFFFFFFF


def _check_arguments(resolution, grad_f, D0, Dmin, potential, d_c, max_iter, max_particles, n_star, tol,
                     reach) -> None:
    """The checks of :func:`self_organize`'s scalar arguments (before any work)."""
    if (resolution is None) == (grad_f is None):
        raise ValueError("give exactly one of resolution (a D~ callable) and grad_f (for the monitor function)")
    if grad_f is not None and D0 is None:
        raise ValueError("grad_f needs D0 (the coarsest resolution of the monitor function)")
    if resolution is not None and not callable(resolution):
        raise TypeError("resolution must be a callable mapping (m, d) points to (m,) values")
    if potential.upper() not in POTENTIALS:
        raise ValueError(f"potential must be one of {sorted(POTENTIALS)}, got {potential!r}")
    for name, val in (("D0", D0), ("Dmin", Dmin)):
        if val is not None and not (np.isfinite(val) and val > 0):
            raise ValueError(f"{name} must be a finite number > 0")
    if D0 is not None and Dmin is not None and Dmin > D0:
        raise ValueError("Dmin must not exceed D0")
    if not (np.isfinite(d_c) and d_c > 2.0):
        raise ValueError("d_c must be > 2 (fusion already removes pairs closer than D_pq / 2)")
    check_count("max_iter", max_iter)
    check_count("max_particles", max_particles)
    if n_star is not None:
        check_count("n_star", n_star)
    if not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be a finite number >= 0, got {tol!r}")
    check_reach(reach)


def displace_set(ps: Particles, *, order: int = 4, old: Particles | tuple[np.ndarray, np.ndarray] | None = None,
                 rng: np.random.Generator | int | None = None) -> tuple[Particles, Displaced]:
    """:func:`arpy.dcpse.displace.displace_until_valid` on a :class:`Particles` (its r* and domain): (a
    copy of the set with the particles displaced and inserted, :class:`arpy.dcpse.displace.Displaced`).
    ``old``: the set the values come from (a re-organization), whose interpolation rows to the particles
    must be valid too: a :class:`Particles`, or on one process (x_old (k, d), eps_old (k,)).
    A set spread over the ranks: each rank's share, displaced over the ranks
    (:func:`arpy.dcpse.displace.displace_on_ranks`, the particles numbered by their places in key order,
    the inserted ones after them; ``old`` a set on the same ranks, moved into these boxes), bitwise one
    process's; the result is each rank's share, in the same boxes.  Collective then."""
    if ps.names:
        raise ValueError("displace_set takes a set without fields")
    if not ps.parallel:
        olds = (old.x, old.eps) if isinstance(old, Particles) else old
        x, D, done = displace_until_valid(ps.x, ps.D, ps.rstar, domain=ps.domain, order=order, old=olds, rng=rng)
        return Particles(x, D, ps.rstar, ps.n_star, ps.domain, ps.log, ps.converged), done
    on_ranks = None
    if old is not None:
        if not isinstance(old, Particles) or old.comm is not ps.comm:
            raise ValueError("displace_set of a set spread over the ranks takes old= as a Particles on the same ranks")
        xo, ko, got = migrate(ps.comm, ps.decomposition, old.x, key_places(ps.comm, old.keys), {"eps": old.eps})
        on_ranks = (xo, got["eps"], ko)
    x, D, keys, done = displace_on_ranks(ps.comm, ps.decomposition, ps.x, ps.D, key_places(ps.comm, ps.keys),
                                         ps.rstar, domain=ps.domain, order=order, old=on_ranks, rng=rng)
    return Particles(x, D, ps.rstar, ps.n_star, ps.domain, ps.log, ps.converged, keys=keys,
                     decomposition=ps.decomposition, comm=ps.comm), done


def valid_stencils(ps: Particles, rule: str, rng: np.random.Generator | int | None = None) -> Particles:
    """An initial set for a simulation under a stencil rule: the set itself ("repair") or
    :func:`displace_set` of it ("displace")."""
    check_stencil_rule(rule)
    return ps if rule == "repair" else displace_set(ps, rng=rng)[0]
