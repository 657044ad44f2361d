"""The self-organizing adaptation loop (Reboux et al. 2012, §2.3.4, §3.1 and §3.2.2 step 4(e)).

Particles p carry a resolution D_p, a cutoff r_c,p = r* D_p and a core size
eps_p = r_c,p.  :func:`self_organize` iterates

  i.   fuse pairs closer than D_pq / 2 (one particle at their midpoint);
  ii.  insert one particle at a random position near every particle with fewer
       than N* neighbours (distance U(0.5, 1) D_p in a random direction);
  iii. rebuild the neighbour lists (|x_p - x_q| <= min(r_c,p, r_c,q));
  iv.  D_p at the new positions: from the target field D~ and Eq. 2.9, or
       interpolated from an old particle set (:class:`SampledResolution`);
  v.   r_c,p = eps_p = r* D_p;
  vi.  energy W and gradient (Fortran core, :func:`arpy.selforg.energy`),
       with V shifted by V(r*) so that W is continuous as pairs enter or
       leave the lists (the forces are the paper's);
  vii. a backtracking (Armijo) line search along -grad W, each trial energy
       evaluated with the neighbour lists of the trial positions, so that an
       accepted step never raises W;
  viii. stop when every particle has >= N* neighbours and
       max_p max_q D_pq / r_pq <= d_c; else back to i.

Boundaries: a periodic box (minimum image, ghosts for the lists), a box
with rigid walls (positions are projected back into it), or free space,
optionally limited to a region (particles leaving it are removed, and the
neighbour requirement is waived within r_c + D_p / 2 of its edge).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from . import _core
from ._errors import raise_for_info
from .neighbors import NeighborList, _as_positions, neighbor_list
from .periodic import as_box, nearest, periodic_ghosts, wrap
from .selforg import POTENTIALS, _period, energy, fourth_multi_indices, monitor_fourth, r_star
from .selforg import monitor as _eq28, resolution as _eq29

__all__ = ["MAX_PARTICLES", "ParticleSet", "SampledResolution", "field_resolution", "n_star_for", "self_organize"]

#: Monitor functions of :func:`field_resolution`: Eq. 2.8 and Eq. B.13 (m = 4).
MONITORS = ("gradient", "fourth")
#: DC-PSE order of the fourth derivatives behind ``monitor="fourth"`` (exact on quintics).
FOURTH_ORDER = 6
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
#: Thickness (in units of D_p) of the sparser outermost layer at a free-space region's
#: edge: particles whose neighbourhood ball (radius r_c) comes closer than this to
#: the edge are exempt from the neighbour requirement.  (Insertions for particles
#: just inside that layer drift into it and the requirement is never met.)
EDGE_LAYER = 0.5


def n_star_for(order: int, d: int) -> int:
    """N*: the number of moment conditions of DC-PSE of order m in d dimensions,
    i.e. monomials of degree < m (m = 4: 10 in 2D, 20 in 3D; §2.3.4)."""
    from math import comb

    if d not in (2, 3) or int(order) != order or order < 1:
        raise ValueError("need d in (2, 3) and an integer order >= 1")
    return comb(int(order) - 1 + d, d)


def log_arrays(log: list[dict]) -> dict[str, np.ndarray]:
    """A list of per-iteration (or per-step) dicts as arrays, one per key present in every entry."""
    if not log:
        return {}
    return {k: np.array([e[k] for e in log]) for k in log[0] if all(k in e for e in log)}


@dataclass(eq=False)
class ParticleSet:
    """An adapted particle set.

    Attributes
    ----------
    x : (n, d) positions.
    D : (n,) resolution D_p (length unit of x).
    rstar : cutoff factor, r_c = eps = rstar * D.
    n_star : the wanted number of neighbours N*.
    box : (lo, hi) arrays of shape (d,), or None (free space).
    periodic : whether the box is periodic (else its faces are rigid walls).
    log : one dict per iteration: ``iteration, n, fused, inserted, removed,
        energy_before, energy, gamma, trials, min_neighbors, max_ratio`` and
        timings ``t_fuse_insert, t_resolution, t_lists, t_forces, t_total``
        in seconds (``energy_before``/``energy``: W before and after the step,
        same particles, same D), ``moved`` (whether a step was accepted).
    converged : True if the stopping rule was met (else max_iter ran out or
        the descent stalled).
    """

    x: np.ndarray
    D: np.ndarray
    rstar: float
    n_star: int
    box: tuple[np.ndarray, np.ndarray] | None = None
    periodic: bool = False
    log: list[dict] = field(default_factory=list)
    converged: bool = False

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

    @property
    def eps(self) -> np.ndarray:
        """Core sizes eps_p = r_c,p, shape (n,)."""
        return self.rc

    def neighbor_list(self, symmetric: bool = True) -> NeighborList:
        """Neighbour lists under the min rule (periodic images included for a periodic box)."""
        return neighbor_list(self.x, self.rc, method="auto", symmetric=symmetric,
                             box=self.box if self.periodic else None)

    def history(self) -> dict[str, np.ndarray]:
        """The iteration log as arrays, one per key."""
        return log_arrays(self.log)

    def plot(self, ax=None, **kwargs):
        """Draw the particles (see :func:`arpy.plotting.plot_particles`)."""
        from .plotting import plot_particles

        return plot_particles(self, ax=ax, **kwargs)


class SampledResolution:
    """D_p known on an (old) particle set, interpolated to any points (§3.2.2 step 4(e)iv).

    First-order (Shepard) interpolation: D(y) = sum_q w_q D_q / sum_q w_q
    over the old particles q whose cutoff r* D_q reaches y, with
    w_q = (1 - |y - x_q|^2 / (r* D_q)^2)^2; a point no old particle reaches
    takes the D of the nearest one.  Positive, bounded by the old values,
    exact for constant D.  The values are taken to satisfy Eq. 2.9 already, so
    :func:`self_organize` uses them as D_p directly.

    x : (n, d) old positions; D : (n,) their D_p; rstar : cutoff factor;
    box : periodic box or None.
    """

    def __init__(self, x: np.ndarray, D: np.ndarray, rstar: float, box=None) -> None:
        from scipy.spatial import cKDTree

        from .arcells import ARCellList
        from .neighbors import _as_cutoffs

        xs = _as_positions(x)
        self.d = xs.shape[1]
        Ds = _as_cutoffs(D, xs.shape[0])
        if xs.shape[0] == 0:
            raise ValueError("SampledResolution needs at least one particle")
        if not np.all(np.isfinite(Ds)) or np.any(Ds <= 0):
            raise ValueError("D must be finite and > 0")
        self.box = None if box is None else as_box(box, self.d)
        if self.box is not None:
            xg, src = periodic_ghosts(xs, rstar * Ds, self.box)
            xs, Ds = np.concatenate([xs, xg]), np.concatenate([Ds, Ds[src]])
        self._x, self._D, self._rc = xs, Ds, rstar * Ds
        self._cells = ARCellList(xs, self._rc)
        self._tree = cKDTree(xs)
        self.degenerate = 0          # set by field_resolution: particles without a DC-PSE stencil

    def __call__(self, y: np.ndarray) -> np.ndarray:
        ys = _as_positions(y)
        if ys.shape[1] != self.d:
            raise ValueError(f"points must have d = {self.d} columns")
        if ys.shape[0] == 0:
            return np.zeros(0)
        nl = self._cells.cross_list(ys, self._rc.max())     # the old particle's own r_c decides
        rows, q = nl.rows(), nl.indices.astype(np.int64)
        s = ((ys[rows] - self._x[q]) ** 2).sum(axis=1) / self._rc[q] ** 2
        w = np.clip(1.0 - s, 0.0, None) ** 2
        num = np.bincount(rows, w * self._D[q], minlength=ys.shape[0])
        den = np.bincount(rows, w, minlength=ys.shape[0])
        out = np.empty(ys.shape[0])
        ok = den > 0
        out[ok] = num[ok] / den[ok]
        if not np.all(ok):
            _, nearest = self._tree.query(ys[~ok])
            out[~ok] = self._D[nearest]
        return out


def _check_reach(reach: float) -> None:
    if not (np.isfinite(reach) and reach >= 1.0):
        raise ValueError(f"reach must be a finite number >= 1, got {reach!r}")


def _check_monitor(monitor: str, order: int) -> None:
    if monitor not in MONITORS:
        raise ValueError(f"monitor must be one of {MONITORS}, got {monitor!r}")
    if monitor == "fourth" and order != 4:
        raise ValueError(f"monitor='fourth' is Eq. B.13 for order 4 interpolation; got order={order}")


def field_resolution(x: np.ndarray, f: np.ndarray, D: np.ndarray, *, D0: float, Dmin: float | None = None,
                     order: int = 4, box=None, periodic: bool = False, strict: bool = True,
                     widen: int = 0, max_lebesgue: float | None = None, reach: float = 1.0,
                     monitor: str = "gradient") -> SampledResolution:
    """Steps 4(a)-(c) of §3.2.2 on an old particle set: DC-PSE derivatives of the
    field values f, the monitor function D~, D_p by Eq. 2.9.

    x : (n, d) positions; f : (n,) field values; D : (n,) the particles'
    current D_p (their core sizes eps = r* D set the DC-PSE stencils);
    D0, Dmin : as in :func:`arpy.selforg.monitor`; box, periodic : the domain
    (a periodic box, walls with mirror images, or None).
    monitor : "gradient" -- Eq. 2.8 from the DC-PSE gradient (order ``order``);
        "fourth" -- Appendix B's Eq. B.13 for m = 4 (:func:`arpy.selforg.monitor_fourth`)
        from the fourth derivatives, by DC-PSE of order 6 (exact on quintics,
        error O(D^2); :data:`FOURTH_ORDER`) on cores widened to r* D_p with
        the r* of N* = 21 in 2D, 56 in 3D (2D: sqrt(7) instead of sqrt(3)),
        at most 0.45 of the shortest box edge.
        Needs ``order = 4``.
    strict=False: particles without a valid DC-PSE stencil get zero
    derivatives (so D~ = D0) instead of an error; their number is the
    result's ``degenerate``.
    widen, max_lebesgue : repair of such points and of wild stencils (see
        :func:`arpy.dcpse.boundary_dcpse`).
    reach : the factor on the ball of Eq. 2.9 (see :func:`self_organize`).
    Returns the new D_p as a :class:`SampledResolution` for :func:`self_organize`.
    """
    from .dcpse import boundary_dcpse

    xs = _as_positions(x)
    n, d = xs.shape
    f = np.asarray(f, dtype=np.float64)
    if f.shape != (n,) or not np.all(np.isfinite(f)):
        raise ValueError(f"f must be finite with shape ({n},)")
    _check_reach(reach)
    _check_monitor(monitor, order)
    rs = r_star(d, n_star_for(order, d))
    eps = rs * np.asarray(D, dtype=np.float64)
    if monitor == "gradient":
        op, extend = boundary_dcpse(xs, eps, box=box, periodic=periodic, order=order, strict=strict, widen=widen,
                                    max_lebesgue=max_lebesgue)
        target = _eq28(np.stack([g @ extend(f) for g in op.gradient()], axis=1), D0, Dmin)
    else:
        m = FOURTH_ORDER
        eps = eps * r_star(d, n_star_for(m, d)) / rs
        if box is not None:
            eps = np.minimum(eps, 0.45 * np.min(np.diff(as_box(box, d), axis=0)))
        op, extend = boundary_dcpse(xs, eps, box=box, periodic=periodic, order=m, strict=strict, widen=widen)
        fe = extend(f)
        d4f = np.stack([mat @ fe for mat in op.derivatives(fourth_multi_indices(d))], axis=1)
        target = monitor_fourth(d4f, D0, Dmin)
    pbox = box if periodic else None
    field = SampledResolution(xs, _eq29(xs, target, reach * rs, box=pbox), rs, box=pbox)
    field.degenerate = int(op.failed.size)
    return field


class _Domain:
    """Boundary handling: periodic box, walled box, or free space (with an optional region)."""

    def __init__(self, d: int, box, periodic: bool, region, rstar: float = 1.0) -> None:
        self.d, self.periodic, self.region, self.rstar = d, bool(periodic), region, float(rstar)
        self.box = None if box is None else as_box(box, d)
        if self.periodic and self.box is None:
            raise ValueError("periodic=True needs a box")
        if region is not None and not callable(region):
            raise TypeError("region must be a callable mapping (m, d) points to an (m,) boolean mask")
        self.period = _period(self.box if self.periodic else None, d)

    def inside(self, x: np.ndarray) -> np.ndarray:
        ok = np.ones(x.shape[0], bool)
        if self.box is not None and not self.periodic:
            ok &= np.all((x >= self.box[0]) & (x <= self.box[1]), axis=1)
        if self.region is not None:
            mask = np.asarray(self.region(x), dtype=bool)
            if mask.shape != (x.shape[0],):
                raise ValueError("region(x) must return a boolean mask of shape (m,)")
            ok &= mask
        return ok

    def confine(self, x: np.ndarray) -> np.ndarray:
        """Rigid walls: project into the box; periodic: wrap; free space: as is."""
        if self.box is None:
            return x
        if self.periodic:
            return wrap(x, self.box)
        return np.clip(x, *self.box)

    def reflect(self, x: np.ndarray) -> np.ndarray:
        """For inserted particles: mirror at the walls (then project), wrap if periodic."""
        if self.box is not None and not self.periodic:
            lo, hi = self.box
            x = np.where(x < lo, 2 * lo - x, x)
            x = np.where(x > hi, 2 * hi - x, x)
        return self.confine(x)

    def lists(self, x: np.ndarray, rc: np.ndarray) -> NeighborList:
        return neighbor_list(x, rc, method="auto", box=self.box if self.periodic else None)

    def mirror_counts(self, x: np.ndarray, rc: np.ndarray) -> np.ndarray:
        """Walls: neighbours p gains from the mirror images of the particles across the
        walls (method of images; a particle's own image is not counted).  Zeros otherwise."""
        n = x.shape[0]
        if self.box is None or self.periodic or n == 0:
            return np.zeros(n, np.int64)
        from .arcells import cross_neighbor_list
        from .periodic import mirror_images

        xm, src = mirror_images(x, rc, self.box)
        if src.size == 0:
            return np.zeros(n, np.int64)
        nl = cross_neighbor_list(x, rc, xm, rc[src])
        rows = nl.rows()
        keep = src[nl.indices] != rows
        return np.bincount(rows[keep], minlength=n)

    def near_edge(self, x: np.ndarray, rc: np.ndarray) -> np.ndarray:
        """Particles within about r_c + EDGE_LAYER D_p of the region's edge (probes along
        the axes and diagonals)."""
        if self.region is None or x.shape[0] == 0:
            return np.zeros(x.shape[0], bool)
        dirs = np.array([v for v in np.ndindex(*([3] * self.d)) if any(c != 1 for c in v)], float) - 1.0
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        reach = rc * (1.0 + EDGE_LAYER / self.rstar)
        probes = (x[:, None, :] + reach[:, None, None] * dirs[None]).reshape(-1, self.d)
        return ~np.asarray(self.region(probes), bool).reshape(x.shape[0], -1).all(axis=1)


def _insertion_sites(x: np.ndarray, D: np.ndarray, parents: np.ndarray, dom: _Domain,
                     rng: np.random.Generator) -> np.ndarray:
    """One new particle near each parent: of INSERT_CANDIDATES random points at
    distance U(0.5, 1) D_p in random directions (inside the domain), the one
    with the largest clearance min_q |x - x_q| / D_pq to the existing
    particles among those that would count as the parent's neighbour (D of
    the new particle estimated from the grading of Eq. 2.9); of two new sites
    closer than half their D, only the first is kept."""
    k, d = INSERT_CANDIDATES, x.shape[1]
    u = rng.normal(size=(parents.size, k, d))
    u /= np.maximum(np.linalg.norm(u, axis=2), 1e-300)[:, :, None]
    rho = rng.uniform(0.5, 1.0, size=(parents.size, k))
    cand = dom.reflect((x[parents, None, :] + (rho * D[parents, None])[:, :, None] * u).reshape(-1, d))
    ok = dom.inside(cand)
    m = min(INSERT_NEAREST, x.shape[0])
    dist, near = nearest(x, cand, m, dom.box if dom.periodic else None)
    dist, near = dist.reshape(cand.shape[0], m), near.reshape(cand.shape[0], m)
    # the new particle's D, estimated with the grading of Eq. 2.9 (D rises by at most
    # 1/r* per unit distance) from its nearest particles and the parent
    rs = dom.rstar
    Dpar = np.repeat(D[parents], k)
    Dnew = np.minimum((D[near] + dist / rs).min(axis=1), Dpar * (1.0 + rho.ravel() / rs))
    # clearance: the smallest distance to an existing particle in units of D_pq
    clearance = (dist / np.minimum(Dnew[:, None], D[near])).min(axis=1)
    # a site counts only if it would be the parent's neighbour: |x - x_p| <= r* min(D_p, D_new)
    counts = rho.ravel() * Dpar <= rs * np.minimum(Dpar, Dnew)
    score = np.where(ok, clearance + np.where(counts, 1e3, 0.0), -np.inf).reshape(parents.size, k)
    best = np.argmax(score, axis=1)
    rows = np.arange(parents.size)
    keep = np.isfinite(score[rows, best])
    sites, Ds = cand.reshape(parents.size, k, d)[rows[keep], best[keep]], D[parents[keep]]
    # neighbouring parents may pick the same hole: keep the first of sites closer than D/2
    # (the min rule of an AR list at 0.5 D: a kd-tree query at the largest D would
    # compare every pair of fine sites when the resolutions span decades)
    if sites.shape[0] > 1:
        a, b = neighbor_list(sites, 0.5 * Ds, method="auto").pairs()
        hit = np.linalg.norm(sites[a] - sites[b], axis=1) < 0.5 * np.minimum(Ds[a], Ds[b])
        drop = np.zeros(sites.shape[0], bool)
        for i, j in zip(a[hit], b[hit]):
            if not drop[i]:
                drop[j] = True
        sites = sites[~drop]
    return sites


def _scan(x: np.ndarray, D: np.ndarray, nl: NeighborList, period: np.ndarray, rcount: float):
    xo, alive, cnt_all, cnt_alive, ratio, nfused, info, bad = _core.arpy_so_scan(
        x.T, D, period, rcount, nl.offsets, nl.indices)
    raise_for_info(info, bad, context="self_organize")
    return np.ascontiguousarray(xo.T), alive.astype(bool), cnt_all, cnt_alive, float(ratio), int(nfused)


#: A target resolution must be at least 2**-RESOLUTION_BITS of the coordinates' scale (the largest
#: |coordinate| of the particles or the box): positions carry 52 bits, so offsets of finer stencils
#: would be rounded by more than 2**-22 of their size and DC-PSE moments would lose their digits.
RESOLUTION_BITS = 30


def _check_count(name: str, value) -> None:
    """A count parameter must be an integer >= 1 (NaN, inf, 2.5 and 0 are refused)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer, float, np.floating)) \
            or not np.isfinite(value) or int(value) != value or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")


def self_organize(
    x: np.ndarray | ParticleSet,
    resolution: Callable[[np.ndarray], np.ndarray] | None = None,
    *,
    grad_f: Callable[[np.ndarray], np.ndarray] | None = None,
    D0: float | None = None,
    Dmin: float | None = None,
    potential: str = "V2",
    box=None,
    periodic: bool = False,
    region: Callable[[np.ndarray], np.ndarray] | None = None,
    d_c: float = 2.5,
    order: int = 4,
    n_star: int | None = None,
    reach: float = 1.0,
    adapt_number: bool = True,
    max_iter: int = 100,
    tol: float = 1e-4,
    seed: int | np.random.Generator | None = None,
    progress: bool = False,
    max_particles: int = MAX_PARTICLES,
) -> ParticleSet:
    """Adapt particles to a target resolution by fusion, insertion and gradient descent.

    Parameters
    ----------
    x : (n, d) initial positions (d = 2 or 3), or a :class:`ParticleSet`.
    resolution : callable, (m, d) points -> (m,) target resolution D~ (length
        unit of x), e.g. a lambda or a :class:`SampledResolution`.  Exactly one
        of ``resolution`` and ``grad_f`` must be given.
    grad_f : callable, (m, d) points -> (m, d) gradient of the field f; then
        D~ = D0 / sqrt(1 + |grad f|^2) (the monitor function, Eq. 2.8).
    D0 : coarsest resolution: required with ``grad_f``; with ``resolution``
        an optional upper bound on D~.
    Dmin : optional lower bound on D~ (bounds the particle number, §2.3.4).
    potential : "V2" (repulsive; finite and periodic boxes) or "V1" (Morse; free space).
    box : None (free space), edge lengths (d,) (box [0, L]) or (lo, hi).
    periodic : the box is periodic; otherwise its faces are rigid walls.
    region : optional callable (m, d) -> (m,) bool: particles must stay where it
        is True (e.g. a narrow band in free space).  Needed for free space
        with ``adapt_number`` (else the edge of the cloud keeps growing).
        Particles within r_c + ``EDGE_LAYER`` D_p of its edge need not have N*
        neighbours.
    d_c : the stopping threshold on max D_pq / r_pq (default 2.5, §3.1).
    order : DC-PSE order m; sets N* (``n_star_for``) and r* (``arpy.selforg.r_star``).
    n_star : override N*.
    reach : factor on the radius of the ball of Eq. 2.9 (kappa in
        D_p = min over |x_q - x_p| <= kappa r* D_p of D~_q).  1 is the
        paper's; larger values grade D_p more slowly (slope 1 / (kappa r*))
        away from fine features, so that coarse stencils keep their distance
        from them (see :func:`arpy.selforg.resolution`).
    adapt_number : True: fuse and insert (§2.3.4).  False: fixed particle
        number, plain descent, stopping when W falls by less than ``tol``
        (relative) in an iteration (Fig. 2.3 of the paper).
    max_iter : most iterations.
    tol : relative energy decrease that ends a fixed-number run.
    seed : seed (or Generator) of the random insertion positions; the same
        seed gives the same result.
    progress : show a tqdm progress bar.
    max_particles : the particle number at which to stop with an error (a
        resolution field asking for far more particles than intended, e.g.
        from a noisy gradient, would otherwise exhaust the memory; bound D~
        with Dmin).

    Returns
    -------
    ParticleSet : positions, D_p, r_c, eps and the iteration log.  When
        converged, D_p is the resolution at the final positions and the
        stopping rule holds with it; otherwise D_p is the last value used.
    """
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
    _check_count("max_iter", max_iter)
    _check_count("max_particles", max_particles)
    if n_star is not None:
        _check_count("n_star", n_star)
    if not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be a finite number >= 0, got {tol!r}")
    _check_reach(reach)

    xs = _as_positions(x.x if isinstance(x, ParticleSet) else x).copy()
    n0, d = xs.shape
    if n0 == 0:
        raise ValueError("self_organize needs at least one particle")
    bad = np.flatnonzero(~np.all(np.isfinite(xs), axis=1))
    if bad.size:
        raise ValueError(f"self_organize: position of particle {bad[0]} is not finite (NaN or Inf)")
    ns = n_star_for(order, d) if n_star is None else int(n_star)
    rs = r_star(d, ns)
    dom = _Domain(d, box, periodic, region, rs)
    if box is None and region is None and adapt_number:
        raise ValueError("free space with adapt_number=True needs a region (else particles keep being "
                         "inserted at the edge of the cloud); give box=..., region=... or adapt_number=False")
    if not np.all(dom.inside(dom.confine(xs))):
        raise ValueError("initial particles lie outside the region")
    xs = dom.confine(xs)
    sampled = isinstance(resolution, SampledResolution)
    if sampled and (resolution.box is None) != (not dom.periodic):
        raise ValueError("the SampledResolution and self_organize must agree on periodicity")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    pbox = dom.box if dom.periodic else None
    scale = max(float(np.max(np.abs(xs))), 0.0 if dom.box is None else float(np.max(np.abs(dom.box))))
    floor = math.ldexp(scale, -RESOLUTION_BITS)

    def target(p: np.ndarray) -> np.ndarray:
        if grad_f is not None:
            g = np.asarray(grad_f(p), dtype=np.float64)
            if g.shape != p.shape:
                raise ValueError(f"grad_f must return shape {p.shape}, got {g.shape}")
            dt = _eq28(g, D0, Dmin)
        else:
            dt = np.asarray(resolution(p), dtype=np.float64)
            if dt.shape != (p.shape[0],):
                raise ValueError(f"resolution must return shape ({p.shape[0]},), got {dt.shape}")
            if D0 is not None:
                dt = np.minimum(dt, D0)
            if Dmin is not None:
                dt = np.maximum(dt, Dmin)
        if not np.all(np.isfinite(dt)) or np.any(dt <= 0):
            raise ValueError("the target resolution must be finite and > 0 everywhere")
        if dt.min() < floor:
            raise ValueError(f"the target resolution reaches {dt.min():.3g}, below 2**-{RESOLUTION_BITS} of the "
                             f"coordinates' scale {scale:.3g}: positions cannot resolve it; bound it with Dmin")
        return dt if sampled else _eq29(p, dt, reach * rs, box=pbox)


    def descend(p, Dp, nl, gamma):
        """Armijo backtracking along -grad W with a per-particle displacement cap."""
        W0, g = energy(p, Dp, nl, potential, box=pbox, cutoff=rs)
        gnorm = np.sqrt((g * g).sum(axis=1))
        if not np.any(gnorm > 0):
            return p, nl, W0, W0, gamma, 0, False
        if gamma is None:                   # the median particle moves 0.1 D_p
            gamma = 0.1 * np.median(Dp[gnorm > 0] / gnorm[gnorm > 0])
        cap = MAX_STEP * Dp                 # and none more than MAX_STEP D_p
        for trial in range(1, MAX_HALVINGS + 1):
            step = gamma * g * np.minimum(1.0, cap / np.maximum(gamma * gnorm, 1e-300))[:, None]
            pt = dom.confine(p - step)
            keep = dom.inside(pt)
            if dom.region is not None and not np.all(keep):
                pt = np.where(keep[:, None], pt, p)   # a particle never steps out of the region
            disp = p - pt if not dom.periodic else step * keep[:, None]
            nlt = dom.lists(pt, rs * Dp)
            Wt, _ = energy(pt, Dp, nlt, potential, box=pbox, cutoff=rs)
            predicted = float((g * disp).sum())      # first-order decrease
            if Wt <= W0 - ARMIJO_C * predicted:
                grow = 2.0 if W0 - Wt >= 0.5 * predicted else 1.0
                return pt, nlt, W0, Wt, gamma * grow, trial, True
            gamma *= 0.5
        return p, nl, W0, W0, gamma, MAX_HALVINGS, False

    def check(p, Dp, nl):
        """The scan, and the stopping figures: fewest neighbours (mirror images
        across walls included, particles at a region's edge exempt) and max D_pq / r_pq."""
        sc = _scan(p, Dp, nl, dom.period, INSERT_MARGIN * rs)
        cnt = sc[2] + dom.mirror_counts(p, rs * Dp)
        counted = ~dom.near_edge(p, rs * Dp)
        return sc, (int(cnt[counted].min()) if np.any(counted) else ns), sc[4]

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=int(max_iter), desc="self-organize", unit="it")
    log: list[dict] = []
    D = target(xs)
    nl = dom.lists(xs, rs * D)
    scan = check(xs, D, nl)[0]
    gamma, converged = None, False
    for it in range(1, int(max_iter) + 1):
        t_start = time.perf_counter()
        fused = inserted = removed = 0
        if adapt_number:
            # i. fusion; ii. insertion near particles with fewer than N* neighbours
            xo, alive, _, cnt_alive, _, fused = scan
            xs, D = dom.confine(xo[alive]), D[alive]      # a fused midpoint may cross a periodic face
            cnt = cnt_alive[alive] + dom.mirror_counts(xs, INSERT_MARGIN * rs * D)
            need = cnt < ns
            if dom.region is not None:
                need &= ~dom.near_edge(xs, rs * D)
            parents = np.flatnonzero(need)
            if parents.size:
                new = _insertion_sites(xs, D, parents, dom, rng)
                inserted = new.shape[0]
                xs = np.concatenate([xs, new])
            if dom.region is not None:
                ok = dom.inside(xs)
                removed = int((~ok).sum())
                xs = xs[ok]
            if xs.shape[0] > max_particles:
                raise RuntimeError(f"self_organize: {xs.shape[0]} particles exceed max_particles = {max_particles} "
                                   f"(smallest D_p {D.min():.3g}); bound the resolution with Dmin")
        t_fi = time.perf_counter()
        # iii-v. D_p at the current positions, r_c = eps = r* D_p
        D = target(xs)
        t_res = time.perf_counter()
        nl = dom.lists(xs, rs * D)
        t_lst = time.perf_counter()
        # vi-vii. energy, gradient, line search
        xs, nl, W_before, W, gamma, trials, moved = descend(xs, D, nl, gamma)
        t_desc = time.perf_counter()
        # viii. stopping figures (the scan's fusion part serves the next iteration)
        scan, min_nb, ratio = check(xs, D, nl)
        t_end = time.perf_counter()
        log.append(dict(iteration=it, n=int(xs.shape[0]), fused=int(fused), inserted=int(inserted),
                        removed=int(removed), energy_before=W_before, energy=W,
                        gamma=np.nan if gamma is None else float(gamma),   # None: no gradient yet
                        trials=int(trials), moved=bool(moved), min_neighbors=min_nb, max_ratio=ratio,
                        t_fuse_insert=t_fi - t_start, t_resolution=t_res - t_fi, t_lists=t_lst - t_res,
                        t_forces=(t_desc - t_lst) + (t_end - t_desc), t_total=t_end - t_start))
        if bar is not None:
            bar.update(1)
            bar.set_postfix(n=xs.shape[0], W=f"{W:.4g}", nb=min_nb, ratio=f"{ratio:.2f}")
        if adapt_number:
            if min_nb >= ns:
                # candidate end state: these positions, or, if only pairs closer than
                # D_pq / d_c fail the rule, the set after fusing them (step i of the next
                # iteration); with D_p at those positions the rule must hold once more
                x_end = xs if ratio <= d_c else dom.confine(scan[0][scan[1]])
                D_end = target(x_end)
                _, nb_end, ratio_end = check(x_end, D_end, dom.lists(x_end, rs * D_end))
                if nb_end >= ns and ratio_end <= d_c:
                    log[-1]["fused"] += xs.shape[0] - x_end.shape[0]
                    log[-1]["n"] = int(x_end.shape[0])
                    xs, D, converged = x_end, D_end, True
                    break
            if fused == inserted == removed == 0 and not moved:
                break                         # stalled: nothing changes any more
        elif W_before - W <= tol * abs(W_before):
            converged = True
            break
    if bar is not None:
        bar.close()
    return ParticleSet(x=xs, D=D, rstar=rs, n_star=ns, box=dom.box, periodic=dom.periodic, log=log,
                       converged=converged)
