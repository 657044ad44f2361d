"""The budding-cell surface: a surface of revolution made of three circular arcs.

Reboux et al. (2012), §4.6, and Awile et al. (2012), §3.2: a large sphere
(radius ``R``, centre on the z axis at z = 0), a small bud (radius ``r``,
centre at z = ``L``) and a concave neck arc of radius ``r_neck`` tangent to
both.  In the meridian half-plane (z, rho), rho = sqrt(x^2 + y^2) >= 0, the
neck circle's centre c_n = (z_n, rho_n) lies at distance R + r_neck from the
sphere's centre and r + r_neck from the bud's, and the neck's narrowest
radius is rho_n - r_neck; the neck pinches off (the surface becomes singular)
where rho_n = r_neck.

:class:`Bud` gives, for points anywhere in space (all lengths in the unit of R):

- ``phi(x)``: the exact signed distance to the surface (< 0 inside), the
  level-set function;
- ``principal_curvatures(x)``, ``curvature(x)``: the principal curvatures at
  the closest surface point (meridional, circumferential; > 0 where the surface
  bends away from its outward normal, i.e. spheres 1/R, the neck's meridian
  -1/r_neck) and the larger of their magnitudes, kappa;
- ``thickness(x)``: d, the distance from the closest surface point along the
  normal (inwards and outwards) to the next crossing of the surface, the
  "distance to the opposing surface" of Eq. 4.14;
- ``monitor(x, D0)``: ``D~ = D0 / sqrt(1 + max(kappa, 1/d)^2)`` (Eq. 4.14);
- ``in_band(x, spacing, half_width)``: the narrow band ``|phi| <= half_width * spacing(x)``;
- ``sample_band(spacing, width, rng)``: random particles filling the band
  with about one particle per spacing^3 volume;
- ``surface_points`` / ``mesh``: points on the surface, for tests and plots.

Everything that depends on the position along the surface (curvature,
thickness, spacing) is a function of the closest surface point, so it is
constant along the band's normals.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["Bud", "SurfaceSpacing", "eq_4_14", "pinch_off_distance"]

#: Points per arc of the profile tables (thickness, band sampling).
TABLE_POINTS = 4001
#: The thickness tables made last, by geometry (L, R, r, r_neck): every Bud of the same shape has the
#: same table, which takes a second to make (at most THICKNESS_TABLES_KEPT kept, about 190 kB each).
THICKNESS_TABLES_KEPT = 16
_THICKNESS_TABLES: dict[tuple[float, float, float, float], list[tuple[np.ndarray, np.ndarray]]] = {}


def pinch_off_distance(R: float, r: float, r_neck: float) -> float:
    """The centre distance L at which the neck's narrowest radius reaches 0."""
    return float(np.sqrt((R + r_neck) ** 2 - r_neck ** 2) + np.sqrt((r + r_neck) ** 2 - r_neck ** 2))


def eq_4_14(curvatures: np.ndarray, thickness: np.ndarray, D0: float) -> np.ndarray:
    """The monitor function of Eq. 4.14 from the principal curvatures (m, 2) and the
    thickness d (m,): ``D0 / sqrt(1 + max(kappa, 1/d)^2)``, ``kappa = max |k_i|``."""
    kappa = np.abs(curvatures).max(axis=1)
    return D0 / np.sqrt(1.0 + np.maximum(kappa, 1.0 / thickness) ** 2)


@dataclass(frozen=True)
class _Arc:
    """A circular arc of the profile: centre (z, rho), radius, angle range, and the
    sign of the meridional curvature (+1 convex, -1 concave)."""

    z: float
    rho: float
    radius: float
    a0: float
    a1: float
    sign: float

    def angles(self, m: int) -> np.ndarray:
        return np.linspace(self.a0, self.a1, m)

    def point(self, a: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        return self.z + self.radius * np.cos(a), self.rho + self.radius * np.sin(a)

    def normal(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Outward unit normal of the body (z, rho components)."""
        return self.sign * np.cos(a), self.sign * np.sin(a)


class Bud:
    """A large sphere and a small bud joined by a concave neck (a surface of revolution about z).

    Parameters
    ----------
    L : float
        Distance between the centres of the sphere (z = 0) and the bud (z = L).
    R, r : float
        Radii of the sphere and of the bud (defaults 0.3 and 0.1, §4.6).
    r_neck : float
        Radius of curvature of the neck arc (default 0.1).

    Raises
    ------
    ValueError
        Unless the three arcs form a closed surface with a neck of positive radius (L below
        :func:`pinch_off_distance`, and the neck circle touching the bud beyond the sphere).
    """

    def __init__(self, L: float, R: float = 0.3, r: float = 0.1, r_neck: float = 0.1) -> None:
        for name, v in (("L", L), ("R", R), ("r", r), ("r_neck", r_neck)):
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
        self.L, self.R, self.r, self.r_neck = float(L), float(R), float(r), float(r_neck)
        zn = ((R + r_neck) ** 2 - (r + r_neck) ** 2 + L ** 2) / (2 * L)
        rho2 = (R + r_neck) ** 2 - zn ** 2
        if rho2 <= r_neck ** 2:
            L_max = pinch_off_distance(R, r, r_neck)
            raise ValueError(f"the neck has pinched off: L = {L:g} >= {L_max:.6g}" if L >= L_max else
                             f"the neck circle crosses the axis: L = {L:g} is too small for these radii")
        rn = float(np.sqrt(rho2))
        a_sphere = float(np.arctan2(rn, zn))               # sphere: angles [a_sphere, pi]
        a_bud = float(np.arctan2(rn, zn - L))              # bud: angles [0, a_bud]
        n0, n1 = float(np.arctan2(-rn, -zn)), float(np.arctan2(-rn, L - zn))
        if not n0 < n1:
            raise ValueError("the neck arc does not join the sphere to the bud (L too small for these radii)")
        self.z_neck, self.rho_neck = float(zn), rn
        self.arcs = (_Arc(0.0, 0.0, self.R, a_sphere, np.pi, 1.0),
                     _Arc(self.L, 0.0, self.r, 0.0, a_bud, 1.0),
                     _Arc(zn, rn, self.r_neck, n0, n1, -1.0))
        self._thickness_table: list[tuple[np.ndarray, np.ndarray]] | None = None

    def __repr__(self) -> str:
        return f"Bud(L={self.L:g}, R={self.R:g}, r={self.r:g}, r_neck={self.r_neck:g})"

    @property
    def neck_radius(self) -> float:
        """The narrowest radius of the neck (distance from the axis)."""
        a = self.arcs[2]
        lowest = np.clip(-np.pi / 2, a.a0, a.a1)
        return float(a.rho + a.radius * np.sin(lowest))

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounding box (lo, hi) of the body, (3,) each."""
        return (np.array([-self.R, -self.R, -self.R]),
                np.array([self.R, self.R, max(self.R, self.L + self.r)]))

    # --- closest point in the meridian half-plane ---------------------------------------
    def _closest(self, z: np.ndarray, rho: np.ndarray):
        """For meridian points (z, rho >= 0): distance to the profile, the arc index and
        the angle of the closest point on that arc, and whether the point is inside."""
        best = np.full(z.shape, np.inf)
        arc_id = np.zeros(z.shape, np.int64)
        angle = np.zeros(z.shape)
        for k, a in enumerate(self.arcs):
            dz, dr = z - a.z, rho - a.rho
            t = np.arctan2(dr, dz)
            dist = np.abs(np.hypot(dz, dr) - a.radius)
            for end, beyond in ((a.a0, t < a.a0), (a.a1, t > a.a1)):   # outside its range: the end point
                if beyond.any():
                    ez, er = a.point(end)
                    dist[beyond] = np.hypot(z[beyond] - ez, rho[beyond] - er)
                    t[beyond] = end
            better = dist < best
            best[better], arc_id[better], angle[better] = dist[better], k, t[better]
        return best, arc_id, angle, self._inside(z, rho)

    def _inside(self, z: np.ndarray, rho: np.ndarray) -> np.ndarray:
        """Whether meridian points (z, rho >= 0) are inside the surface."""
        s, b, n = self.arcs
        inside = (np.hypot(z - s.z, rho) < s.radius) | (np.hypot(z - b.z, rho) < b.radius)
        zt0, zt1 = n.point(np.array([n.a0, n.a1]))[0]
        between = (z >= zt0) & (z <= zt1)
        under = rho < n.rho - np.sqrt(np.maximum(n.radius ** 2 - (z - n.z) ** 2, 0.0))
        return inside | (between & under)

    @staticmethod
    def _meridian(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != 3:
            raise ValueError(f"x must have shape (m, 3), got {x.shape}")
        return x[:, 2], np.hypot(x[:, 0], x[:, 1])

    def phi(self, x: np.ndarray) -> np.ndarray:
        """Signed distance to the surface, (m, 3) -> (m,); negative inside."""
        dist, _, _, inside = self._closest(*self._meridian(x))
        return np.where(inside, -dist, dist)

    def _curvatures_at(self, arc_id: np.ndarray, angle: np.ndarray) -> np.ndarray:
        k = np.empty(arc_id.shape + (2,))
        for i, a in enumerate(self.arcs):
            sel = arc_id == i
            if not np.any(sel):
                continue
            _, rho = a.point(angle[sel])
            _, n_rho = a.normal(angle[sel])
            k_mer = a.sign / a.radius
            on_axis = rho < 1e-12 * max(self.R, 1.0)
            k[sel, 0] = k_mer
            k[sel, 1] = np.where(on_axis, k_mer, n_rho / np.where(on_axis, 1.0, rho))
        return k

    def principal_curvatures(self, x: np.ndarray) -> np.ndarray:
        """(m, 3) -> (m, 2): meridional and circumferential curvature at the closest
        surface point (1/R on a sphere; -1/r_neck and 1/rho on the neck)."""
        _, arc_id, angle, _ = self._closest(*self._meridian(x))
        return self._curvatures_at(arc_id, angle)

    def curvature(self, x: np.ndarray) -> np.ndarray:
        """kappa: the larger magnitude of the two principal curvatures, (m,)."""
        return np.abs(self.principal_curvatures(x)).max(axis=1)

    # --- thickness: distance to the opposing surface --------------------------------------
    def _ray_distance(self, z0, r0, nz, nr, direction: float) -> np.ndarray:
        """Distance from profile points along direction * normal to the next crossing of the
        surface (rays in the meridian plane cross the axis into the mirrored half-plane)."""
        scale = self.bounds[1][2] - self.bounds[0][2]
        t = np.geomspace(1e-7 * scale, 2.0 * scale, 400)
        start_inside = direction < 0

        def inside_at(tt):
            zz = z0[:, None] + direction * tt * nz[:, None]
            rr = np.abs(r0[:, None] + direction * tt * nr[:, None])
            return self._inside(zz.ravel(), rr.ravel()).reshape(zz.shape)

        ins = inside_at(t[None, :] * np.ones((z0.size, 1)))
        crossed = ins != start_inside
        # the first sample past the first stretch on the starting side
        started = np.cumsum(ins == start_inside, axis=1) > 0
        hit = crossed & started
        k = np.argmax(hit, axis=1)
        found = hit[np.arange(z0.size), k]
        lo = np.where(k > 0, t[np.maximum(k - 1, 0)], 0.0)
        hi = t[k]
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            m_in = inside_at(mid[:, None])[:, 0]
            go = m_in == start_inside
            lo, hi = np.where(go, mid, lo), np.where(go, hi, mid)
        return np.where(found, hi, np.inf)

    def _table(self) -> list[tuple[np.ndarray, np.ndarray]]:
        shape = (self.L, self.R, self.r, self.r_neck)
        if self._thickness_table is None:
            self._thickness_table = _THICKNESS_TABLES.get(shape)
        if self._thickness_table is None:
            tables = []
            for a in self.arcs:
                ang = a.angles(TABLE_POINTS)
                z0, r0 = a.point(ang)
                nz, nr = a.normal(ang)
                d = np.minimum(self._ray_distance(z0, r0, nz, nr, -1.0), self._ray_distance(z0, r0, nz, nr, 1.0))
                tables.append((ang, d))
            for _, d in tables:
                d.setflags(write=False)
            while len(_THICKNESS_TABLES) >= THICKNESS_TABLES_KEPT:
                del _THICKNESS_TABLES[next(iter(_THICKNESS_TABLES))]      # the oldest
            self._thickness_table = _THICKNESS_TABLES[shape] = tables
        return self._thickness_table

    def _thickness_at(self, arc_id: np.ndarray, angle: np.ndarray) -> np.ndarray:
        d = np.empty(arc_id.shape)
        for i, (ang, tab) in enumerate(self._table()):
            sel = arc_id == i
            d[sel] = np.interp(angle[sel], ang, tab)
        return d

    def thickness(self, x: np.ndarray) -> np.ndarray:
        """d(x): the distance from the closest surface point along its normal (inwards or
        outwards, the nearer) to the next crossing of the surface, (m,); inf if none.
        Tabulated along the profile (``TABLE_POINTS`` per arc) and interpolated."""
        _, arc_id, angle, _ = self._closest(*self._meridian(x))
        return self._thickness_at(arc_id, angle)

    def monitor(self, x: np.ndarray, D0: float) -> np.ndarray:
        """D~(x) = D0 / sqrt(1 + max(kappa, 1/d)^2) (Eq. 4.14), (m,), unit of D0."""
        return self.monitor_spacing(D0)(x)

    # --- the narrow band ------------------------------------------------------------------
    def in_band(self, x: np.ndarray, spacing: Callable[[np.ndarray], np.ndarray], half_width: float = 4.0) -> np.ndarray:
        """Points within the band ``|phi| <= half_width * spacing(x)``, (m,) bool.  ``spacing``
        maps (m, 3) points to (m,) lengths, e.g. a :class:`SurfaceSpacing` of this surface
        (then the closest surface points are found once for both)."""
        x = np.asarray(x, dtype=np.float64)
        if isinstance(spacing, SurfaceSpacing) and spacing.bud is self:
            dist, arc_id, angle, _ = self._closest(*self._meridian(x))
            return dist <= half_width * spacing.at_profile(arc_id, angle)
        return np.abs(self.phi(x)) <= half_width * np.asarray(spacing(x))

    def surface_points(self, n_angle: int = 64, n_azimuth: int = 48) -> np.ndarray:
        """Points on the surface: ``n_angle`` per arc times ``n_azimuth`` azimuths, (m, 3)."""
        z, rho = self.profile(n_angle)
        return self._revolve(z, rho, n_azimuth).reshape(-1, 3)

    def profile(self, n_angle: int = 200) -> tuple[np.ndarray, np.ndarray]:
        """The profile curve (z, rho) from the sphere's pole to the bud's, ``n_angle`` points per arc."""
        s, b, n = self.arcs
        parts = [s.point(s.angles(n_angle)[::-1]), n.point(n.angles(n_angle)), b.point(b.angles(n_angle)[::-1])]
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])

    @staticmethod
    def _revolve(z: np.ndarray, rho: np.ndarray, n_azimuth: int) -> np.ndarray:
        t = np.linspace(0.0, 2 * np.pi, n_azimuth, endpoint=False)
        return np.stack([rho[:, None] * np.cos(t), rho[:, None] * np.sin(t), np.broadcast_to(z[:, None], (z.size, t.size))],
                        axis=-1)

    def mesh(self, n_angle: int = 120, n_azimuth: int = 96) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """X, Y, Z arrays (profile points x azimuths, azimuth closed) for ``plot_surface``."""
        z, rho = self.profile(n_angle)
        t = np.linspace(0.0, 2 * np.pi, n_azimuth)
        return rho[:, None] * np.cos(t), rho[:, None] * np.sin(t), np.broadcast_to(z[:, None], (z.size, t.size)).copy()

    def sample_band(self, spacing: "SurfaceSpacing", *, half_width: float = 4.0,
                    density: float = 1.0, seed: int | np.random.Generator | None = None) -> np.ndarray:
        """Random particles in the narrow band, about ``density`` per spacing^3 of volume.

        The profile is cut into segments, each receiving a Poisson number of particles with mean
        ``density * 2 pi rho * ds * 2 half_width h / h^3``; each particle sits at a random point of
        its segment, a random azimuth, and a random normal offset; points outside their band
        (possible near the neck) are dropped.

        Parameters
        ----------
        spacing : SurfaceSpacing
            The local spacing h, a :class:`SurfaceSpacing` of this surface (see :meth:`spacing`,
            :meth:`monitor_spacing`).
        half_width : float
            The band's half-width in units of h (``|phi| <= half_width * h``).
        density : float
            Particles per h^3 of volume.
        seed : int or numpy.random.Generator, optional
            Seed of the random positions.

        Returns
        -------
        array (N, 3)
            The positions.
        """
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        out = []
        for i, a in enumerate(self.arcs):
            ang = a.angles(TABLE_POINTS)
            mid = 0.5 * (ang[1:] + ang[:-1])
            h = spacing.at_profile(np.full(mid.size, i), mid)
            _, rho = a.point(mid)
            ds = a.radius * np.diff(ang)
            counts = rng.poisson(density * 4 * np.pi * rho * ds * half_width / h ** 2)
            seg = np.repeat(np.arange(mid.size), counts)
            t = ang[seg] + rng.uniform(size=seg.size) * (ang[seg + 1] - ang[seg])
            pz, pr = a.point(t)
            nz, nr = a.normal(t)
            off = (2 * rng.uniform(size=seg.size) - 1.0) * half_width * h[seg]
            zz, rr = pz + off * nz, pr + off * nr
            az = rng.uniform(0, 2 * np.pi, size=seg.size)
            pts = np.stack([np.abs(rr) * np.cos(az), np.abs(rr) * np.sin(az), zz], axis=1)
            out.append(pts)
        x = np.concatenate(out)
        # an offset point can have another closest surface point (and spacing) than the one
        # it was placed from (near the neck): keep the points inside their band
        dist, arc_id, angle, _ = self._closest(*self._meridian(x))
        return x[dist <= half_width * spacing.at_profile(arc_id, angle)]

    def spacing(self, of: Callable[[np.ndarray, np.ndarray | None], np.ndarray], thickness: bool = True) -> "SurfaceSpacing":
        """A length field set by the surface's shape: ``of(curvatures (m, 2), thickness (m,))
        -> (m,)`` at the closest surface point (see :class:`SurfaceSpacing`).
        ``thickness=False``: ``of`` gets None instead of d (whose table costs a few
        seconds to build the first time)."""
        return SurfaceSpacing(self, of, thickness)

    def monitor_spacing(self, D0: float, Dmin: float | None = None) -> "SurfaceSpacing":
        """Eq. 4.14 as a :class:`SurfaceSpacing`, optionally bounded below by ``Dmin``."""
        lower = 0.0 if Dmin is None else float(Dmin)

        def of(k: np.ndarray, d: np.ndarray | None) -> np.ndarray:
            assert d is not None        # a spacing with thickness (the default) gets d
            return np.maximum(eq_4_14(k, d, D0), lower)
        return self.spacing(of)


class SurfaceSpacing:
    """A length field (resolution, spacing) that depends only on the closest point of a
    :class:`Bud`'s surface, so it is constant along the normals.

    Calling it with (m, 3) positions gives (m,) lengths; :meth:`at_profile`
    gives them at profile points (arc index, angle), which is what
    :meth:`Bud.sample_band` needs.
    """

    def __init__(self, bud: Bud, of: Callable[[np.ndarray, np.ndarray | None], np.ndarray],
                 thickness: bool = True) -> None:
        self.bud, self._of, self._thickness = bud, of, bool(thickness)

    def at_profile(self, arc_id: np.ndarray, angle: np.ndarray) -> np.ndarray:
        b = self.bud
        d = b._thickness_at(arc_id, angle) if self._thickness else None
        return np.asarray(self._of(b._curvatures_at(arc_id, angle), d), dtype=np.float64)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        _, arc_id, angle, _ = self.bud._closest(*self.bud._meridian(x))
        return self.at_profile(arc_id, angle)
