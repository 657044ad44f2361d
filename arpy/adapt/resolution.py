"""The target resolution of the self-organizing particles (Reboux et al. 2012, §2.3.1-2.3.2, App. B).

* :func:`monitor_gradient` -- the monitor function of Eq. 2.8, ``D~(x) = D0 / sqrt(1 + |grad f|^2)``, bounded
  below by D_min; :func:`monitor_fourth` -- Appendix B's Eq. B.13 for m = 4,
  ``D~ = D0 (1 + max |d^4 f|)^(-1/4)``, from the fourth derivatives;
* :func:`graded_resolution` -- Eq. 2.9: D_p = min of D~ over the particles within reach r* D_p;
* :func:`r_star`, :func:`n_star_for` -- the cutoff r_c = r* D_p that holds N* neighbours (§2.3.4);
* :class:`SampledResolution` -- D_p known on an old particle set, at any point (§3.2.2 step 4(e)iv);
* :func:`field_resolution` -- steps 4(a)-(c) of §3.2.2: DC-PSE derivatives of a field on the old
  particles, the monitor, Eq. 2.9, as a :class:`SampledResolution` for :func:`arpy.self_organize`.
"""

from __future__ import annotations

from math import comb
from typing import Any, Callable, Sequence

import numpy as np

from .. import _bridge
from .._validate import as_cutoffs, as_positions
from ..lists.ar import ARCellList
from ..dcpse.boundary import Conditions
from ..dcpse.kernel import gradient_indices
from ..domain import Domain, as_domain
from ..distributed.comm import Comm, SerialComm
from ..distributed.dcpse import DistributedDCPSE, nearest_values
from ..distributed.decomposition import Decomposition, bounding_box
from ..distributed.ghosts import fetch, halo, owned
from ..distributed.share import Sharing
from .view import Confinement, View

__all__ = ["FOURTH_ORDER", "MONITORS", "SampledResolution", "check_monitor", "check_reach", "field_resolution",
           "fourth_multi_indices", "grade", "graded_among", "graded_resolution", "monitor_fourth", "monitor_gradient",
           "monitor_target", "n_star_for", "r_star"]

#: Monitor functions of :func:`field_resolution`: Eq. 2.8 and Eq. B.13 (m = 4).
MONITORS = ("gradient", "fourth")
#: DC-PSE order of the fourth derivatives behind ``monitor="fourth"`` (exact on quintics).
FOURTH_ORDER = 6


def monitor_gradient(grad_f: np.ndarray, D0: float, Dmin: float | None = None) -> np.ndarray:
    """Target resolution ``D~ = D0 / sqrt(1 + |grad f|^2)`` (Eq. 2.8), at least Dmin.

    Parameters
    ----------
    grad_f : array (n, d)
        Gradient of the field at the particles (units of f per length).
    D0 : float
        The coarsest resolution, > 0 (length).
    Dmin : float, optional
        The finest resolution, 0 < Dmin <= D0 (length).

    Returns
    -------
    array (n,)
        D~ (length).
    """
    g = np.asarray(grad_f, dtype=np.float64)
    if g.ndim != 2:
        raise ValueError("grad_f must have shape (n, d)")
    _check_d0(D0)
    return _bounded(D0 / np.sqrt(1.0 + (g * g).sum(axis=1)), D0, Dmin)


def monitor_fourth(d4f: np.ndarray, D0: float, Dmin: float | None = None) -> np.ndarray:
    """Target resolution of Appendix B (Eq. B.13) for interpolation of order m = 4,
    regularised like Eq. 2.8: ``D~ = D0 (1 + max over |beta| = 4 of |d^beta f|)^(-1/4)``,
    at least Dmin.

    It equidistributes the leading error of m = 4 interpolation, ``D_p^4 |f|_{W^4}``,
    so the flanks of a front, where ``|grad f|`` is small but the fourth derivatives
    are not, get the resolution they need (Eq. 2.8 leaves them at about D0).

    Parameters
    ----------
    d4f : array (n, k)
        Fourth partial derivatives of the field at the particles, any k >= 1 of them (e.g. the k of
        :func:`fourth_multi_indices`; units of f per length^4).
    D0, Dmin : float
        As for :func:`monitor_gradient` (length).

    Returns
    -------
    array (n,)
        D~ (length).
    """
    g = np.asarray(d4f, dtype=np.float64)
    if g.ndim != 2 or g.shape[1] == 0:
        raise ValueError("d4f must have shape (n, k) with k >= 1")
    _check_d0(D0)
    return _bounded(D0 * (1.0 + np.abs(g).max(axis=1)) ** -0.25, D0, Dmin)


def fourth_multi_indices(d: int) -> list[tuple[int, ...]]:
    """The multi-indices beta with ``|beta| = 4`` in d dimensions (5 in 2D, 15 in 3D),
    first coordinate's power descending: (4, 0), (3, 1), ... in 2D."""
    if d not in (2, 3):
        raise ValueError("d must be 2 or 3")
    if d == 2:
        return [(4 - k, k) for k in range(5)]
    return [(a, b, 4 - a - b) for a in range(4, -1, -1) for b in range(4 - a, -1, -1)]


def _check_d0(D0: float) -> None:
    if not (np.isfinite(D0) and D0 > 0):
        raise ValueError("D0 must be a finite number > 0")


def _bounded(out: np.ndarray, D0: float, Dmin: float | None) -> np.ndarray:
    if Dmin is not None:
        if not (np.isfinite(Dmin) and 0 < Dmin <= D0):
            raise ValueError("Dmin must satisfy 0 < Dmin <= D0")
        out = np.maximum(out, Dmin)
    return out


def r_star(d: int, n_star: int | None = None) -> float:
    """Cutoff factor r* (r_c = r* D): the smallest neighbour-shell radius of a
    triangular (2D) or face-centred cubic (3D) lattice of spacing 1 that holds
    at least N* neighbours (§2.3.4).  N* defaults to 10 in 2D and 20 in 3D
    (order-4 DC-PSE).  2D: sqrt(3) (12 neighbours); 3D: sqrt(3) (42).
    """
    if d not in (2, 3):
        raise ValueError("d must be 2 or 3")
    n_star = (10 if d == 2 else 20) if n_star is None else int(n_star)
    if n_star < 1:
        raise ValueError("n_star must be >= 1")
    k = np.arange(-8, 9)
    if d == 2:
        i, j = np.meshgrid(k, k, indexing="ij")
        pts = np.stack([i + 0.5 * j, j * np.sqrt(3) / 2], axis=-1).reshape(-1, 2)
    else:
        i, j, l = np.meshgrid(k, k, k, indexing="ij")
        cubic = np.stack([i, j, l], axis=-1).reshape(-1, 3)
        pts = cubic[(cubic.sum(axis=1) % 2) == 0] / np.sqrt(2)     # fcc, nearest distance 1
    dist = np.sort(np.sqrt((pts ** 2).sum(axis=1)))[1:]
    shells = np.unique(np.round(dist, 9))
    for radius in shells:
        if np.sum(dist <= radius + 1e-9) >= n_star:
            return float(np.sqrt(round(radius ** 2, 6)))
    raise ValueError(f"N* = {n_star} is too large")


def n_star_for(order: int, d: int) -> int:
    """N*: the number of moment conditions of DC-PSE of order m in d dimensions,
    i.e. monomials of degree < m (m = 4: 10 in 2D, 20 in 3D; §2.3.4)."""
    if d not in (2, 3) or int(order) != order or order < 1:
        raise ValueError("need d in (2, 3) and an integer order >= 1")
    return comb(int(order) - 1 + d, d)


#: The two readings of Eq. 2.9 (see :func:`graded_resolution`).
READINGS = ("implicit", "explicit", "pointwise")


def check_reading(reading: str) -> None:
    """A reading of Eq. 2.9, one of :data:`READINGS`."""
    if reading not in READINGS:
        raise ValueError(f"reading must be one of {READINGS}, got {reading!r}")


def graded_resolution(x: np.ndarray, d_tilde: np.ndarray | Callable[[np.ndarray], np.ndarray],
                      rstar: float, domain: Domain | None = None, reading: str = "implicit") -> np.ndarray:
    """D_p = min of D~(x_q) over the particles q within r_c,p = r* D_p of p (Eq. 2.9).

    The equation is implicit (the ball's radius depends on D_p).  With
    ``g_p(R) = min { D~(x_q) : |x_q - x_p| <= R }``, non-increasing in R, D_p is
    its largest consistent value, D_p = sup { D : g_p(r* D) >= D }: the
    resolution of p is as coarse as it can be while no particle within its
    own reach asks for a finer one.  D_p <= D~(x_p); where D~ varies slowly
    D_p = D~(x_p); near a fine feature D_p is graded, falling to the fine
    value over a distance of r* times the local D (rather than jumping to
    it wherever the coarse reach r* D~_p would touch the feature).

    The constraint from a particle q at distance s is D <= max(D~_q, s / r*)
    (either q is out of reach, or its demand is met), so
    ``D_p = min over q of max(D~_q, |x_q - x_p| / r*)`` (q = p gives D~_p itself).
    The particles are scanned ring by ring of a grid, nearest rings first; once
    the distance s reaches r* times the running minimum, no farther particle can
    lower it, so each p visits about the particles within its own final reach
    r* D_p (about 16 in an adapted set), not all those within r* D~_p (many,
    beside a fine feature).

    Parameters
    ----------
    x : array (n, d)
        Positions.
    d_tilde : array (n,) or callable
        The target resolution D~ at the particles (length unit of x), or a callable giving it
        from positions.
    rstar : float
        The factor r* of the ball's radius (times the ``reach`` of :func:`arpy.self_organize`).
    domain : Domain or None
        Along periodic axes the ball reaches across the faces (minimum image).
    reading : {"implicit", "explicit", "pointwise"}
        "implicit" (above; arpy's default): the ball's radius is r* D_p itself.  "explicit": its
        radius is r* D~(x_p), the un-graded value, ``D_p = min { D~_q : |x_q - x_p| <= r* D~_p }``:
        D_p jumps to the fine value wherever the coarse reach touches a fine feature (a reading
        of the paper's text; ``benchmarks/monitor_study.py`` compares the two).  "pointwise":
        no ball, D_p = D~(x_p) (Eq. 2.9 left out; to see what it does, e.g. on Fig. 2.3's jump).

    Returns
    -------
    array (n,)
        D_p, length unit of x (:func:`graded_among`: at some points over other sources).
    """
    check_reading(reading)

    xs = as_positions(x)
    target = np.asarray(d_tilde(xs) if callable(d_tilde) else d_tilde, dtype=np.float64)
    target = as_cutoffs(target, xs.shape[0])
    if not (np.isfinite(rstar) and rstar > 0):
        raise ValueError("r* must be a finite number > 0")
    if not np.all(np.isfinite(target)) or np.any(target <= 0):
        raise ValueError("the target resolution must be finite and > 0")
    return graded_among(xs, target, xs, target, rstar, domain, reading)


def graded_among(x: np.ndarray, target: np.ndarray, sources: np.ndarray, source_target: np.ndarray, rstar: float,
                 domain: Domain | None = None, reading: str = "implicit") -> np.ndarray:
    """D_p of Eq. 2.9 (:func:`graded_resolution`) at the points x (n, d) with their D~ ``target`` (n,),
    over the ``sources`` (m, d) with their D~ ``source_target`` (m,), among which are the points
    themselves and every source within r* D~_p of each (minimum image along periodic axes): the
    value does not depend on which other sources there are.  Returns D (n,)."""
    if reading == "pointwise" or x.shape[0] == 0:
        return np.array(target, dtype=np.float64)
    xr, dr = sources, source_target
    if domain is not None and domain.any_periodic:
        xg, src = domain.images(sources, rstar * source_target.max())    # images out to the largest reach
        xr, dr = np.concatenate([sources, xg]), np.concatenate([source_target, source_target[src]])
    return grade(x, target, xr, dr, rstar, reading)


def grade(x: np.ndarray, target: np.ndarray, sources: np.ndarray, source_target: np.ndarray, rstar: float,
          reading: str = "implicit") -> np.ndarray:
    """The scan of :func:`graded_resolution` (readings "implicit" and "explicit"): D_p of the particles
    x (n, d) with their D~ ``target`` (n,), over the ``sources`` (m, d) with their D~
    ``source_target`` (m,), which hold every point within the ball of each particle (one process:
    the particles and their periodic images; ranks: a rank's particles and those the other ranks
    sent).  Returns D (n,).

    "implicit": the core's ring scan of a grid of the sources (``fortran/selforg/arpy_grade.f90``), which
    visits about the sources within each particle's final reach, a wide reach by blocks of cells that
    skip the sources that cannot lower D_p, and runs on every core; the exact minimum over every source,
    bitwise the same for any number of threads (tests/test_selforg.py checks it against the O(n m)
    minimum)."""
    n = x.shape[0]
    if reading == "explicit":
        from scipy.spatial import cKDTree

        near = cKDTree(sources).query_ball_point(x, rstar * target)
        counts = np.fromiter((len(q) for q in near), dtype=np.int64, count=n)   # p itself: >= 1 each
        flat = np.fromiter((j for q in near for j in q), dtype=np.int64, count=int(counts.sum()))
        return np.minimum.reduceat(source_target[flat], np.concatenate([[0], np.cumsum(counts)[:-1]]))
    if not (np.isfinite(rstar) and rstar > 0):
        raise ValueError("r* must be a finite number > 0")
    if n == 0:
        return target.copy()
    if sources.shape[0] == 0:
        raise ValueError("Eq. 2.9 needs at least one source (the particles themselves)")
    return _bridge.grade(x, target, sources, source_target, rstar, context="graded_resolution")


class SampledResolution:
    """D_p known on an (old) particle set, interpolated to any points (§3.2.2 step 4(e)iv).

    First-order (Shepard) interpolation: ``D(y) = sum_q w_q D_q / sum_q w_q``
    over the old particles q whose cutoff r* D_q reaches y, with
    ``w_q = (1 - |y - x_q|^2 / (r* D_q)^2)^2``; a point no old particle reaches
    takes the D of the nearest one (ties by key).  Positive, bounded by the old values,
    exact for constant D.  The values are taken to satisfy Eq. 2.9 already, so
    :func:`arpy.self_organize` uses them as D_p directly.

    The old set may be spread over the ranks of ``comm`` (each rank gives its own particles and their
    keys): a call, collective then, asks the other ranks for their old particles (and periodic images)
    whose reach meets the box of its points, and sums in the order of one process holding the whole
    set numbered by key, so the values are bitwise the same for every rank count.  One process holds
    every old particle and its periodic images from the start.

    Parameters
    ----------
    x : array (n, d)
        Old positions (this rank's).
    D : array (n,)
        Their D_p (length unit of x).
    rstar : float
        Cutoff factor: old particle q reaches r* D_q.
    domain : Domain or None
        Along periodic axes the old particles reach across the faces.
    comm : Comm, optional
        The ranks holding the old set (default: this process alone).
    keys : int array (n,), optional
        The old particles' global keys (default: their indices).
    """

    #: Its values are D_p already graded by Eq. 2.9 (:func:`arpy.self_organize` takes them as they are).
    graded = True

    def __init__(self, x: np.ndarray, D: np.ndarray, rstar: float, domain: Domain | None = None, *,
                 comm: Comm | None = None, keys: np.ndarray | None = None) -> None:
        xs = as_positions(x)
        self.d = xs.shape[1]
        Ds = as_cutoffs(D, xs.shape[0])
        self.comm = comm or SerialComm()
        if self.comm.sum(xs.shape[0]) == 0:
            raise ValueError("SampledResolution needs at least one particle")
        if not np.all(np.isfinite(Ds)) or np.any(Ds <= 0):
            raise ValueError("D must be finite and > 0")
        if keys is None and self.comm.size > 1:
            raise ValueError("a SampledResolution on several ranks needs the old particles' global keys (keys=)")
        self.keys = np.arange(xs.shape[0], dtype=np.int64) if keys is None else np.asarray(keys, dtype=np.int64)
        if self.keys.shape != (xs.shape[0],):
            raise ValueError(f"keys must have one entry per particle ({xs.shape[0]}), got shape {self.keys.shape}")
        self.domain = as_domain(domain, self.d)
        if not (np.isfinite(rstar) and rstar > 0):
            raise ValueError(f"rstar must be a finite number > 0 (r* of Eq. 2.9, e.g. Particles.rstar), "
                             f"got {rstar!r}")
        self.x, self.D, self.rstar = xs, Ds, float(rstar)
        self._whole = self._sources(None) if self.comm.size == 1 else None
        # (the sources are positioned images, so reaches are plain distances)
        self._sharing = Sharing(self.comm, None)
        self.degenerate = 0          # set by field_resolution: particles without a DC-PSE stencil

    def _sources(self, ys: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, ARCellList | None]:
        """The old particles (and periodic images) that may reach the points ys (None: any point of
        the domain), in the order of one process holding them all numbered by key (particles by key,
        then images by shift and key): (positions, D, r_c, their AR cell list).  Collective."""
        n, d = self.x.shape
        reach = self.rstar * self.D
        if ys is None:              # one process: the whole box (every particle and its images near the faces)
            lo, hi = np.full(d, -np.inf), np.full(d, np.inf)
            if self.domain.lo is not None and self.domain.hi is not None:
                per = np.asarray(self.domain.periodic, bool)
                lo, hi = np.where(per, self.domain.lo, lo), np.where(per, self.domain.hi, hi)
        else:
            lo, hi = bounding_box(ys)
        asks = self.comm.gather_arrays(np.concatenate([lo, hi]).astype(np.float64))[0].reshape(self.comm.size, 2, d)
        boxes = Decomposition(asks[:, 0], asks[:, 1])
        sends = halo(self.x, reach, boxes, np.full(n, self.comm.rank, np.int64), domain=self.domain)
        own = sends[self.comm.rank]                         # own particles: to itself unshifted too
        sends[self.comm.rank] = (np.concatenate([np.arange(n), own[0]]), np.concatenate([np.zeros((n, d)), own[1]]))
        xl, Dl, _, _, _, _ = fetch(self.comm, self.x, self.D, self.keys, sends, self.domain)
        rc = self.rstar * Dl
        return xl, Dl, rc, ARCellList(xl, rc) if xl.shape[0] else None

    def __call__(self, y: np.ndarray) -> np.ndarray:
        """D at the points y (m, d), (m,).  Collective on several ranks."""
        ys = as_positions(y)
        if ys.shape[1] != self.d:
            raise ValueError(f"points must have d = {self.d} columns")
        out, ok = self.shepard(ys)
        out[~ok] = nearest_values(self.comm, self.x, self.keys, self.D, self.domain, ys[~ok], 1)[:, 0]
        return out

    def shepard(self, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The Shepard interpolation at the points ys (m, d), and whether an old particle reaches each
        (bool (m,); the others' values are left undefined, :meth:`__call__` gives them the nearest's).
        Collective on several ranks."""
        xl, Dl, rc, cells = self._whole if self._whole is not None else self._sources(ys)

        def work(y: np.ndarray, xs: np.ndarray, rcs: np.ndarray, Ds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            if y.shape[0] == 0 or xs.shape[0] == 0:
                return np.empty(y.shape[0]), np.zeros(y.shape[0], bool)
            # the old particle's own r_c decides; the core sums each row in ascending source order, so
            # the result follows no list layout (nor which sources beyond the points' reach there are)
            nl = (cells if xs is xl and cells is not None else ARCellList(xs, rcs)).cross_list(y, rcs.max())
            out, ok = _bridge.shepard(y, xs, rcs, Ds, nl.offsets, nl.indices, context="SampledResolution")
            return out, ok.astype(bool)

        # a point's value depends on the old particles whose reach holds it alone: it may be computed elsewhere
        out, ok = self._sharing.map("shepard", work, (ys,), ys, lambda: np.full(ys.shape[0], rc.max(initial=0.0)),
                                    (xl, rc, Dl))
        return out, ok


def check_reach(reach: float) -> None:
    """The factor on the ball of Eq. 2.9 must be a finite number >= 1."""
    if not (np.isfinite(reach) and reach >= 1.0):
        raise ValueError(f"reach must be a finite number >= 1, got {reach!r}")


def check_monitor(monitor: str, order: int) -> None:
    """A monitor of :data:`MONITORS`; "fourth" (Eq. B.13 for m = 4) needs DC-PSE order 4."""
    if monitor not in MONITORS:
        raise ValueError(f"monitor must be one of {MONITORS}, got {monitor!r}")
    if monitor == "fourth" and order != 4:
        raise ValueError(f"monitor='fourth' is Eq. B.13 for order 4 interpolation; got order={order}")


def field_resolution(x: np.ndarray, f: np.ndarray, D: np.ndarray, *, D0: float, Dmin: float | None = None,
                     order: int = 4, domain: Domain | None = None, strict: bool = True,
                     widen: int = 0, max_lebesgue: float | None = None, reach: float = 1.0,
                     monitor: str = "gradient", bc: Sequence[Conditions | None] | None = None,
                     t: float = 0.0, reading: str = "implicit", comm: Comm | None = None,
                     keys: np.ndarray | None = None, decomposition: Decomposition | None = None) -> SampledResolution:
    """Steps 4(a)-(c) of §3.2.2 on an old particle set: DC-PSE derivatives of the
    field values f, the monitor function D~, D_p by Eq. 2.9.  The set may be spread over the ranks
    of ``comm``: the same code, bitwise the same result for every rank count.

    Parameters
    ----------
    x : array (n, d)
        Positions (length).
    f : array (n,) or (n, k)
        Field values at the particles; with k fields, D~ is the finest of their monitors.
    D : array (n,)
        The particles' current D_p (length); their core sizes eps = r* D set the DC-PSE stencils.
    D0, Dmin : float
        As for :func:`monitor_gradient` (length).
    order : int
        DC-PSE order m of the gradient; sets N* and r*.
    domain : Domain or None
        Periodic axes give periodic images, walls mirror images (homogeneous Neumann); None: free space.
    strict : bool
        False: particles without a valid DC-PSE stencil get zero derivatives (so D~ = D0) instead
        of an error; their number is the result's ``degenerate``.
    widen, max_lebesgue : int, float or None
        Repair of such points and of wild stencils (see :class:`arpy.dcpse.domain.DomainDCPSE`).
    reach : float
        The factor on the ball of Eq. 2.9 (see :func:`arpy.self_organize`).
    monitor : {"gradient", "fourth"}
        "gradient": Eq. 2.8 from the DC-PSE gradient (order ``order``).  "fourth": Appendix B's
        Eq. B.13 for m = 4 (:func:`monitor_fourth`) from the fourth derivatives, by DC-PSE of order
        6 (exact on quintics, error O(D^2); :data:`FOURTH_ORDER`) on cores widened to r* D_p with
        the r* of N* = 21 in 2D, 56 in 3D (2D: sqrt(7) instead of sqrt(3)), at most 0.45 of the
        shortest box edge; needs ``order = 4``.
    bc : sequence of Conditions or None, t : float
        Per field, the values of the ghosts at walls at time t (:mod:`arpy.dcpse.boundary`); None: every
        wall homogeneous Neumann.
    reading : {"implicit", "explicit", "pointwise"}
        The reading of Eq. 2.9 (see :func:`graded_resolution`).
    comm, keys, decomposition : optional
        The ranks (default: this process alone), this rank's particles' global keys (default: their
        indices) and the boxes that own them (default: bisected).  Collective.

    Returns
    -------
    SampledResolution
        The new D_p, for :func:`arpy.self_organize` (over the ranks of ``comm``).

    Examples
    --------
    Uniform particles in a periodic box, then a set refined where the sampled field is steep:

    >>> import numpy as np
    >>> import arpy
    >>> box = arpy.Domain([1.0, 1.0], periodic=True)
    >>> def uniform(p):
    ...     return np.full(len(p), 0.08)
    >>> old = arpy.self_organize(np.random.default_rng(0).random((200, 2)), uniform, domain=box, seed=0)
    >>> f = np.exp(-20 * ((old.x - 0.5) ** 2).sum(1))
    >>> target = arpy.field_resolution(old.x, f, old.D, D0=0.08, Dmin=0.03, domain=box)
    >>> D = target(old.x)
    >>> round(float(D.min()), 6), bool(D.max() <= 0.08)
    (0.03, True)
    >>> new = arpy.self_organize(old, target, domain=box, seed=0)
    >>> new.converged, new.n > old.n
    (True, True)
    """
    xs = as_positions(x)
    n, d = xs.shape
    f = np.asarray(f, dtype=np.float64)
    if f.shape[:1] != (n,) or f.ndim not in (1, 2) or not np.all(np.isfinite(f)):
        raise ValueError(f"f must be finite with shape ({n},) or ({n}, k)")
    fields = f.reshape(n, -1)
    bcs = [None] * fields.shape[1] if bc is None else list(bc)
    if len(bcs) != fields.shape[1]:
        raise ValueError(f"bc must give one Conditions (or None) per field: {fields.shape[1]}, got {len(bcs)}")
    check_reach(reach)
    check_monitor(monitor, order)
    domain = as_domain(domain, d)
    comm = comm or SerialComm()
    if keys is None and comm.size > 1:
        raise ValueError("field_resolution on several ranks needs the particles' global keys (keys=)")
    ks = np.arange(n, dtype=np.int64) if keys is None else np.asarray(keys, dtype=np.int64)
    xs, ks, got, dec = owned(comm, domain, xs, ks, decomposition, {"f": fields, "D": np.asarray(D, np.float64)})
    fields, D, n = got["f"], got["D"], xs.shape[0]

    def build(eps: np.ndarray, m: int, operators: list, wild: bool) -> DistributedDCPSE:
        return DistributedDCPSE(comm, dec, xs, eps, ks, domain=domain, order=m, strict=strict, widen=widen,
                                max_lebesgue=max_lebesgue if wild else None, operators=operators, reorder=False)

    op, target = monitor_target(build, fields, D, d=d, D0=D0, Dmin=Dmin, order=order, domain=domain,
                                monitor=monitor, bcs=bcs, t=t)
    rs = r_star(d, n_star_for(order, d))
    # Eq. 2.9 over this rank's particles and those of the other ranks within the ball of their box
    ball = reach * rs
    view = View(Confinement(domain, None), comm, dec)
    xa, ta = view.around(xs, ks, ball * float(target.max(initial=0.0)), target)
    graded, = view.sharing.map("monitor grade", lambda xi, ti, xq, tq: (graded_among(xi, ti, xq, tq, ball, domain,
                                                                                       reading),),
                               (xs, target), xs, lambda: ball * target, (xa, ta))
    field = SampledResolution(xs, graded, rs, domain, comm=comm, keys=ks)
    field.degenerate = comm.sum(int(op.failed.size))
    return field


def monitor_target(build: Callable, fields: np.ndarray, D: np.ndarray, *, d: int, D0: float, Dmin: float | None,
                   order: int, domain: Domain, monitor: str, bcs: list, t: float) -> tuple[Any, np.ndarray]:
    """Steps 4(a)-(b) of §3.2.2: the DC-PSE derivatives of the fields (n, k) at their particles and the
    monitor's D~ there, the finest of the fields'.  ``build(eps, m, operators, wild)`` makes the
    DC-PSE operator set of the particles (one process: :class:`arpy.DomainDCPSE`; ranks:
    :class:`arpy.distributed.DistributedDCPSE`) with core sizes eps, order m, those operators, and
    the repair of wild rows if ``wild``.  Returns (the operator set, D~ (n,))."""
    rs = r_star(d, n_star_for(order, d))
    eps = rs * np.asarray(D, dtype=np.float64)
    if monitor == "gradient":
        grad = gradient_indices(d)
        op = build(eps, order, grad, True)
        mats = op.derivatives(grad)
        return op, _finest([monitor_gradient(np.stack([g @ fe for g in mats], axis=1), D0, Dmin)
                            for fe in _extended(op, fields, bcs, t)])
    m = FOURTH_ORDER
    eps = eps * r_star(d, n_star_for(m, d)) / rs
    if domain.bounded:
        eps = np.minimum(eps, 0.45 * np.min(domain.edge))
    fourth = fourth_multi_indices(d)
    op = build(eps, m, fourth, False)
    mats = op.derivatives(fourth)
    return op, _finest([monitor_fourth(np.stack([mat @ fe for mat in mats], axis=1), D0, Dmin)
                        for fe in _extended(op, fields, bcs, t)])


def _extended(op, fields: np.ndarray, bcs: list, t: float) -> list[np.ndarray]:
    """Each column of fields (n, k) on the operator's sources, with its conditions."""
    return [op.extend(fields[:, j], bcs[j], t) for j in range(fields.shape[1])]


def _finest(targets: list[np.ndarray]) -> np.ndarray:
    """The smallest of several fields' target resolutions, per particle."""
    return targets[0] if len(targets) == 1 else np.minimum.reduce(targets)
