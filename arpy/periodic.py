"""Boundaries by ghost particles: periodic images, and mirror images at rigid walls."""

from __future__ import annotations

import itertools
import math

import numpy as np

__all__ = ["periodic_ghosts", "mirror_images", "as_box", "wrap", "box_coordinates", "nearest"]


def as_box(box, d: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalise a periodic box to ``(lo, hi)``, arrays of shape (d,).

    ``box`` is either the edge lengths, shape (d,) (the box is [0, L)), or a
    pair ``(lo, hi)`` of arrays of shape (d,).
    """
    arr = np.asarray(box, dtype=np.float64)
    if arr.shape == (d,):
        lo, hi = np.zeros(d), arr.copy()
    elif arr.shape == (2, d):
        lo, hi = arr[0].copy(), arr[1].copy()
    else:
        raise ValueError(f"box must be edge lengths of shape ({d},) or (lo, hi) of shape (2, {d}), got {arr.shape}")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi > lo)
            and np.all(np.isfinite(hi - lo))):
        raise ValueError("box must be finite (edges too) with hi > lo along every axis")
    return lo, hi


def wrap(x: np.ndarray, box: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Positions x (m, d) mapped into the periodic box (lo, hi): lo + (x - lo) mod (hi - lo)."""
    lo, hi = box
    return lo + np.mod(x - lo, hi - lo)


def box_coordinates(x: np.ndarray, box: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Coordinates relative to lo, strictly inside [0, hi - lo) (as scipy's periodic
    cKDTree with ``boxsize = hi - lo`` requires)."""
    lo, hi = box
    return np.minimum(np.mod(x - lo, hi - lo), np.nextafter(hi - lo, 0))


def nearest(x: np.ndarray, y: np.ndarray, k: int = 1, box=None) -> tuple[np.ndarray, np.ndarray]:
    """Distances and indices of the k points of x (n, d) nearest to each point of y (m, d),
    as scipy's ``cKDTree.query`` returns them; with a periodic box (edge lengths or
    (lo, hi), see :func:`as_box`), by the minimum image.

    Where the largest |coordinate| lies outside [2**-400, 2**400], coordinates
    are first scaled by a power of two (exact) that puts it near 1, so that
    squared distances neither overflow nor underflow (inside that window the
    squared spacing of distinct doubles, >= (2**-452)**2, stays normal)."""
    from scipy.spatial import cKDTree

    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if box is not None:
        box = as_box(box, x.shape[1])
    bounds = [float(f(v)) for v in (x, y) + (box if box is not None else ()) if v.size for f in (np.min, np.max)]
    top = max(map(abs, bounds), default=0.0)
    e = 0
    if np.isfinite(top) and top > 0 and not -400 <= math.frexp(top)[1] <= 400:
        e = -math.frexp(top)[1]
        x, y = np.ldexp(x, e), np.ldexp(y, e)
        box = None if box is None else (np.ldexp(box[0], e), np.ldexp(box[1], e))
    if box is None:
        dist, idx = cKDTree(x).query(y, k=k)
    else:
        dist, idx = cKDTree(box_coordinates(x, box), boxsize=box[1] - box[0]).query(box_coordinates(y, box), k=k)
    return (np.ldexp(dist, -e) if e else dist), idx


def periodic_ghosts(x: np.ndarray, rc: float | np.ndarray, box, skin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Ghost copies of particles near the faces of a periodic box.

    A particle is imaged across a face only if it lies within its own cutoff
    (plus skin) of that face: under the min rule a pair across the boundary
    needs both particles that close to it.  Corners and edges get the
    combined images.

    Parameters
    ----------
    x : (n, d) positions inside the box [lo, hi].
    rc : scalar or (n,) cutoff radii; ``max(rc) + skin`` must be < half the
        smallest box edge (so that each pair has at most one image within reach).
    box : edge lengths (d,) or (lo, hi), see :func:`as_box`.
    skin : Verlet skin added to every cutoff.

    Returns
    -------
    x_ghost : (m, d) ghost positions (outside the box, within reach of it).
    source : (m,) int64, index of the real particle each ghost copies.
    """
    from .neighbors import _as_cutoffs, _as_positions

    xs = _as_positions(x)
    n, d = xs.shape
    lo, hi = as_box(box, d)
    skin = float(skin)
    if not (np.isfinite(skin) and skin >= 0.0):
        raise ValueError(f"periodic_ghosts: skin must be a finite number >= 0, got {skin}")
    r = _as_cutoffs(rc, n) + skin
    if n == 0:
        return np.zeros((0, d)), np.zeros(0, np.int64)
    if not np.all(np.isfinite(xs)) or not np.all(np.isfinite(r)) or np.any(r <= 0):
        raise ValueError("positions and cutoffs must be finite, cutoffs > 0")
    outside = np.any((xs < lo) | (xs > hi), axis=1)
    if np.any(outside):
        i = int(np.flatnonzero(outside)[0])
        raise ValueError(f"particle {i} at {xs[i]} lies outside the periodic box [{lo}, {hi}]")
    length = hi - lo
    if r.max() >= 0.5 * length.min():
        raise ValueError(f"periodic box too small: the largest cutoff + skin ({r.max():g}) must be "
                         f"below half the smallest box edge ({0.5 * length.min():g})")
    near_lo = (xs - lo) <= r[:, None]      # imaged to the high side (+L)
    near_hi = (hi - xs) <= r[:, None]      # imaged to the low side (-L)
    ghosts, sources = [], []
    for shift in itertools.product((-1, 0, 1), repeat=d):
        s = np.asarray(shift)
        if not s.any():
            continue
        need = np.ones(n, bool)
        for ax in range(d):
            if s[ax] == 1:
                need &= near_lo[:, ax]
            elif s[ax] == -1:
                need &= near_hi[:, ax]
        idx = np.flatnonzero(need)
        ghosts.append(xs[idx] + s * length)
        sources.append(idx)
    return np.concatenate(ghosts), np.concatenate(sources).astype(np.int64)


def mirror_images(x: np.ndarray, rc: np.ndarray, box) -> tuple[np.ndarray, np.ndarray]:
    """Mirror images of the particles across the faces of a box (method of images, §2.4).

    A particle inside the box within its cutoff rc of a face (but not on it)
    is mirrored across it (across two or three faces near edges and corners).  Particles outside
    the box are not mirrored.  Returns ``(x_image, source)`` like
    :func:`periodic_ghosts`; even images (the source's value) give homogeneous
    Neumann conditions.
    """
    n, d = x.shape
    lo, hi = as_box(box, d)
    rc = np.broadcast_to(np.asarray(rc, dtype=np.float64), (n,))
    inside = np.all((x >= lo) & (x <= hi), axis=1)
    # a particle on a face is its own image there: not mirrored across that face
    near_lo = inside[:, None] & ((x - lo) <= rc[:, None]) & (x > lo)
    near_hi = inside[:, None] & ((hi - x) <= rc[:, None]) & (x < hi)
    images, sources = [], []
    for flips in itertools.product((0, 1, 2), repeat=d):     # 0: as is, 1: across lo, 2: across hi
        if not any(flips):
            continue
        need = np.ones(n, bool)
        img = x.copy()
        for a, f in enumerate(flips):
            if f == 1:
                need &= near_lo[:, a]
                img[:, a] = 2 * lo[a] - x[:, a]
            elif f == 2:
                need &= near_hi[:, a]
                img[:, a] = 2 * hi[a] - x[:, a]
        images.append(img[need])
        sources.append(np.flatnonzero(need))
    return np.concatenate(images), np.concatenate(sources).astype(np.int64)
