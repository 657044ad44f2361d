"""Boundary conditions of a field on the walls of a box: the values its mirror images carry.

DC-PSE operators near a wall read mirror images of the particles across it (the ghosts of
:meth:`arpy.Domain.ghosts`, §2.4).  The values the images carry set the condition, so every field
of a simulation shares one set of sources and one assembly of its operators, whatever its
conditions.  :class:`Neumann` with ``flux`` q (the outward normal derivative): the image of a
particle at distance s from the wall carries ``f_p + 2 s q``.  Taylor expansion about the wall
point w between them gives ``f(image) - f_p = 2 s f_n(w) + s^3/3 f_nnn(w) + ...``, so the image is
exact to O(s^3); q = 0 is the plain mirror (even image), the default at every wall.

Near an edge or a corner an image lies across two or three walls; the rules are applied one wall
after the other in axis order, each at the wall point between the image so far and its
reflection.  Periodic images carry the particle's value.  A field's conditions are given per face
by :func:`conditions`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping, Union

import numpy as np

from .domain import Domain

__all__ = ["Conditions", "Neumann", "conditions", "face_names"]

#: A value on a wall: a number, or ``(x (m, d) wall points, t) -> (m,)``.
WallValue = Union[float, Callable[[np.ndarray, float], np.ndarray]]


@dataclass(frozen=True)
class Neumann:
    """df/dn = flux on the wall (n the outward normal, flux in f per length); ``flux``: a number
    or ``(x (m, d), t) -> (m,)`` at wall points."""

    flux: WallValue = 0.0

    def __post_init__(self) -> None:
        if not callable(self.flux) and not np.isfinite(float(self.flux)):
            raise ValueError(f"the Neumann flux must be finite or a callable (x, t) -> values, got {self.flux!r}")

    @property
    def homogeneous(self) -> bool:
        """flux = 0: the image carries its particle's value."""
        return not callable(self.flux) and float(self.flux) == 0.0

    def image(self, v: np.ndarray, w: np.ndarray, s: np.ndarray, t: float) -> np.ndarray:
        """The value of the image, at distance s beyond the wall point w, of a point with value v."""
        if self.homogeneous:
            return v
        if not callable(self.flux):
            return v + 2.0 * s * float(self.flux)
        q = np.asarray(self.flux(w, t), dtype=np.float64)
        if q.shape != (w.shape[0],) or not np.all(np.isfinite(q)):
            raise ValueError(f"the Neumann flux must give finite values of shape ({w.shape[0]},), got {q.shape}")
        return v + 2.0 * s * q


def face_names(d: int) -> tuple[str, ...]:
    """The faces of a box in d dimensions: ``("x-", "x+", "y-", "y+"[, "z-", "z+"])``."""
    return tuple(f"{a}{s}" for a in "xyz"[:d] for s in "-+")


class Conditions:
    """A field's condition on each face of a domain (see :func:`conditions`).

    ``faces[2 a]`` is the face lo along axis a, ``faces[2 a + 1]`` the face hi; periodic axes have
    None.  :meth:`ghost_values` gives the values of the ghosts of a DC-PSE operator."""

    def __init__(self, domain: Domain, faces: tuple[Neumann | None, ...]) -> None:
        self.domain, self.faces = domain, faces

    @property
    def homogeneous(self) -> bool:
        """Every wall homogeneous Neumann: ghosts carry their particle's value."""
        return all(c is None or c.homogeneous for c in self.faces)

    def __repr__(self) -> str:
        named = [f"{n}: {c!r}" for n, c in zip(face_names(len(self.faces) // 2), self.faces) if c is not None]
        return f"Conditions({', '.join(named) or 'periodic'})"

    def ghost_values(self, f: np.ndarray, x: np.ndarray, src: np.ndarray, xg: np.ndarray, t: float) -> np.ndarray:
        """Values at ghosts xg (m, d), images of the particles x[src] (x (n, d), values f (n,)), at time t."""
        v = f[src]
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


def conditions(spec: Neumann | Mapping[str, Neumann] | None, domain: Domain) -> Conditions:
    """A field's boundary conditions in a domain.

    Parameters
    ----------
    spec : Neumann, mapping or None
        One condition for every wall; or a mapping from face names (``"x-"``, ``"x+"``, ``"y-"``, ...,
        see :func:`face_names`) to conditions, the faces not named homogeneous Neumann; None: every
        wall homogeneous Neumann.
    domain : Domain
        A box (free space has no walls: only None is accepted there).

    Raises
    ------
    ValueError
        For an unknown face, a condition on a periodic face, or something that is not a condition.
    """
    if not domain.bounded:
        if spec is not None:
            raise ValueError("boundary conditions need a box with walls; the domain is free space")
        return Conditions(domain, ())
    names = face_names(int(domain.d or 0))
    walls = domain.walls
    if spec is None:
        given: dict = {}
    elif isinstance(spec, Neumann):
        given = {n: spec for k, n in enumerate(names) if walls[k // 2]}
    elif isinstance(spec, Mapping):
        given = dict(spec)
    else:
        raise ValueError(f"a boundary condition is an arpy.boundary.Neumann or a mapping of faces to them, "
                         f"got {spec!r}")
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise ValueError(f"unknown faces {unknown}; the faces of this box are {list(names)}")
    faces: list[Neumann | None] = []
    for k, n in enumerate(names):
        c = given.get(n)
        if not walls[k // 2]:
            if c is not None:
                raise ValueError(f"face {n!r} is periodic: it takes no boundary condition")
            faces.append(None)
            continue
        if c is not None and not isinstance(c, Neumann):
            raise ValueError(f"face {n!r}: a condition is an arpy.boundary.Neumann, got {c!r}")
        faces.append(c if c is not None else Neumann())
    return Conditions(domain, tuple(faces))
