"""Boundary conditions of a field on the walls of a box.

Every field of a simulation shares its DC-PSE sources with the fields that have the same Dirichlet
faces, so one assembly of the operators serves all of them:

* :class:`Neumann` with ``flux`` q (the outward normal derivative; q = 0, the default at every
  wall, is §2.4's homogeneous condition): the operators read mirror images of the particles
  across the wall (:meth:`arpy.Domain.ghosts`).  The image of a particle at distance s from the
  wall carries ``f_p + 2 s q``; Taylor expansion about the wall point w between them gives
  ``f(image) - f_p = 2 s f_n(w) + s^3/3 f_nnn(w) + ...``, so the image is exact to O(s^3).
* :class:`Dirichlet` with ``value`` g: no images across the wall.  Instead the wall carries
  boundary particles with the values g (:meth:`Conditions.wall_points`: the projections of the
  particles within half their core size of it), and the stencils of points within their core
  size of the wall are one-sided, over every source within ``2^(1/d)`` times that core size, so
  that the half ball holds about as many sources as a full one (see
  :class:`arpy.dcpse.domain.DomainDCPSE`).  Such stencils are consistent to the operators' order.
  Odd images (``2 g - f_p``, exact to O(s^2) only) serve where a field is read through mirror
  images anyway, e.g. the gradient of the resolution monitor.

Near an edge or a corner an image lies across two or three walls; the rules are applied one wall
after the other in axis order, each at the wall point between the image so far and its
reflection.  Periodic images carry the particle's value.  A field's conditions are given per face
by :func:`conditions`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping, Union

import numpy as np

from ..domain import Domain

__all__ = ["Conditions", "Dirichlet", "Neumann", "conditions", "face_names"]

#: A value on a wall: a number, or ``(x (m, d) wall points, t) -> (m,)``.
WallValue = Union[float, Callable[[np.ndarray, float], np.ndarray]]


def _wall_value(v: WallValue, w: np.ndarray, t: float, what: str) -> np.ndarray:
    """A wall value at wall points w (m, d) at time t, checked."""
    if not callable(v):
        return np.full(w.shape[0], float(v))
    out = np.asarray(v(w, t), dtype=np.float64)
    if out.shape != (w.shape[0],) or not np.all(np.isfinite(out)):
        raise ValueError(f"the {what} must give finite values of shape ({w.shape[0]},), got {out.shape}")
    return out


def _check_wall_value(v: WallValue, what: str) -> None:
    """A wall value is a callable or a finite real number (ValueError naming ``what`` otherwise)."""
    if callable(v):
        return
    try:
        ok = bool(np.isfinite(float(v)))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"the {what} must be a finite number or a callable (x, t) -> values, got {v!r}")


@dataclass(frozen=True)
class Dirichlet:
    """f = value on the wall; ``value``: a number or ``(x (m, d), t) -> (m,)`` at wall points."""

    value: WallValue = 0.0

    def __post_init__(self) -> None:
        _check_wall_value(self.value, "Dirichlet value")

    #: A Dirichlet wall's images do not carry their particle's value.
    homogeneous = False

    def at(self, w: np.ndarray, t: float) -> np.ndarray:
        """The value at wall points w (m, d) at time t, (m,)."""
        return _wall_value(self.value, w, t, "Dirichlet value")

    def image(self, v: np.ndarray, w: np.ndarray, s: np.ndarray, t: float) -> np.ndarray:
        """The odd image ``2 g(w) - v`` of a point with value v at distance s from the wall point w."""
        return 2.0 * self.at(w, t) - v


@dataclass(frozen=True)
class Neumann:
    """df/dn = flux on the wall (n the outward normal, flux in f per length); ``flux``: a number
    or ``(x (m, d), t) -> (m,)`` at wall points."""

    flux: WallValue = 0.0

    def __post_init__(self) -> None:
        _check_wall_value(self.flux, "Neumann flux")

    @property
    def homogeneous(self) -> bool:
        """flux = 0: the image carries its particle's value."""
        return not callable(self.flux) and float(self.flux) == 0.0

    def image(self, v: np.ndarray, w: np.ndarray, s: np.ndarray, t: float) -> np.ndarray:
        """The value of the image, at distance s beyond the wall point w, of a point with value v."""
        if self.homogeneous:
            return v
        return v + 2.0 * s * _wall_value(self.flux, w, t, "Neumann flux")


Condition = Union[Dirichlet, Neumann]


def face_names(d: int) -> tuple[str, ...]:
    """The faces of a box in d dimensions: ``("x-", "x+", "y-", "y+"[, "z-", "z+"])``."""
    return tuple(f"{a}{s}" for a in "xyz"[:d] for s in "-+")


class Conditions:
    """A field's condition on each face of a domain (see :func:`conditions`).

    ``faces[2 a]`` is the face lo along axis a, ``faces[2 a + 1]`` the face hi; periodic axes have
    None.  :meth:`ghost_values` gives the values of the ghosts of a DC-PSE operator."""

    def __init__(self, domain: Domain, faces: tuple[Condition | None, ...]) -> None:
        self.domain, self.faces = domain, faces

    @property
    def homogeneous(self) -> bool:
        """Every wall homogeneous Neumann: ghosts carry their particle's value."""
        return all(c is None or c.homogeneous for c in self.faces)

    def __repr__(self) -> str:
        named = [f"{n}: {c!r}" for n, c in zip(face_names(len(self.faces) // 2), self.faces) if c is not None]
        return f"Conditions({', '.join(named) or 'periodic'})"

    @property
    def dirichlet_faces(self) -> np.ndarray:
        """bool (d, 2): the Dirichlet faces, (lo, hi) per axis."""
        return np.array([isinstance(c, Dirichlet) for c in self.faces], dtype=bool).reshape(-1, 2)

    @property
    def has_dirichlet(self) -> bool:
        return any(isinstance(c, Dirichlet) for c in self.faces)

    def _dirichlet(self):
        """(face index, axis, wall coordinate, condition) of each Dirichlet face."""
        dom = self.domain
        for k, c in enumerate(self.faces):
            if isinstance(c, Dirichlet):
                assert dom.lo is not None and dom.hi is not None
                yield k, k // 2, (dom.hi if k % 2 else dom.lo)[k // 2], c

    def wall_gap(self, x: np.ndarray) -> np.ndarray:
        """Per point of x (n, d), the distance to the nearest Dirichlet face (inf without one)."""
        gap = np.full(x.shape[0], np.inf)
        for _, a, wall, _ in self._dirichlet():
            gap = np.minimum(gap, np.abs(x[:, a] - wall))
        return gap

    def projections(self, x: np.ndarray, eps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The projection onto each Dirichlet face of every point of x (n, d; core sizes eps (n,)) within
        the walls lying within eps/2 of that face but not on it, by face, then point: (positions (m, d),
        the point of each, its face index 2 a + side).  Along periodic axes the points may lie anywhere
        (a periodic image projects onto the image of its particle's projection)."""
        inside = self.domain.contains(x)
        pts, src, face = [], [], []
        for k, a, wall, _ in self._dirichlet():
            s = np.abs(x[:, a] - wall)
            rows = np.flatnonzero(inside & (s > 0) & (s <= 0.5 * eps))
            w = x[rows].copy()
            w[:, a] = wall
            pts.append(w)
            src.append(rows)
            face.append(np.full(rows.size, k))
        if not pts:
            return np.zeros((0, x.shape[1])), np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate(pts), np.concatenate(src).astype(np.int64), np.concatenate(face).astype(np.int64)

    def wall_points(self, x: np.ndarray, eps: np.ndarray, keys: np.ndarray | None = None,
                    group: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Boundary particles on the Dirichlet faces: the projection of every particle (x (n, d) in
        the box, core sizes eps) lying within eps/2 of such a face but not on it (a particle on a
        face is a boundary particle itself), one per position and none on a particle.  Returns
        (positions (m, d), the particle of each, its face index 2 a + side), by face, then particle
        (with ``keys``: then key).

        Of projections at one position the first by (face, particle) stays; with ``keys`` (int (n,)) the
        first by (face, key), so that the boundary particles do not depend on how the particles are
        numbered.  ``group`` (int (n,)): only points of one group coincide (e.g. the periodic images of
        one shift; default: all one group)."""
        w, src, face = self.projections(x, eps)
        if src.size == 0:
            return w, src, face
        order = np.arange(src.size) if keys is None else np.lexsort((np.asarray(keys)[src], face))
        # near edges and corners projections can coincide with each other or with a particle on a
        # face (only those: every projection lies on a face)
        on = np.flatnonzero(self.wall_gap(x) == 0)
        every = np.concatenate([x[on], w[order]])
        if group is not None:
            every = np.column_stack([np.concatenate([group[on], group[src[order]]]).astype(np.float64), every])
        _, first = np.unique(every, axis=0, return_index=True)
        keep = order[np.sort(first[first >= on.size]) - on.size]
        return w[keep], src[keep], face[keep]

    def wall_values(self, w: np.ndarray, face: np.ndarray, t: float) -> np.ndarray:
        """The Dirichlet values at wall points w (m, d) on the faces ``face`` (m,) at time t."""
        out = np.zeros(w.shape[0])
        for k in np.unique(face):
            cond = self.faces[int(k)]
            if not isinstance(cond, Dirichlet):
                raise ValueError(f"face {face_names(len(self.faces) // 2)[int(k)]!r} is not a Dirichlet face")
            rows = np.flatnonzero(face == k)
            out[rows] = cond.at(w[rows], t)
        return out

    def on_walls(self, x: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(indices, values): the points of x (n, d) on a Dirichlet face and its value there (the
        first such face in axis order)."""
        taken = np.zeros(x.shape[0], dtype=bool)
        idx, vals = [], []
        for _, a, wall, cond in self._dirichlet():
            rows = np.flatnonzero(~taken & (x[:, a] == wall))
            taken[rows] = True
            idx.append(rows)
            vals.append(cond.at(x[rows], t))
        if not idx:
            return np.zeros(0, np.int64), np.zeros(0)
        return np.concatenate(idx), np.concatenate(vals)

    def snap(self, x: np.ndarray, eps: np.ndarray, fraction: float) -> np.ndarray:
        """x (n, d) with every point closer than ``fraction`` times its eps to a Dirichlet face (in
        the box) moved onto that face."""
        out = x
        inside = self.domain.contains(x)
        for _, a, wall, _ in self._dirichlet():
            s = np.abs(x[:, a] - wall)
            rows = np.flatnonzero(inside & (s > 0) & (s < fraction * eps))
            if rows.size:
                out = x.copy() if out is x else out
                out[rows, a] = wall
        return out

    def ghost_values(self, f: np.ndarray, x: np.ndarray, src: np.ndarray, xg: np.ndarray, t: float,
                     start: np.ndarray | None = None) -> np.ndarray:
        """Values at ghosts xg (m, d), images of the particles x[src] (x (n, d), values f (n,)), at time t;
        ``start`` (m,): each ghost's value before its reflections (default: its particle's)."""
        v = f[src] if start is None else start
        if self.homogeneous or src.size == 0:
            return v
        dom = self.domain
        assert dom.lo is not None and dom.hi is not None
        y = xg.copy()
        walls = np.flatnonzero(dom.walls)
        y[:, walls] = x[src][:, walls]           # the image before its reflections (periodic shifts kept)
        for a in walls:
            for side, wall, beyond in ((0, dom.lo[a], xg[:, a] < dom.lo[a]), (1, dom.hi[a], xg[:, a] > dom.hi[a])):
                rows = np.flatnonzero(beyond)
                cond = self.faces[2 * a + side]
                if rows.size == 0 or cond is None:
                    continue
                w = y[rows].copy()
                w[:, a] = wall
                v[rows] = cond.image(v[rows], w, np.abs(y[rows, a] - wall), t)
                y[rows, a] = 2 * wall - y[rows, a]
        return v


def conditions(spec: Condition | Mapping[str, Condition] | None, domain: Domain) -> Conditions:
    """A field's boundary conditions in a domain.

    Parameters
    ----------
    spec : Dirichlet, Neumann, mapping or None
        One condition for every wall; or a mapping from face names (``"x-"``, ``"x+"``, ``"y-"``, ...,
        see :func:`face_names`) to conditions, the faces not named homogeneous Neumann; None: every
        wall homogeneous Neumann.
    domain : Domain
        A box (free space has no walls: only None is accepted there).

    Raises
    ------
    ValueError
        For an unknown face, a condition on a periodic face or on a box without walls (free space, or
        periodic along every axis), or something that is not a condition.
    """
    if not domain.bounded:
        if spec is not None:
            raise ValueError("boundary conditions need a box with walls; the domain is free space")
        return Conditions(domain, ())
    names = face_names(int(domain.d or 0))
    walls = domain.walls
    if spec is None:
        given: dict = {}
    elif isinstance(spec, (Dirichlet, Neumann)):
        if not walls.any():
            raise ValueError(f"boundary condition {spec!r}: the box is periodic along every axis ({domain!r}), it has "
                             "no walls: give no condition, or a Domain with walls (periodic=False along some axis)")
        given = {n: spec for k, n in enumerate(names) if walls[k // 2]}
    elif isinstance(spec, Mapping):
        given = dict(spec)
    else:
        raise ValueError(f"a boundary condition is an arpy.dcpse.boundary.Dirichlet, Neumann or a mapping of faces to them, "
                         f"got {spec!r}")
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise ValueError(f"unknown faces {unknown}; the faces of this box are {list(names)}")
    faces: list[Condition | None] = []
    for k, n in enumerate(names):
        c = given.get(n)
        if not walls[k // 2]:
            if c is not None:
                raise ValueError(f"face {n!r} is periodic: it takes no boundary condition")
            faces.append(None)
            continue
        if c is not None and not isinstance(c, (Dirichlet, Neumann)):
            raise ValueError(f"face {n!r}: a condition is an arpy.dcpse.boundary.Dirichlet or Neumann, got {c!r}")
        faces.append(c if c is not None else Neumann())
    return Conditions(domain, tuple(faces))
