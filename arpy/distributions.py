"""Particle distributions used by the papers' benchmarks and by arpy's demos."""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np

if TYPE_CHECKING:
    from .surface import Bud

__all__ = ["ar_benchmark", "bud_benchmark", "quadtree_particles"]


def ar_benchmark(n_small: int, lam: float, d: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Two-resolution distribution of the AR cell-list benchmark (Awile et al. 2012, §3.1).

    A block of 10^d "large" particles on a Cartesian mesh of spacing h_b = 0.1
    (cell-centred in [0, 1]^d) with cutoff r_c,b = 1.5 h_b = 0.15, and
    ``n_small`` "small" particles with cutoff r_c,s = r_c,b / lam on a
    Cartesian mesh of spacing h_s = 2 r_c,s / 3 = h_b / lam adjacent to the
    coarse block: the small mesh fills the same extent [0, 1] in every axis
    but the first and is stacked in columns along x starting at x = 1.
    Every particle away from the block edges has exactly 8 neighbours in 2D
    (18 in 3D: r_c = 1.5 h reaches the face and edge neighbours, not the corners).  The paper does not fix the shape of the small block; this
    choice keeps the interface as long as the coarse block.

    Parameters
    ----------
    n_small : int
        Number of small particles (>= 0).
    lam : float
        Resolution span max(r_c) / min(r_c) (>= 1).
    d : int
        Dimension, 2 or 3.

    Returns
    -------
    x : array (10^d + n_small, d)
        Positions; the large particles come first.
    rc : array (10^d + n_small,)
        Cutoff radii.
    """
    if d not in (2, 3):
        raise ValueError("d must be 2 or 3")
    if lam < 1 or not np.isfinite(lam):
        raise ValueError("lam (resolution span) must be a finite number >= 1")
    if n_small < 0:
        raise ValueError("n_small must be >= 0")
    hb, rcb = 0.1, 0.15
    hs, rcs = hb / lam, rcb / lam
    axis = (np.arange(10) + 0.5) * hb
    big = np.stack(np.meshgrid(*([axis] * d), indexing="ij"), axis=-1).reshape(-1, d)
    per_col = max(1, int(round(1.0 / hs)))          # small points per axis across the block
    layer = per_col ** (d - 1)                       # small points in one x-column layer
    k = np.arange(n_small)
    col, rem = np.divmod(k, layer)
    small = np.empty((n_small, d))
    small[:, 0] = 1.0 + (col + 0.5) * hs
    for ax in range(1, d):
        rem, idx = np.divmod(rem, per_col)
        small[:, ax] = (idx + 0.5) * hs
    x = np.concatenate([big, small])
    rc = np.concatenate([np.full(big.shape[0], rcb), np.full(n_small, rcs)])
    return x, rc


def quadtree_particles(spacing: Callable[[np.ndarray], np.ndarray], lo: float = -1.0, hi: float = 1.0,
                       jitter: float = 0.15, seed: int | None = 0) -> tuple[np.ndarray, np.ndarray]:
    """An adaptive 2D particle set: one particle per leaf of a quadtree on [lo, hi]^2.

    A cell is split while it is larger than ``spacing`` (the wanted local
    spacing, e.g. a monitor function D(x), Eq. 2.8) at its centre; each leaf
    holds one particle at its centre, moved by up to ``jitter`` times the
    leaf size.  A quick stand-in for self-organized particles.

    Returns positions (n, 2) and leaf sizes (n,) (the local spacing h_p).
    """
    if not hi > lo:
        raise ValueError("need hi > lo")
    rng = np.random.default_rng(seed)
    centres, size = np.array([[0.5 * (lo + hi)] * 2]), float(hi - lo)
    xs, hs = [], []
    while len(centres):
        split = spacing(centres) < size
        xs.append(centres[~split])
        hs.append(np.full(int((~split).sum()), size))
        quarter = size / 4 * np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]])
        centres = (centres[split][:, None, :] + quarter).reshape(-1, 2)
        size /= 2
        if size < 1e-12 * (hi - lo):
            raise ValueError("spacing function asks for a resolution below 1e-12 of the domain")
    x, h = np.concatenate(xs), np.concatenate(hs)
    return x + rng.uniform(-jitter, jitter, x.shape) * h[:, None], h


def bud_benchmark(h0: float, lam: float, *, R: float = 3.0, r: float = 1.0, L: float | None = None,
                  half_width: float = 2.0, seed: int | np.random.Generator | None = 0
                  ) -> tuple[np.ndarray, np.ndarray, Bud]:
    """The budding-cell distribution of the AR cell-list application (Awile et al. 2012, §3.2).

    A sphere of radius ``R`` and a bud of radius ``r`` (centres ``L`` apart,
    default R + r: touching, as a bud about to pinch off) joined by a neck arc
    of radius r_P = R / lam (:class:`arpy.surface.Bud`).  Particles fill the
    narrow band ``|phi| <= half_width * h`` with about one particle per h^3, where
    the spacing h = h0 / (R kappa) is proportional to the local radius of
    curvature 1 / kappa (kappa the larger principal curvature), so h = h0 on
    the sphere and h0 r_P / R on the neck's meridian; cutoffs r_c = r* h with
    r* = sqrt(3) (about 20 neighbours, :func:`arpy.adapt.resolution.r_star`).  The
    resolution span max r_c / min r_c is about ``lam`` (larger when the neck's
    own radius is below r_P).

    Returns (x, rc, bud): positions (N, 3), cutoffs (N,), the geometry.
    """
    from .adapt.resolution import r_star
    from .surface import Bud

    if not (np.isfinite(h0) and h0 > 0):
        raise ValueError("h0 must be a finite number > 0")
    if not (np.isfinite(lam) and lam >= 1):
        raise ValueError("lam must be a finite number >= 1")
    bud = Bud(R + r if L is None else L, R, r, R / lam)
    spacing = bud.spacing(lambda k, d: h0 / (R * np.abs(k).max(axis=1)), thickness=False)
    x = bud.sample_band(spacing, half_width=half_width, seed=seed)
    return x, r_star(3) * spacing(x), bud
