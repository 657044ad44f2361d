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

import math
import time
from pathlib import Path
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Callable, cast

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes

from .. import _bridge
from .._validate import as_positions, check_count
from ..domain import Domain, nearest
from .forces import POTENTIALS, energy_terms
from ..io import load_results, save_results
from ..distributed.comm import Comm, SerialComm
from ..distributed.decomposition import Decomposition, bisect
from ..distributed.ghosts import scatter
from ..distributed.reductions import gather
from ..lists.neighborlist import NeighborList
from ..lists.search import neighbor_list
from .view import EDGE_LAYER, Confinement, Near, View
from .resolution import (SampledResolution, check_reach, check_reading, graded_resolution, monitor_gradient, n_star_for,
                         r_star)
from ..dcpse.displace import Displaced, check_stencil_rule, displace_until_valid

__all__ = ["EDGE_LAYER", "MAX_PARTICLES", "ParticleSet", "displace_set", "log_arrays", "self_organize",
           "valid_stencils"]

#: Displacement cap of one descent step, in units of the particle's D_p.
MAX_STEP = 0.25
#: Armijo sufficient-decrease constant and the most step halvings per line search.
ARMIJO_C, MAX_HALVINGS = 0.1, 40
#: Random candidate sites tried per insertion (the one farthest from other particles wins).
INSERT_CANDIDATES = 16
#: The default particle number at which :func:`self_organize` stops with an error.
MAX_PARTICLES = 5_000_000

#: Insertion counts neighbours within this fraction of the cutoff (the stopping rule
#: counts up to the cutoff): a margin that keeps neighbours from flickering out.
INSERT_MARGIN = 0.97
#: Nearest existing particles checked for the clearance of a candidate site.
INSERT_NEAREST = 8


def log_arrays(log: list[dict]) -> dict[str, np.ndarray]:
    """A list of per-iteration (or per-step) dicts as arrays, one per key present in every entry."""
    if not log:
        return {}
    return {k: np.array([e[k] for e in log]) for k in log[0] if all(k in e for e in log)}


@dataclass(eq=False)
class ParticleSet:
    """An adapted particle set, as :func:`self_organize` returns it.

    Attributes
    ----------
    x : array (n, d)
        Positions.
    D : array (n,)
        Resolution D_p (length unit of x).
    rstar : float
        Cutoff factor, r_c = eps = rstar * D.
    n_star : int
        The wanted number of neighbours N*.
    domain : Domain
        The :class:`arpy.Domain` the particles live in.
    log : list of dict
        One dict per iteration: ``iteration, n, fused, inserted, removed,
        energy_before, energy, gamma, trials, min_neighbors, max_ratio`` and
        timings ``t_fuse_insert, t_resolution, t_lists, t_forces, t_total``
        in seconds (``energy_before``/``energy``: W before and after the step,
        same particles, same D), ``moved`` (whether a step was accepted).
    converged : bool
        True if the stopping rule was met (else max_iter ran out or the descent stalled).
    keys : int64 array (n,) or None
        Of a rank's share of a set (``self_organize(..., keys=)``): the particles' global keys, in
        ascending order; None: the whole set, numbered by index.
    decomposition : Decomposition or None
        Of a rank's share: the ranks' boxes that own the particles at the end.

    Examples
    --------
    >>> import numpy as np
    >>> import arpy
    >>> def wavy(p):
    ...     return 0.06 * (1 + 0.5 * np.sin(2 * np.pi * p[:, 0]))
    >>> box = arpy.Domain([1.0, 1.0], periodic=True)
    >>> ps = arpy.self_organize(np.random.default_rng(2).random((200, 2)), wavy, domain=box, seed=2)
    >>> ps.d, ps.n_star, ps.converged
    (2, 10, True)
    >>> ps.x.shape == (ps.n, 2) and ps.D.shape == ps.rc.shape == (ps.n,)
    True
    >>> history = ps.history()
    >>> len(history["n"]) == len(ps.log)
    True

    ``ps.save(path)`` and ``arpy.ParticleSet.load(path)`` write and read it; ``ps.plot()`` draws
    it (with matplotlib).
    """

    x: np.ndarray
    D: np.ndarray
    rstar: float
    n_star: int
    domain: Domain = field(default_factory=Domain)
    log: list[dict] = field(default_factory=list)
    converged: bool = False
    keys: np.ndarray | None = None
    decomposition: Decomposition | None = None

    @property
    def n(self) -> int:
        """Number of particles."""
        return int(self.x.shape[0])

    @property
    def d(self) -> int:
        """Dimension."""
        return int(self.x.shape[1])

    @property
    def rc(self) -> np.ndarray:
        """Cutoff radii r_c,p = r* D_p, shape (n,)."""
        return self.rstar * self.D

    def save(self, path: str | Path) -> Path:
        """Write the set to a .npz (positions, D, r*, N*, the domain, the log; a .json sidecar too)."""
        meta = {"rstar": self.rstar, "n_star": self.n_star, "converged": self.converged,
                "domain": self.domain.state(), "log": self.log}
        return save_results(path, meta, x=self.x, D=self.D)

    @classmethod
    def load(cls, path: str | Path) -> "ParticleSet":
        """The set written by :meth:`save`."""
        meta, arrays = load_results(path)
        return cls(arrays["x"], arrays["D"], float(meta["rstar"]), int(meta["n_star"]),
                   Domain.from_state(meta["domain"]), list(meta["log"]), bool(meta["converged"]))

    def __repr__(self) -> str:
        D = f", D in [{self.D.min():.3g}, {self.D.max():.3g}]" if self.n else ""
        state = "converged" if self.converged else "not converged"
        return (f"ParticleSet(n={self.n}, d={self.d}{D}, r*={self.rstar:.3g}, N*={self.n_star}, "
                f"{self.domain!r}, {len(self.log)} iterations, {state})")

    @property
    def eps(self) -> np.ndarray:
        """Core sizes eps_p = r_c,p, shape (n,)."""
        return self.rc

    def neighbor_list(self, symmetric: bool = True) -> NeighborList:
        """Neighbour lists under the min rule (minimum image along periodic axes)."""
        return neighbor_list(self.x, self.rc, method="auto", symmetric=symmetric, domain=self.domain)

    def history(self) -> dict[str, np.ndarray]:
        """The iteration log as arrays, one per key."""
        return log_arrays(self.log)

    def plot(self, ax: Axes | None = None, **kwargs: Any) -> Axes:
        """Draw the particles (see :func:`arpy.plotting.plot_particles`)."""
        from ..plotting import plot_particles

        return plot_particles(self, ax=ax, **kwargs)


#: The mixing constants of SplitMix64 (Steele, Lea and Flood 2014), the hash of :func:`counter_uniforms`.
_MIX = (np.uint64(0x9E3779B97F4A7C15), np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB))


def _mix(z: np.ndarray) -> np.ndarray:
    """SplitMix64's finalizer of z + the golden-ratio increment (a bijection of uint64; wraps)."""
    z = z + _MIX[0]
    z = (z ^ (z >> np.uint64(30))) * _MIX[1]
    z = (z ^ (z >> np.uint64(27))) * _MIX[2]
    return z ^ (z >> np.uint64(31))


def counter_uniforms(seed: int, stream: int, keys: np.ndarray, count: int) -> np.ndarray:
    """Uniform numbers in [0, 1) from a counter-based generator: value (i, j) is a hash of
    (seed, stream, keys[i], j), so it does not depend on which other keys are drawn for, in which
    order, or on which process.  Returns an array (len(keys), count)."""
    with np.errstate(over="ignore"):
        base = _mix(_mix(np.full(1, seed & 0xFFFFFFFFFFFFFFFF, np.uint64)) ^ np.uint64(stream & 0xFFFFFFFFFFFFFFFF))
        per_key = _mix(base ^ np.asarray(keys, np.int64).astype(np.uint64))
        h = _mix(per_key[:, None] ^ np.arange(count, dtype=np.uint64)[None, :])
    return (h >> np.uint64(11)).astype(np.float64) * 2.0 ** -53


def _candidate_sites(x: np.ndarray, D: np.ndarray, parents: np.ndarray, dom: Confinement, draws: np.ndarray,
                     around: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """One site near each parent (``x[parents]``): of INSERT_CANDIDATES random points at distance
    U(0.5, 1) D_p in random directions (inside the domain), the one with the largest clearance
    min_q |x - x_q| / D_pq to the particles ``around(candidates)`` returns (positions, D; all of them
    on one process) among those that would count as the parent's neighbour (D of the new particle
    estimated from the grading of Eq. 2.9).  ``draws``: (parents, INSERT_CANDIDATES (2 d + 1))
    uniforms.  Returns (sites, the index into ``parents`` of each one's parent)."""
    k, d = INSERT_CANDIDATES, x.shape[1]
    u = draws.reshape(parents.size, k, 2 * d + 1)
    # d normal deviates per candidate (Box-Muller), a uniformly random direction once normalized
    g = np.sqrt(-2.0 * np.log1p(-u[:, :, 0:2 * d:2])) * np.cos(2.0 * np.pi * u[:, :, 1:2 * d:2])
    g /= np.maximum(np.linalg.norm(g, axis=2), 1e-300)[:, :, None]
    rho = 0.5 + 0.5 * u[:, :, 2 * d]
    cand = dom.domain.reflect((x[parents, None, :] + (rho * D[parents, None])[:, :, None] * g).reshape(-1, d))
    ok = dom.inside(cand)
    xa, Da = around(cand)
    m = min(INSERT_NEAREST, xa.shape[0])
    dist, near = nearest(xa, cand, m, dom.domain)
    dist, near = dist.reshape(cand.shape[0], m), near.reshape(cand.shape[0], m)
    # the new particle's D, estimated with the grading of Eq. 2.9 (D rises by at most
    # 1/r* per unit distance) from its nearest particles and the parent
    rs = dom.rstar
    Dpar = np.repeat(D[parents], k)
    Dnew = np.minimum((Da[near] + dist / rs).min(axis=1), Dpar * (1.0 + rho.ravel() / rs))
    # clearance: the smallest distance to an existing particle in units of D_pq
    clearance = (dist / np.minimum(Dnew[:, None], Da[near])).min(axis=1)
    # a site counts only if it would be the parent's neighbour: |x - x_p| <= r* min(D_p, D_new)
    counts = rho.ravel() * Dpar <= rs * np.minimum(Dpar, Dnew)
    score = np.where(ok, clearance + np.where(counts, 1e3, 0.0), -np.inf).reshape(parents.size, k)
    best = np.argmax(score, axis=1)
    keep = np.flatnonzero(np.isfinite(score[np.arange(parents.size), best]))
    return cand.reshape(parents.size, k, d)[keep, best[keep]], keep


def _displacement(domain: Domain, p: np.ndarray, pt: np.ndarray, step: np.ndarray) -> np.ndarray:
    """The move from p to pt (the descent's actual displacement): along periodic axes the step taken
    (pt is wrapped), else p - pt (walls may have shortened it)."""
    if domain.all_periodic:
        return step
    if domain.any_periodic:
        return np.where(np.asarray(domain.periodic), step, p - pt)
    return p - pt


def greedy_matching(rho: np.ndarray, ka: np.ndarray, kb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fusion's matching: the candidate pairs (ka < kb, keys) visited in the order of (rho = r / D_pq,
    ka, kb), each taken when neither particle is in a pair taken before.  Returns the taken pairs
    (ka, kb).  Equal to the locally dominant matching, so every process can run it on the gathered
    candidates."""
    order = np.lexsort((kb, ka, rho))
    used: set[int] = set()
    take = []
    for i in order.tolist():
        a, b = int(ka[i]), int(kb[i])
        if a not in used and b not in used:
            used.update((a, b))
            take.append(i)
    t = np.asarray(take, dtype=np.int64)
    return ka[t], kb[t]


def _scan(near: Near, period: np.ndarray, rcount: float, ctx: View):
    """The adaptation's pass over the own rows (§3.1): (own positions after fusion, alive, neighbour
    counts, neighbour counts among the survivors within rcount D_pq, max D_pq / r_pq, fusions).
    Fusion is :func:`greedy_matching` of the pairs closer than D_pq / 2 (each particle fuses at most
    once per pass, the first of the pair in key order moves to the midpoint): it does not depend on
    the list's layout or on how the particles are spread over processes."""
    n, keys, nl = near.n, near.keys, near.nl
    rho = _bridge.so_ratios(near.x, near.D, period, nl.offsets, nl.indices, context="self_organize")
    cols = nl.indices
    lowest = ctx.gmin(float(rho.min()) if rho.size else np.inf)
    ratio = 1.0 / lowest if lowest > 0 else float(np.finfo(np.float64).max)
    # the entries closer than half their D_pq (few), each pair from the row of its smaller key
    close = np.flatnonzero(rho < 0.5)
    crow = np.searchsorted(nl.offsets, close, side="right") - 1        # their rows
    first = keys[cols[close]] > keys[crow]
    cand, crow = close[first], crow[first]
    ka, kb = greedy_matching(*ctx.gather(rho[cand], keys[crow], keys[cols[cand]]))
    alive_all = ~np.isin(keys, kb)
    xo = near.x[:n]
    mine = np.isin(ka, keys[:n])
    if mine.any():
        by_key = np.argsort(keys, kind="stable")
        a = by_key[np.searchsorted(keys, ka[mine], sorter=by_key)].astype(np.int32)
        b = by_key[np.searchsorted(keys, kb[mine], sorter=by_key)].astype(np.int32)
        xo = np.ascontiguousarray(_bridge.so_fuse(near.x, period, a, b, context="self_organize")[:n])
    # per row, the entries within rcount D_pq whose two particles both survive
    within = rho <= rcount
    if kb.size:
        within &= alive_all[cols]
    run = np.zeros(within.size + 1, np.int64)
    np.cumsum(within, out=run[1:])
    cnt_alive = run[nl.offsets[1:n + 1]] - run[nl.offsets[:n]]
    if kb.size:
        cnt_alive[~alive_all[:n]] = 0
    return xo, alive_all[:n], nl.counts()[:n], cnt_alive, ratio, int(ka.size)


#: A target resolution must be at least 2**-RESOLUTION_BITS of the coordinates' scale (the largest
#: |coordinate| of the particles or the box): positions carry 52 bits, so offsets of finer stencils
#: would be rounded by more than 2**-22 of their size and DC-PSE moments would lose their digits.
RESOLUTION_BITS = 30


def self_organize(
    x: np.ndarray | ParticleSet,
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
    max_iter: int = 100,
    tol: float = 1e-4,
    seed: int | np.random.Generator | None = None,
    progress: bool = False,
    max_particles: int = MAX_PARTICLES,
    comm: Comm | None = None,
    keys: np.ndarray | None = None,
    decomposition: Decomposition | None = None,
) -> ParticleSet:
    """Adapt particles to a target resolution by fusion, insertion and gradient descent.

    Parameters
    ----------
    x : array (n, d) or ParticleSet
        Initial positions (d = 2 or 3), or a :class:`ParticleSet`.
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
        Most iterations.
    tol : float
        Relative energy decrease that ends a fixed-number run.
    seed : int or numpy.random.Generator, optional
        Seed (an int >= 0, or a Generator to draw one from) of the random insertion positions.
        The draws come from a counter-based generator keyed on (seed, iteration, parent particle,
        candidate): the same seed gives the same result, whatever the list method, thread or
        process count.  None: a fresh random seed.
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
        dealt to the ranks, adapted there and gathered: every rank gets the whole result.
    decomposition : Decomposition, optional
        With ``keys``: the ranks' boxes owning the particles given (default: bisected anew).

    Returns
    -------
    ParticleSet
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
    xs = as_positions(x.x if isinstance(x, ParticleSet) else x).copy()
    d = xs.shape[1]
    dom = (domain or Domain()).for_dim(d)
    if comm.size > 1:
        if isinstance(resolution, SampledResolution):
            raise NotImplementedError("self-organization of a SampledResolution (old particles) over several ranks "
                                      "is not available yet")
        seed = int_seed(seed, "an int >= 0, the same on every rank")
    kw: dict[str, Any] = dict(resolution=resolution, grad_f=grad_f, D0=D0, Dmin=Dmin, potential=potential, domain=dom, region=region,
              d_c=d_c, order=order, n_star=n_star, reach=reach, reading=reading, adapt_number=adapt_number,
              max_iter=max_iter, tol=tol, seed=seed, progress=progress and comm.rank == 0,
              max_particles=max_particles)
    if keys is None:
        if decomposition is not None:
            raise ValueError("decomposition= is for a rank's share of the particles: give their keys= too")
        if comm.size == 1:
            finite = np.all(np.isfinite(xs), axis=1)
            out = adapt(xs, np.arange(xs.shape[0], dtype=np.int64), comm, bisect(xs[finite], 1, domain=dom)[0], **kw)
            return replace(out, keys=None, decomposition=None)
        dec, xs, ks, _ = scatter(comm, xs, domain=dom)
        out = adapt(xs, ks, comm, dec, **kw)
        assert out.keys is not None
        _, xa, Da = gather(comm, out.keys, out.x, out.D)
        return replace(out, x=xa, D=Da, keys=None, decomposition=None)
    ks = np.asarray(keys)
    if ks.shape != (xs.shape[0],) or not np.issubdtype(ks.dtype, np.integer):
        raise ValueError(f"keys must be one integer per particle, shape ({xs.shape[0]},)")
    order = np.argsort(ks, kind="stable")
    xs, ks = xs[order], ks[order].astype(np.int64)
    if decomposition is None:
        decomposition = bisect(xs, comm.size, domain=dom, comm=comm)[0]
    return adapt(xs, ks, comm, decomposition, **kw)


def adapt(xs: np.ndarray, keys: np.ndarray, comm: Comm, dec: Decomposition, *, resolution, grad_f, D0, Dmin,
          potential: str, domain: Domain, region, d_c: float, order: int, n_star: int | None, reach: float,
          reading: str, adapt_number: bool, max_iter: int, tol: float, seed, progress: bool,
          max_particles: int) -> ParticleSet:
    """The work of :func:`self_organize` on this rank's particles ``xs`` with their ``keys``
    (ascending), the ranks of ``comm`` and their boxes ``dec``: the checks, the set-up and the
    iteration.  Returns this rank's particles of the adapted set in key order, with their keys and
    the boxes owning them at the end."""
    _check_arguments(resolution, grad_f, D0, Dmin, potential, d_c, max_iter, max_particles, n_star, tol, reach)
    check_reading(reading)
    n_own, d = xs.shape
    bad = np.flatnonzero(~np.all(np.isfinite(xs), axis=1))
    ns = n_star_for(order, d) if n_star is None else int(n_star)
    rs = r_star(d, ns)
    conf = Confinement(domain, region, rs)
    ctx = View(conf, comm, dec)
    if ctx.gsum(n_own) == 0:
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
    target = _Target(resolution, grad_f, D0, Dmin, reach * rs, domain, scale, reading)
    loop = _Adaptation(conf, target, potential, ns, d_c, seed64(seed), max_particles, ctx)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=int(max_iter), desc="self-organize", unit="it", disable=None)
    try:
        x_out, D, k_out, log, converged = loop.run(xs, keys, int(max_iter), adapt_number, tol, bar)
    finally:
        if bar is not None:
            bar.close()
    return ParticleSet(x_out, D, rs, ns, domain, log, converged, keys=k_out, decomposition=ctx.dec)


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


class _Target:
    """Steps iii-iv: D_p at given positions, from the monitor of a gradient (Eq. 2.8) or a target
    field D~, bounded by D0 and Dmin, graded by Eq. 2.9 (a :class:`SampledResolution` is taken as D_p
    directly)."""

    def __init__(self, resolution, grad_f, D0, Dmin, ball: float, domain: Domain, scale: float,
                 reading: str = "implicit") -> None:
        self.resolution, self.grad_f, self.D0, self.Dmin = resolution, grad_f, D0, Dmin
        self.ball, self.domain, self.scale, self.reading = ball, domain, scale, reading
        self.floor = math.ldexp(scale, -RESOLUTION_BITS)     # the finest D~ positions can resolve
        self.sampled = bool(getattr(resolution, "graded", False))     # (a SampledResolution, on one or many ranks)

    def d_tilde(self, p: np.ndarray) -> np.ndarray:
        """The target D~ at the points p (m, d), bounded by D0 and Dmin, before the grading of Eq. 2.9."""
        D0, Dmin = self.D0, self.Dmin
        if self.grad_f is not None:
            g = np.asarray(self.grad_f(p), dtype=np.float64)
            if g.shape != p.shape:
                raise ValueError(f"grad_f must return shape {p.shape}, got {g.shape}")
            d_tilde = monitor_gradient(g, D0, Dmin)
        else:
            d_tilde = np.asarray(self.resolution(p), dtype=np.float64)
            if d_tilde.shape != (p.shape[0],):
                raise ValueError(f"resolution must return shape ({p.shape[0]},), got {d_tilde.shape}")
            if D0 is not None:
                d_tilde = np.minimum(d_tilde, D0)
            if Dmin is not None:
                d_tilde = np.maximum(d_tilde, Dmin)
        if not np.all(np.isfinite(d_tilde)) or np.any(d_tilde <= 0):
            raise ValueError("the target resolution must be finite and > 0 everywhere")
        if d_tilde.min() < self.floor:
            raise ValueError(f"the target resolution reaches {d_tilde.min():.3g}, below 2**-{RESOLUTION_BITS} of the "
                             f"coordinates' scale {self.scale:.3g}: positions cannot resolve it; bound it with Dmin")
        return d_tilde


class _Adaptation:
    """The iteration of :func:`self_organize`, one method per step of the module docstring, over the own
    particles of a rank (one process: P = 1) as its :class:`~arpy.adapt.view.View` shows them."""

    def __init__(self, conf: Confinement, target: _Target, potential: str, n_star: int, d_c: float,
                 seed: int, max_particles: int, ctx: View) -> None:
        self.conf, self.domain, self.target = conf, conf.domain, target
        self.potential, self.ns, self.rs, self.d_c = potential, n_star, conf.rstar, d_c
        self.seed, self.max_particles, self.ctx = seed, max_particles, ctx
        self.next_key = 0

    def resolution(self, x: np.ndarray, keys: np.ndarray) -> np.ndarray:
        """iii-iv. D_p at the own particles: from the target at them and at the particles within the
        ball of Eq. 2.9 (r* times the largest target value here) around them."""
        n, target = x.shape[0], self.target
        own = target.d_tilde(x)
        if target.sampled:
            return own
        xa, = self.ctx.around(x, keys, target.ball * float(own.max(initial=0.0)))
        ext = np.concatenate([own, target.d_tilde(xa[n:])]) if xa.shape[0] > n else own
        return graded_resolution(xa, ext, target.ball, target.domain, target.reading)[:n]

    def near(self, x: np.ndarray, D: np.ndarray, keys: np.ndarray, skin: float = 0.0) -> Near:
        return self.ctx.near(x, D, keys, self.rs * D, skin)

    def forces(self, near: Near) -> tuple[float, np.ndarray]:
        """W (an exact sum over every process) and the own particles' gradient."""
        e, g = energy_terms(near.x, near.D, near.nl, self.potential, domain=self.domain, cutoff=self.rs)
        assert g is not None
        return self.ctx.fsum(e[: near.n]), g[: near.n]

    def energy(self, near: Near) -> float:
        """W alone (as :meth:`forces` gives it): a trial of the line search needs no gradient."""
        e, _ = energy_terms(near.x, near.D, near.nl, self.potential, domain=self.domain, cutoff=self.rs,
                            gradient=False)
        return self.ctx.fsum(e[: near.n])

    def mirror_counts(self, x: np.ndarray, keys: np.ndarray, rc: np.ndarray) -> np.ndarray:
        """The own particles' neighbours among the mirror images across the walls (cutoffs rc)."""
        if not self.domain.has_walls:
            return np.zeros(x.shape[0], np.int64)
        xa, ra = self.ctx.around(x, keys, self.ctx.gmax(float(rc.max(initial=0.0))), rc)
        return self.conf.mirror_counts(xa, ra)[: x.shape[0]]

    def fuse_and_insert(self, scan, D: np.ndarray, keys: np.ndarray,
                        iteration: int) -> tuple[np.ndarray, np.ndarray, int, int, int]:
        """i. fusion (the scan's survivors); ii. one new particle near every particle with fewer
        than N* neighbours (keys after every existing one, in the order of their parents' keys);
        particles that left the region are removed.  The particles stay in key order.  Returns
        (x, keys, fused, inserted, removed)."""
        conf, rs, ctx = self.conf, self.rs, self.ctx
        xo, alive, _, cnt_alive, _, fused = scan
        xs, D, keys = self.domain.confine(xo[alive]), D[alive], keys[alive]   # a midpoint may cross a periodic face
        cnt = cnt_alive[alive] + self.mirror_counts(xs, keys, INSERT_MARGIN * rs * D)
        need = cnt < self.ns
        if conf.region is not None:
            need &= ~conf.near_edge(xs, rs * D)
        parents = np.flatnonzero(need)
        count = ctx.gsum(parents.size)
        inserted = removed = 0
        if count:
            draws = counter_uniforms(self.seed, iteration, keys[parents], INSERT_CANDIDATES * (2 * xs.shape[1] + 1))
            new, which = _candidate_sites(xs, D, parents, conf, draws, lambda c: self._around_sites(xs, D, keys, c))
            kept = ctx.sites(new, D[parents[which]], keys[parents[which]])
            new_keys, self.next_key = ctx.new_keys(keys[parents[which[kept]]], self.next_key)
            inserted = ctx.gsum(int(kept.sum()))
            xs = np.concatenate([xs, new[kept]])
            keys = np.concatenate([keys, new_keys])
        if conf.region is not None:
            ok = conf.inside(xs)
            removed = ctx.gsum(int((~ok).sum()))
            xs, keys = xs[ok], keys[ok]
        total = ctx.gsum(xs.shape[0])
        if total > self.max_particles:
            raise RuntimeError(f"self_organize: {total} particles exceed max_particles = {self.max_particles} "
                               f"(smallest D_p {ctx.gmin(D.min(initial=np.inf)):.3g}); bound the resolution with Dmin")
        return xs, keys, fused, inserted, removed

    def _around_sites(self, xs: np.ndarray, D: np.ndarray, keys: np.ndarray, cand: np.ndarray):
        """The particles whose INSERT_NEAREST nearest to the candidates are among: the own ones give an
        upper bound of each candidate's distance to its nearest, every particle nearer is within that
        bound plus the candidate's distance from here."""
        def width() -> float:
            m = min(INSERT_NEAREST, xs.shape[0])
            if cand.shape[0] == 0 or m == 0:
                return 0.0
            dist, _ = nearest(xs, cand, m, self.domain)
            return float((dist.reshape(cand.shape[0], m)[:, -1] + self.ctx.gap(cand)).max())

        xa, Da = self.ctx.around(xs, keys, width, D)
        return xa, Da

    def descend(self, near: Near, gamma: float | None):
        """vi-vii. Armijo backtracking along -grad W with a per-particle displacement cap.  Returns
        (positions, their Near, W before, W after, the next step size, trials, moved)."""
        domain, conf, ctx = self.domain, self.conf, self.ctx
        p, Dp, keys = near.x[: near.n], near.D[: near.n], near.keys[: near.n]
        W0, g = self.forces(near)
        gnorm = np.sqrt((g * g).sum(axis=1))
        if not ctx.gsum(int(np.count_nonzero(gnorm > 0))):
            return p, near, W0, W0, gamma, 0, False
        if gamma is None:                   # the median particle moves 0.1 D_p
            gamma = 0.1 * float(np.median(ctx.gather(Dp[gnorm > 0] / gnorm[gnorm > 0])[0]))
        cap = MAX_STEP * Dp                 # and none more than MAX_STEP D_p
        for trial in range(1, MAX_HALVINGS + 1):
            step = gamma * g * np.minimum(1.0, cap / np.maximum(gamma * gnorm, 1e-300))[:, None]
            pt = domain.confine(p - step)
            keep = conf.inside(pt)
            if conf.region is not None and not np.all(keep):
                pt = np.where(keep[:, None], pt, p)   # a particle never steps out of the region
            disp = _displacement(domain, p, pt, step * keep[:, None])
            skin = ctx.gmax(float(np.sqrt((disp * disp).sum(axis=1)).max(initial=0.0)))
            near_t = self.near(pt, Dp, keys, skin)
            Wt = self.energy(near_t)
            predicted = ctx.fsum(g * disp)      # first-order decrease (an exact sum)
            if Wt <= W0 - ARMIJO_C * predicted:
                grow = 2.0 if W0 - Wt >= 0.5 * predicted else 1.0
                return pt, near_t, W0, Wt, gamma * grow, trial, True
            gamma *= 0.5
        return p, near, W0, W0, gamma, MAX_HALVINGS, False

    def check(self, near: Near):
        """viii. The scan, and the stopping figures: fewest neighbours (mirror images across walls
        included, particles at a region's edge exempt) and max D_pq / r_pq."""
        conf, rs, n = self.conf, self.rs, near.n
        sc = _scan(near, self.domain.period, INSERT_MARGIN * rs, self.ctx)
        cnt = sc[2] + self.mirror_counts(near.x[:n], near.keys[:n], rs * near.D[:n])
        counted = ~conf.near_edge(near.x[:n], rs * near.D[:n])
        fewest = self.ctx.gmin(float(cnt[counted].min()) if np.any(counted) else np.inf)
        return sc, (int(fewest) if np.isfinite(fewest) else self.ns), sc[4]

    def settle(self, near: Near) -> Near:
        """The own particles of ``near`` after a move, migrated to their owners (in key order), and
        their Near (``near`` itself when nothing migrated)."""
        n = near.n
        changed, (x, keys, D) = self.ctx.migrate(near.x[:n], near.keys[:n], near.D[:n])
        return self.near(x, D, keys) if changed else near

    def end_state(self, near: Near, scan, ratio: float):
        """The candidate end state once every particle has N* neighbours: these positions, or, if only
        pairs closer than D_pq / d_c fail the rule, the set after fusing them (step i of the next
        iteration); with D_p at those positions the rule must hold once more.  Returns (x, D, keys)
        or None."""
        n = near.n
        if ratio <= self.d_c:
            x_end, k_end = near.x[:n], near.keys[:n]
        else:
            x_end, k_end = self.domain.confine(scan[0][scan[1]]), near.keys[:n][scan[1]]
            _, (x_end, k_end) = self.ctx.migrate(x_end, k_end)
        D_end = self.resolution(x_end, k_end)
        _, nb_end, ratio_end = self.check(self.near(x_end, D_end, k_end))
        return (x_end, D_end, k_end) if nb_end >= self.ns and ratio_end <= self.d_c else None

    def run(self, xs: np.ndarray, keys: np.ndarray, max_iter: int, adapt_number: bool, tol: float, bar):
        """Iterate until the stopping rule holds (or the descent stalls, or max_iter runs out).
        ``keys``: the own particles' keys, ascending.  Returns (x, D, keys, the log, converged)."""
        ctx = self.ctx
        log: list[dict] = []
        self.next_key = int(ctx.gmax(float(keys.max(initial=-1)))) + 1
        D = self.resolution(xs, keys)
        near = self.near(xs, D, keys)
        scan = self.check(near)[0]
        gamma = None
        for it in range(1, max_iter + 1):
            t_start = time.perf_counter()
            fused = inserted = removed = 0
            if adapt_number:
                xs, keys, fused, inserted, removed = self.fuse_and_insert(scan, near.D[: near.n], keys, it)
                _, (xs, keys) = ctx.migrate(xs, keys)
            t_fi = time.perf_counter()
            D = self.resolution(xs, keys)            # iii-v. D_p at the current positions, r_c = r* D_p
            t_res = time.perf_counter()
            near = self.near(xs, D, keys)
            t_lst = time.perf_counter()
            _, near, W_before, W, gamma, trials, moved = self.descend(near, gamma)
            near = self.settle(near)
            xs, keys = near.x[: near.n], near.keys[: near.n]
            t_desc = time.perf_counter()
            scan, min_nb, ratio = self.check(near)     # (its fusion part serves the next iteration)
            t_end = time.perf_counter()
            n_all = ctx.gsum(near.n)
            log.append(dict(iteration=it, n=n_all, fused=int(fused), inserted=int(inserted),
                            removed=int(removed), energy_before=W_before, energy=W,
                            gamma=np.nan if gamma is None else float(gamma),   # None: no gradient yet
                            trials=int(trials), moved=bool(moved), min_neighbors=min_nb, max_ratio=ratio,
                            t_fuse_insert=t_fi - t_start, t_resolution=t_res - t_fi, t_lists=t_lst - t_res,
                            t_forces=(t_desc - t_lst) + (t_end - t_desc), t_total=t_end - t_start))
            if bar is not None:
                bar.update(1)
                bar.set_postfix(n=n_all, W=f"{W:.4g}", nb=min_nb, ratio=f"{ratio:.2f}")
            if adapt_number:
                end = self.end_state(near, scan, ratio) if min_nb >= self.ns else None
                if end is not None:
                    n_end = ctx.gsum(end[0].shape[0])
                    log[-1]["fused"] += n_all - n_end
                    log[-1]["n"] = n_end
                    return end[0], end[1], end[2], log, True
                if fused == inserted == removed == 0 and not moved:
                    break                         # stalled: nothing changes any more
            elif W_before - W <= tol * abs(W_before):
                return xs, near.D[: near.n], keys, log, True
        return xs, near.D[: near.n], keys, log, False


def displace_set(ps: ParticleSet, *, order: int = 4, old: tuple[np.ndarray, np.ndarray] | None = None,
                 rng: np.random.Generator | int | None = None) -> tuple[ParticleSet, Displaced]:
    """:func:`arpy.dcpse.displace.displace_until_valid` on a :class:`ParticleSet` (its r* and domain): (a
    copy of the set with the particles displaced and inserted, :class:`arpy.dcpse.displace.Displaced`)."""
    x, D, done = displace_until_valid(ps.x, ps.D, ps.rstar, domain=ps.domain, order=order, old=old, rng=rng)
    return replace(ps, x=x, D=D), done


def valid_stencils(ps: ParticleSet, rule: str, rng: np.random.Generator | int | None = None) -> ParticleSet:
    """An initial set for a simulation under a stencil rule: the set itself ("repair") or
    :func:`displace_set` of it ("displace")."""
    check_stencil_rule(rule)
    return ps if rule == "repair" else displace_set(ps, rng=rng)[0]
