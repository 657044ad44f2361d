"""The space particles live in: free space, or a box whose axes are periodic or bounded by rigid walls.

A :class:`Domain` is built and validated once, at the entry point a user calls, and handed down to
the neighbour lists, the DC-PSE stencils, the self-organization and the simulation.  It knows how to

* ``wrap`` positions across periodic faces and ``confine`` them (wrap, and project onto the walls);
* tell whether points lie inside the walls (``contains``);
* make the ghost particles a boundary needs: periodic ``images`` (for neighbour lists, minimum
  image) and ``mirrors`` across walls (the method of images of §2.4 of Reboux et al. 2012: even
  images give homogeneous Neumann conditions); ``ghosts`` = both, for DC-PSE stencils;
* find nearest particles by the minimum image (:func:`nearest`).
"""

from __future__ import annotations

import functools
import itertools
import math
from typing import Sequence

import numpy as np
import numpy.typing as npt

from . import _bridge
from ._validate import as_cutoffs, as_positions, column_extremes

__all__ = ["Domain", "as_domain", "h_min", "nearest", "periodic_ghosts"]


@functools.lru_cache(maxsize=None)
def _mirror_flips(d: int) -> tuple[np.ndarray, np.ndarray]:
    """The mirror combinations of :meth:`Domain.mirrors`: flips (3**d - 1, d), per axis 0 as is,
    1 across lo, 2 across hi, every combination but none, the first axis slowest; and the bits a
    particle must have for each (bit 2a: near lo along axis a, bit 2a + 1: near hi)."""
    flips = np.array(list(itertools.product((0, 1, 2), repeat=d))[1:])
    req = ((flips == 1) << (2 * np.arange(d))).sum(axis=1) + ((flips == 2) << (2 * np.arange(d) + 1)).sum(axis=1)
    return flips, req.astype(np.int64)


class Domain:
    """Free space, or a box [lo, hi] with periodic or walled axes.

    Parameters
    ----------
    box : None, array (d,) or array (2, d)
        None: free space (any dimension).  Edge lengths L (the box [0, L]), or the
        corners ``(lo, hi)``; finite, hi > lo along every axis; length unit of the positions.
    periodic : bool or sequence of d bools
        Which axes of the box are periodic (True: all).  The other axes end at rigid walls.

    Attributes
    ----------
    d : int or None
        Dimension (None in free space: any).
    lo, hi : arrays (d,) or None
        The box's corners.
    periodic : tuple of d bools
        Periodic axes (empty in free space).

    Examples
    --------
    >>> import numpy as np
    >>> import arpy
    >>> arpy.Domain()
    Domain(free space)
    >>> torus = arpy.Domain([1.0, 1.0], periodic=True)
    >>> torus.all_periodic
    True

    A 2 x 1 box, periodic along x, with walls at y = 0 and y = 1:

    >>> channel = arpy.Domain(([0.0, 0.0], [2.0, 1.0]), periodic=(True, False))
    >>> channel
    Domain(lo=[0.0, 0.0], hi=[2.0, 1.0], axes='pw' (p: periodic, w: walls))
    >>> channel.wrap(np.array([[2.5, 0.5], [-0.25, 0.5]])).tolist()
    [[0.5, 0.5], [1.75, 0.5]]
    >>> channel.contains(np.array([[0.5, 0.5], [0.5, 1.5]])).tolist()
    [True, False]
    """

    d: int | None
    lo: np.ndarray | None
    hi: np.ndarray | None
    periodic: tuple[bool, ...]

    def __init__(self, box: npt.ArrayLike | None = None, *, periodic: bool | Sequence[bool] = False) -> None:
        if box is None:
            if np.any(periodic):
                raise ValueError("a periodic domain needs a box (edge lengths or (lo, hi))")
            self.d, self.lo, self.hi, self.periodic = None, None, None, ()
            return
        arr = np.asarray(box, dtype=np.float64)
        if arr.ndim == 1 and arr.shape[0] in (2, 3):
            lo, hi = np.zeros(arr.shape[0]), arr.copy()
        elif arr.ndim == 2 and arr.shape[0] == 2 and arr.shape[1] in (2, 3):
            lo, hi = arr[0].copy(), arr[1].copy()
        else:
            raise ValueError(f"box must be edge lengths of shape (d,) or (lo, hi) of shape (2, d), d = 2 or 3; "
                             f"got shape {arr.shape}")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi > lo)
                and np.all(np.isfinite(hi - lo))):
            raise ValueError("box must be finite (edges too) with hi > lo along every axis")
        d = lo.size
        flags = np.broadcast_to(np.asarray(periodic), (d,)) if np.ndim(periodic) == 0 else np.asarray(periodic)
        if flags.shape != (d,) or flags.dtype.kind not in "bi":
            raise ValueError(f"periodic must be a bool or {d} bools, got {periodic!r}")
        self.d, self.lo, self.hi, self.periodic = d, lo, hi, tuple(bool(p) for p in flags)

    # ------------------------------------------------------------------ what it is
    @property
    def bounded(self) -> bool:
        """True for a box, False for free space."""
        return self.lo is not None

    @property
    def any_periodic(self) -> bool:
        """Some axis is periodic."""
        return any(self.periodic)

    @property
    def all_periodic(self) -> bool:
        """A box periodic along every axis."""
        return self.bounded and all(self.periodic)

    @property
    def walls(self) -> np.ndarray:
        """Per axis, whether rigid walls bound it (bool (d,); empty in free space)."""
        return ~np.asarray(self.periodic, dtype=bool)

    @property
    def has_walls(self) -> bool:
        """Some axis of the box ends at walls."""
        return bool(self.walls.any())

    @property
    def edge(self) -> np.ndarray:
        """Edge lengths hi - lo, shape (d,)."""
        assert self.lo is not None and self.hi is not None, "free space has no edges"
        return self.hi - self.lo

    @property
    def period(self) -> np.ndarray:
        """Per axis the period (edge length) of a periodic axis, 0 for the others: the core's
        minimum-image convention.  Needs ``d`` (free space: call :meth:`for_dim` first)."""
        return np.where(self.periodic, self.edge, 0.0) if self.bounded else np.zeros(self.d or 0)

    def whole_periods(self, e: np.ndarray) -> np.ndarray:
        """Per row of offsets e (m, d), the multiple of the period nearest to it along each periodic
        axis (0 along the others): ``e - whole_periods(e)`` is the minimum image."""
        per = self.for_dim(e.shape[1]).period
        axes = per > 0
        out = np.zeros_like(e)
        out[:, axes] = per[axes] * np.round(e[:, axes] / per[axes])
        return out

    def image_shifts(self) -> np.ndarray:
        """The shifts of the periodic images, in whole periods: the s in {-1, 0, 1}^d along the
        periodic axes (0 along the others), s = 0 left out, first axis slowest (the order of
        :meth:`images`), int (m, d)."""
        assert self.d is not None, "free space has no periodic images"
        axes = [(-1, 0, 1) if p else (0,) for p in self.periodic]
        grid = np.array(np.meshgrid(*axes, indexing="ij")).reshape(self.d, -1).T
        return grid[np.any(grid != 0, axis=1)]

    def image_ids(self, offsets: np.ndarray) -> np.ndarray:
        """Per row of offsets (m, d) that are whole periods (the shift of a periodic image), its shift's
        place among all of {-1, 0, 1}^d, first axis slowest (the order of :meth:`images`); -1 for no
        shift."""
        g = np.rint(np.asarray(offsets, dtype=np.float64) / np.where(self.period > 0, self.period, 1.0))
        g = np.where(self.period > 0, g, 0).astype(np.int64)
        ids = ((g + 1) * 3 ** np.arange(g.shape[1] - 1, -1, -1)).sum(axis=1)
        return np.where(np.any(g != 0, axis=1), ids, -1)

    def state(self) -> dict:
        """The domain as plain data (JSON-serialisable): ``{"lo", "hi", "periodic"}``, or ``{}`` for
        free space; :meth:`from_state` rebuilds it."""
        if not self.bounded:
            return {}
        assert self.lo is not None and self.hi is not None
        return {"lo": self.lo.tolist(), "hi": self.hi.tolist(), "periodic": [bool(p) for p in self.periodic]}

    @classmethod
    def from_state(cls, state: dict) -> "Domain":
        """The domain of :meth:`state`."""
        if not state:
            return cls()
        return cls([state["lo"], state["hi"]], periodic=tuple(state["periodic"]))

    def __repr__(self) -> str:
        if not self.bounded:
            return "Domain(free space)"
        assert self.lo is not None and self.hi is not None
        axes = "".join("p" if p else "w" for p in self.periodic)
        return f"Domain(lo={self.lo.tolist()}, hi={self.hi.tolist()}, axes={axes!r} (p: periodic, w: walls))"

    def for_dim(self, d: int) -> "Domain":
        """This domain for particles in d dimensions: checks a box's dimension; free space gets d."""
        if self.bounded:
            if d != self.d:
                raise ValueError(f"the domain is {self.d}-dimensional but the particles are {d}-dimensional")
            return self
        free = Domain()
        free.d = int(d)
        return free

    def scaled(self, k: int) -> "Domain":
        """The same domain with lengths times 2**k (exact)."""
        if not self.bounded or k == 0:
            return self
        assert self.lo is not None and self.hi is not None
        out = Domain(np.stack([np.ldexp(self.lo, k), np.ldexp(self.hi, k)]), periodic=self.periodic)
        return out

    # ------------------------------------------------------------------ positions
    def wrap(self, x: np.ndarray) -> np.ndarray:
        """Positions (m, d) mapped into [lo, hi) along the periodic axes: lo + (x - lo) mod (hi - lo)
        for the coordinates outside [lo, hi); a coordinate inside keeps its bits (the formula would
        round it when lo != 0), so wrapping twice, or wrapping a position that stayed inside, changes
        nothing."""
        if not self.any_periodic:
            return x
        assert self.lo is not None and self.hi is not None
        xs = np.array(x, dtype=np.float64)
        for a in np.flatnonzero(self.periodic):         # (the modulo, slow in NumPy, only where needed)
            col = xs[:, a]
            out = np.flatnonzero((col < self.lo[a]) | (col >= self.hi[a]))
            if out.size:
                col[out] = self.lo[a] + np.mod(col[out] - self.lo[a], self.hi[a] - self.lo[a])
        return xs

    def contains(self, x: np.ndarray) -> np.ndarray:
        """Whether each point (m, d) lies within the walls ([lo, hi] along the walled axes), (m,) bool."""
        if not self.has_walls:
            return np.ones(x.shape[0], bool)
        assert self.lo is not None and self.hi is not None
        w = self.walls
        return np.all((x[:, w] >= self.lo[w]) & (x[:, w] <= self.hi[w]), axis=1)

    def confine(self, x: np.ndarray) -> np.ndarray:
        """Positions wrapped across periodic faces and projected onto the walls."""
        if not self.bounded:
            return x
        if not self.has_walls:
            return self.wrap(x)
        assert self.lo is not None and self.hi is not None
        if not self.any_periodic:
            return np.clip(x, self.lo, self.hi)
        w = self.walls
        return self.wrap(np.where(w, np.clip(x, self.lo, self.hi), x))

    def reflect(self, x: np.ndarray) -> np.ndarray:
        """Positions mirrored at the walls they crossed, then confined (for inserted particles)."""
        if self.has_walls:
            assert self.lo is not None and self.hi is not None
            lo, hi = np.where(self.walls, self.lo, -np.inf), np.where(self.walls, self.hi, np.inf)
            x = np.where(x < lo, 2 * lo - x, x)
            x = np.where(x > hi, 2 * hi - x, x)
        return self.confine(x)

    def beyond_walls(self, x: np.ndarray) -> np.ndarray:
        """Per point (m, d) and axis, whether it lies beyond a wall (below lo or above hi along a
        walled axis), bool (m, d): the axes a mirror image was reflected across."""
        assert self.lo is not None and self.hi is not None, "free space has no walls"
        return self.walls & ((x < self.lo) | (x > self.hi))

    def box_coordinates(self, x: np.ndarray) -> np.ndarray:
        """Coordinates relative to lo, inside [0, hi - lo) along the periodic axes (as scipy's
        cKDTree with ``boxsize = period`` requires; walled axes as they are)."""
        assert self.lo is not None, "free space has no box coordinates"
        if self.all_periodic:
            return np.minimum(np.mod(x - self.lo, self.edge), np.nextafter(self.edge, 0))
        out = x - self.lo
        p = np.asarray(self.periodic)
        out[:, p] = np.minimum(np.mod(out[:, p], self.edge[p]), np.nextafter(self.edge[p], 0))
        return out

    # ------------------------------------------------------------------ ghosts
    def images(self, x: np.ndarray, rc: float | np.ndarray, skin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Periodic ghost copies of the particles near the periodic faces (see :func:`periodic_ghosts`)."""
        xs = as_positions(x)
        r = self.image_reach(xs, rc, skin)
        if xs.shape[0] == 0 or not self.any_periodic:
            return np.zeros((0, xs.shape[1])), np.zeros(0, np.int64)
        assert self.lo is not None and self.hi is not None
        # the core: shifts s in {-1, 0, 1}^d (first axis slowest), a particle imaged by s if it lies
        # within r of the low face along every +1 axis (to the high side) and of the high face along
        # every -1 axis; images by shift, then by particle
        m = _bridge.images_count(xs, r, self.lo, self.hi, self.periodic)
        xg, src = _bridge.images(xs, r, self.lo, self.hi, self.periodic, m, context="periodic_ghosts")
        return xg, src.astype(np.int64)

    def image_reach(self, x: np.ndarray, rc: float | np.ndarray, skin: float = 0.0) -> np.ndarray:
        """The reach rc + skin of each particle's periodic images, shape (n,), after
        :meth:`check_images`."""
        xs = as_positions(x)
        rcs = as_cutoffs(rc, xs.shape[0])
        skin = self.check_images(xs, rcs, skin)
        return rcs + skin

    def check_images(self, x: np.ndarray, rc: np.ndarray, skin: float = 0.0,
                     extremes: tuple[np.ndarray, np.ndarray, float, float] | None = None,
                     rule: str = "min") -> float:
        """Check that the particles x (n, d) lie in the box along its periodic axes and that the
        largest reach of a pair under the cutoff ``rule`` (rc (n,): max(rc) + skin; the sum rule:
        2 max(rc) + skin) is below half the smallest periodic edge (so that each pair has at most
        one image within reach); returns the skin as a float.  ``extremes``: the caller's (per-axis
        least and largest positions, least and largest cutoff), if it has them."""
        xs = as_positions(x)
        n, d = xs.shape
        self.for_dim(d)
        skin = float(skin)
        if not (np.isfinite(skin) and skin >= 0.0):
            raise ValueError(f"periodic_ghosts: skin must be a finite number >= 0, got {skin}")
        if n == 0 or not self.any_periodic:
            return skin
        # per-axis extremes (NaN propagates into them): no temporaries of the particles' size; the
        # least and largest reach are those of rc plus the skin (rounding keeps the order)
        if extremes is None:
            extremes = (*column_extremes(xs), float(rc.min()), float(rc.max()))
        x_min, x_max = extremes[0], extremes[1]
        r_min, r_max = extremes[2] + skin, (2.0 if rule == "sum" else 1.0) * extremes[3] + skin
        if not (np.all(np.isfinite(x_min)) and np.all(np.isfinite(x_max)) and np.isfinite(r_max) and r_min > 0):
            raise ValueError("positions and cutoffs must be finite, cutoffs > 0")
        p = np.asarray(self.periodic)
        lo, hi = self.lo, self.hi
        assert lo is not None and hi is not None
        if np.any(((x_min < lo) | (x_max > hi)) & p):
            outside = np.any(((xs < lo) | (xs > hi))[:, p], axis=1)
            i = int(np.flatnonzero(outside)[0])
            raise ValueError(f"particle {i} at {xs[i]} lies outside the periodic box [{lo}, {hi}]")
        length = hi - lo
        if r_max >= 0.5 * length[p].min():
            largest = "twice the largest cutoff + skin (sum rule)" if rule == "sum" else "the largest cutoff + skin"
            raise ValueError(f"periodic box too small: {largest} ({r_max:g}) must be "
                             f"below half the smallest periodic edge ({0.5 * length[p].min():g})")
        return skin

    def mirrors(self, x: np.ndarray, rc: np.ndarray, faces: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Mirror images of the particles across the walls (method of images, §2.4).

        A particle within the walls, closer than its cutoff rc to a wall (but not on it), is
        mirrored across it (across two or three walls near edges and corners).  ``faces``: bool
        (d, 2), the walls (lo, hi per axis) that mirror (default: all).  Returns ``(x_image,
        source)`` like :meth:`images`; none without walls."""
        n, d = x.shape
        if not self.has_walls:
            return np.zeros((0, d)), np.zeros(0, np.int64)
        lo, hi, w = self.lo, self.hi, self.walls
        assert lo is not None and hi is not None
        mirror = np.stack([w, w], axis=1) if faces is None else np.asarray(faces, dtype=bool) & w[:, None]
        rc = np.broadcast_to(np.asarray(rc, dtype=np.float64), (n,))
        inside = self.contains(x)
        # bits 2a and 2a + 1: near the lo and the hi wall along axis a (within rc, inside the walls;
        # a particle on a wall is its own image there: not mirrored across it)
        bits = np.zeros(n, np.int64)
        for a in range(d):
            xa = x[:, a]
            if mirror[a, 0]:
                bits |= (inside & (xa - lo[a] <= rc) & (xa > lo[a])).astype(np.int64) << (2 * a)
            if mirror[a, 1]:
                bits |= (inside & (hi[a] - xa <= rc) & (xa < hi[a])).astype(np.int64) << (2 * a + 1)
        cand = np.flatnonzero(bits)
        if cand.size == 0:
            return np.zeros((0, d)), np.zeros(0, np.int64)
        flips, req = _mirror_flips(d)
        need = (bits[cand][None, :] & req[:, None]) == req[:, None]     # (combination, candidate)
        comb, k = np.nonzero(need)              # images by combination, then by particle
        src, f, img = cand[k], flips[comb], x[cand[k]]
        img = np.where(f == 1, 2 * lo - img, np.where(f == 2, 2 * hi - img, img))
        return img, src.astype(np.int64)

    def ghosts(self, x: np.ndarray, rc: np.ndarray, faces: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The ghosts a stencil near the boundary reads: periodic images, then the mirror images
        of the particles and of those images across the walls (``faces``: which, see
        :meth:`mirrors`).  Returns ``(x_ghost, source)``."""
        xg, src = self.images(x, rc) if self.any_periodic else (np.zeros((0, x.shape[1])), np.zeros(0, np.int64))
        if not self.has_walls:
            return xg, src
        if src.size == 0:
            return self.mirrors(x, rc, faces)
        rc = np.broadcast_to(np.asarray(rc, dtype=np.float64), (x.shape[0],))
        every, owner = np.concatenate([x, xg]), np.concatenate([np.arange(x.shape[0]), src])
        xm, k = self.mirrors(every, rc[owner], faces)
        return np.concatenate([xg, xm]), np.concatenate([src, owner[k]])


def as_domain(domain: object, d: int | None = None, *, optional: bool = True, name: str = "domain") -> Domain:
    """Where particles live, as a public function's argument ``name`` gives it: a :class:`Domain`, or
    None for free space if ``optional``; for particles in ``d`` dimensions if d is given (a box must
    have d axes, free space gets d).  The one check of a user's domain, at the door; TypeError for
    anything else (a list of edge lengths, say)."""
    if domain is None and optional:
        domain = Domain()
    if not isinstance(domain, Domain):
        free = " or None (free space)" if optional else ""
        raise TypeError(f"{name} must be an arpy.Domain (e.g. arpy.Domain([1, 1])){free}, got {type(domain).__name__}")
    return domain if d is None else domain.for_dim(d)


def periodic_ghosts(x: np.ndarray, rc: float | np.ndarray, domain: Domain, skin: float = 0.0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Ghost copies of particles near the faces of a periodic box.

    A particle is imaged across a face only if it lies within its own cutoff (plus skin) of that
    face: under the min rule a pair across the boundary needs both particles that close to it.
    Corners and edges get the combined images.

    Parameters
    ----------
    x : array (n, d)
        Positions inside the box along its periodic axes.
    rc : float or array (n,)
        Cutoff radii; ``max(rc) + skin`` must be below half the smallest periodic edge (so that
        each pair has at most one image within reach).
    domain : Domain
        The box; only its periodic axes are imaged.
    skin : float
        Verlet skin added to every cutoff.

    Returns
    -------
    x_ghost : array (m, d)
        Ghost positions (outside the box, within reach of it).
    source : int64 array (m,)
        Index of the real particle each ghost copies.
    """
    return as_domain(domain, optional=False).images(x, rc, skin)


def _core_coordinates(arrays: tuple[np.ndarray, ...], domain: Domain | None
                      ) -> tuple[tuple[np.ndarray, ...], np.ndarray, int]:
    """Point sets (each (m, d)) as the core's distance searches take them: in box coordinates
    ([0, period) along periodic axes) and, where the largest ``|coordinate|`` lies outside
    [2**-400, 2**400], scaled by a power of two 2**e (exact) that puts it near 1, so that squared
    distances neither overflow nor underflow (inside that window the squared spacing of distinct
    doubles, >= (2**-452)**2, stays normal).  Returns (the sets, the periods (d,), e)."""
    dom = domain if domain is not None and domain.any_periodic else None
    box: tuple[np.ndarray, ...] = ()
    if dom is not None:
        assert dom.lo is not None and dom.hi is not None      # periodic: a box
        box = (dom.lo, dom.hi)
    bounds = [float(f(v)) for v in arrays + box if v.size for f in (np.min, np.max)]
    if not all(math.isfinite(b) for b in bounds):
        raise ValueError("positions must be finite (no NaN or Inf)")
    top = max(map(abs, bounds), default=0.0)
    e = 0
    if top > 0 and not -400 <= math.frexp(top)[1] <= 400:
        e = -math.frexp(top)[1]
        arrays = tuple(np.ldexp(v, e) for v in arrays)
        dom = None if dom is None else dom.scaled(e)
    d = arrays[0].shape[1]
    if dom is None:
        return arrays, np.zeros(d), e
    return tuple(dom.box_coordinates(v) for v in arrays), dom.period, e


def nearest(x: np.ndarray, k: int = 1, *, y: np.ndarray | None = None, domain: Domain | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest neighbours by the minimum image along the periodic axes of ``domain``: distances
    and indices into x, as scipy's ``cKDTree.query`` returns them.

    Parameters
    ----------
    x : array (n, d)
        The points searched (length).
    k : int >= 1
        How many neighbours.
    y : array (m, d), optional
        Query points: for each, the k points of x nearest to it (``cKDTree(x).query(y, k)``).  None:
        the k nearest *other* points of every point of x (m = n; the point itself is left out by its
        index, so a coincident point is a neighbour at distance 0).
    domain : Domain, optional
        Periodic axes: the minimum image (default: free space).

    Returns
    -------
    dist : float64 array, (m,) for k = 1, else (m, k)
        Nearest first by squared distance, equal ones by index; beyond the points there are, distance
        inf and index n.  The distances are those cKDTree computes (the same sums, bit for bit).
    idx : int64 array, same shape

    The search runs in the core, on its threads.

    Examples
    --------
    >>> import numpy as np, arpy
    >>> x = np.array([[0.05, 0.5], [0.5, 0.5], [0.9, 0.5]])
    >>> dist, idx = arpy.nearest(x, domain=arpy.Domain([1.0, 1.0], periodic=True))
    >>> dist.round(12).tolist(), idx.tolist()
    ([0.15, 0.4, 0.15], [2, 2, 0])
    """
    x = np.asarray(x, dtype=np.float64)
    own = y is None
    y = x if own else np.asarray(y, dtype=np.float64)
    if x.ndim != 2 or y.ndim != 2 or (y.shape[1] != x.shape[1] and y.shape[0]):
        raise ValueError(f"nearest: needs points x (n, d) and y (m, d), got shapes {x.shape} and {y.shape}")
    domain = as_domain(domain, x.shape[1])
    k = int(k)
    if k < 1:
        raise ValueError(f"nearest: k must be >= 1, got {k}")
    n, m = x.shape[0], y.shape[0]
    want = k + 1 if own else k                       # (each point itself among them)
    found = min(want, n)
    dist, idx = np.full((m, want), np.inf), np.full((m, want), n, dtype=np.int64)
    sets, period, e = _core_coordinates((x,) if own else (x, y), domain)
    xc, yc = sets[0], sets[-1]
    if found and m:
        dk, ik = _bridge.knn(xc, yc, found, period, context="nearest")
        dist[:, :found], idx[:, :found] = (np.ldexp(dk, -e) if e else dk), ik
    if own:
        # leave each point itself out (by index; the last column where it is not among them)
        drop = idx == np.arange(m)[:, None]
        drop[~drop.any(axis=1), -1] = True
        dist, idx = dist[~drop].reshape(m, k), idx[~drop].reshape(m, k)
    return (dist[:, 0], idx[:, 0]) if k == 1 else (dist, idx)


def h_min(x: np.ndarray, domain: Domain | None = None) -> float:
    """The smallest distance between two particles (minimum image along periodic axes): the least
    distance to a nearest other particle of :func:`nearest`, found by the core's pair scan."""
    x = np.asarray(x, dtype=np.float64)
    domain = as_domain(domain)
    if x.shape[0] < 2:
        return np.inf
    (xc,), period, e = _core_coordinates((x,), domain)
    dmin = _bridge.min_distance(xc, period, context="h_min")
    return math.ldexp(dmin, -e) if e else dmin
