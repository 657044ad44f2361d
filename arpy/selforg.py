"""Self-organizing particles (Reboux et al. 2012, §2.3 and §3.1): resolution field and pseudo forces.

Building blocks of the adaptation loop (the loop itself: :mod:`arpy.organize`):

* :func:`monitor` -- the target resolution D~(x) = D0 / sqrt(1 + |grad f|^2) (Eq. 2.8),
  bounded below by D_min; :func:`monitor_fourth` -- Appendix B's Eq. B.13 for m = 4,
  D~ = D0 (1 + max |d^4 f|)^(-1/4), from the fourth derivatives;
* :func:`resolution` -- D_p = min of D~ over the particles within reach (Eq. 2.9);
* :func:`r_star` -- the cutoff factor r* from the wanted number of neighbours N* (§2.3.4);
* :func:`pair_potential` -- the normalized potentials V1 (Eq. 2.12) and V2 (Eq. 2.13),
  both replaced below r = 0.5 by a straight line to 0 (particle fusion);
* :func:`energy` -- W = sum_p sum_q D_pq^2 V(r_pq / D_pq) and its gradient (Eqs. 2.10-3.4),
  evaluated in the Fortran core over a symmetric neighbour list.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from . import _core
from ._codes import POTENTIALS
from ._errors import raise_for_info
from .neighbors import NeighborList, _as_cutoffs, _as_positions

__all__ = ["POTENTIALS", "energy", "fourth_multi_indices", "monitor", "monitor_fourth", "pair_potential", "r_star",
           "resolution"]


def _potential_code(potential: str) -> int:
    try:
        return POTENTIALS[potential.upper()]
    except (KeyError, AttributeError):
        raise ValueError(f"potential must be one of {sorted(POTENTIALS)}, got {potential!r}") from None


def pair_potential(r: np.ndarray, potential: str = "V2") -> tuple[np.ndarray, np.ndarray]:
    """Normalized pair potential V(r) and V'(r) (dimensionless; r in units of D_pq).

    V1(r) = 0.8 * 2.5^(1 - 5r) - 2.5^(-4r) (Morse type, minimum at r = 1),
    V2(r) = r^-2 / 2 + r^-6 / 6 (repulsive); below r = 0.5 both follow the line
    V(r) = 2 r V(0.5) down to 0, a short-range attraction that fuses particles
    closer than half the local resolution.
    """
    r = np.ascontiguousarray(r, dtype=np.float64)
    if np.any(~np.isfinite(r)) or np.any(r < 0):
        raise ValueError("r must be finite and >= 0")
    v, dv = _core.arpy_pair_potential(_potential_code(potential), r.ravel())
    return v.reshape(r.shape), dv.reshape(r.shape)


def monitor(grad_f: np.ndarray, D0: float, Dmin: float | None = None) -> np.ndarray:
    """Target resolution D~ = D0 / sqrt(1 + |grad f|^2) (Eq. 2.8), at least Dmin.

    grad_f : (n, d) gradient of the field at the particles; D0 > 0 the coarsest
    resolution (length unit of x); returns (n,) in the same unit.
    """
    g = np.asarray(grad_f, dtype=np.float64)
    if g.ndim != 2:
        raise ValueError("grad_f must have shape (n, d)")
    _check_d0(D0)
    return _bounded(D0 / np.sqrt(1.0 + (g * g).sum(axis=1)), D0, Dmin)


def monitor_fourth(d4f: np.ndarray, D0: float, Dmin: float | None = None) -> np.ndarray:
    """Target resolution of Appendix B (Eq. B.13) for interpolation of order m = 4,
    regularised like Eq. 2.8: D~ = D0 (1 + max over |beta| = 4 of |d^beta f|)^(-1/4),
    at least Dmin.

    It equidistributes the leading error of m = 4 interpolation, D_p^4 |f|_{W^4},
    so the flanks of a front, where |grad f| is small but the fourth derivatives
    are not, get the resolution they need (Eq. 2.8 leaves them at about D0).
    d4f : (n, k) fourth partial derivatives of the field at the particles (any k >= 1
    of them, e.g. the k of :func:`fourth_multi_indices`; units f / length^4);
    returns (n,) in the length unit of D0.
    """
    g = np.asarray(d4f, dtype=np.float64)
    if g.ndim != 2 or g.shape[1] == 0:
        raise ValueError("d4f must have shape (n, k) with k >= 1")
    _check_d0(D0)
    return _bounded(D0 * (1.0 + np.abs(g).max(axis=1)) ** -0.25, D0, Dmin)


def fourth_multi_indices(d: int) -> list[tuple[int, ...]]:
    """The multi-indices beta with |beta| = 4 in d dimensions (5 in 2D, 15 in 3D),
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


def resolution(x: np.ndarray, d_tilde: np.ndarray | Callable[[np.ndarray], np.ndarray],
               rstar: float, box=None) -> np.ndarray:
    """D_p = min of D~(x_q) over the particles q within r_c,p = r* D_p of p (Eq. 2.9).

    The equation is implicit (the ball's radius depends on D_p).  With
    g_p(R) = min { D~(x_q) : |x_q - x_p| <= R }, non-increasing in R, D_p is
    its largest consistent value, D_p = sup { D : g_p(r* D) >= D }: the
    resolution of p is as coarse as it can be while no particle within its
    own reach asks for a finer one.  D_p <= D~(x_p); where D~ varies slowly
    D_p = D~(x_p); near a fine feature D_p is graded, falling to the fine
    value over a distance of r* times the local D (rather than jumping to
    it wherever the coarse reach r* D~_p would touch the feature).

    The constraint from a particle q at distance s is D <= max(D~_q, s / r*)
    (either q is out of reach, or its demand is met), so
    D_p = min over q of max(D~_q, |x_q - x_p| / r*) (q = p gives D~_p itself).
    The particles are scanned nearest first; once the distance s reaches
    r* times the running minimum, no farther particle can lower it, so each
    p visits only the particles within its own final reach r* D_p (about
    16 in an adapted set), not all those within r* D~_p (many, beside a fine feature).

    x : (n, d) positions; d_tilde : (n,) target resolution at the particles,
    or a callable giving it from positions; box : periodic box (edge lengths
    or (lo, hi)), None for none.  Returns D (n,), same unit.
    """
    from scipy.spatial import cKDTree

    xs = _as_positions(x)
    dt = np.asarray(d_tilde(xs) if callable(d_tilde) else d_tilde, dtype=np.float64)
    dt = _as_cutoffs(dt, xs.shape[0])
    if not (np.isfinite(rstar) and rstar > 0):
        raise ValueError("r* must be a finite number > 0")
    if not np.all(np.isfinite(dt)) or np.any(dt <= 0):
        raise ValueError("the target resolution must be finite and > 0")
    n = xs.shape[0]
    if n == 0:
        return dt.copy()
    xr, dr = xs, dt
    if box is not None:
        from .periodic import periodic_ghosts

        xg, src = periodic_ghosts(xs, rstar * dt.max(), box)    # images out to the largest reach
        xr, dr = np.concatenate([xs, xg]), np.concatenate([dt, dt[src]])
    tree = cKDTree(xr)
    D = dt.copy()
    todo, k = np.arange(n), 24            # an adapted set holds ~16 particles within r* D_p
    while todo.size:
        k = min(k, xr.shape[0])
        s, j = tree.query(xs[todo], k=k)
        s, j = s.reshape(todo.size, k), j.reshape(todo.size, k)
        D[todo] = np.minimum(D[todo], np.maximum(dr[j], s / rstar).min(axis=1))
        more = (s[:, -1] < rstar * D[todo]) & (k < xr.shape[0])    # the k-th is still within reach
        todo, k = todo[more], 2 * k
    return D


def _period(box, d: int) -> np.ndarray:
    """Edge lengths of a periodic box as the core's ``period`` (zeros: not periodic)."""
    if box is None:
        return np.zeros(d)
    from .periodic import as_box

    lo, hi = as_box(box, d)
    return hi - lo


def energy(x: np.ndarray, D: np.ndarray, neighbors: NeighborList, potential: str = "V2",
           grad_D: np.ndarray | None = None, box=None, cutoff: float | None = None) -> tuple[float, np.ndarray]:
    """Self-organization energy W (Eq. 2.11) and its gradient dW/dx (Eq. 3.4), shape (n, d).

    neighbors : symmetric list (each interacting pair once).  D : (n,) the
    resolution D_p.  grad_D : (n, d) gradient of the resolution field at the
    particles for the term (2V - rV') grad D_pq; None drops it (the paper
    neglects it once the field is resolved).  box : a periodic box (edge
    lengths or (lo, hi), as for :func:`arpy.neighbor_list`); pairs then use
    the minimum image.  cutoff : if given (the r* of lists built with
    r_c = r* D), each pair uses V(r) - V(cutoff): W is then continuous when
    pairs enter or leave the lists (the gradient is that of the paper's W,
    apart from the grad D term, which uses the shifted V).  Unit of W: length^2.
    """
    xs = _as_positions(x)
    n, d = xs.shape
    Ds = _as_cutoffs(D, n)
    if not isinstance(neighbors, NeighborList) or not neighbors.symmetric or neighbors.cross or neighbors.n != n:
        raise ValueError("energy() needs a symmetric NeighborList over the same particles")
    gD = np.zeros((n, d)) if grad_D is None else np.ascontiguousarray(grad_D, dtype=np.float64)
    if gD.shape != (n, d):
        raise ValueError(f"grad_D must have shape ({n}, {d})")
    vshift = 0.0
    if cutoff is not None:
        if not (np.isfinite(cutoff) and cutoff > 0):
            raise ValueError("cutoff must be a finite number > 0")
        vshift = float(pair_potential(np.array([float(cutoff)]), potential)[0][0])
    W, g, info, bad = _core.arpy_so_energy(xs.T, Ds, gD.T, _period(box, d), neighbors.offsets,
                                           neighbors.indices, _potential_code(potential), vshift)
    raise_for_info(info, bad, context="energy")
    return float(W), np.ascontiguousarray(g.T)
