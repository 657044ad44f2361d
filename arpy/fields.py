"""Analytic test fields of the papers, with their exact derivatives."""

from __future__ import annotations

import numpy as np

from .adapt.resolution import fourth_multi_indices

__all__ = ["tanh_front", "tanh_front_fourth_derivatives", "tanh_front_gradient", "tanh_front_laplacian"]

# Eq. (4.1) of Reboux et al. (2012): f = tanh((x^2 + y^2 - R^2) / W), on [-1, 1]^2
_R2, _W = 0.2 ** 2, 0.01


def tanh_front(x: np.ndarray, width: float = _W) -> np.ndarray:
    """The test function of Sec. 4.1, Eq. (4.1): tanh((x^2 + y^2 - 0.2^2) / W); x (n, 2) -> (n,).

    A steep circular front of radius 0.2; the paper's W is 0.01 (it prints
    the argument as (x^2 + y^2 - 0.2^2)/0.01); a larger ``width`` W gives a
    milder front.
    """
    return np.tanh((x[:, 0] ** 2 + x[:, 1] ** 2 - _R2) / width)


def tanh_front_gradient(x: np.ndarray, width: float = _W) -> np.ndarray:
    """Exact gradient of :func:`tanh_front`, shape (n, 2)."""
    t = tanh_front(x, width)
    return (1 - t * t)[:, None] * 2 * x[:, :2] / width


def tanh_front_laplacian(x: np.ndarray, width: float = _W) -> np.ndarray:
    """Exact Laplacian of :func:`tanh_front`, shape (n,).

    With ``g = (r^2 - R^2)/W``: ``lap f = sech^2(g) lap g - 2 tanh(g) sech^2(g) |grad g|^2``.
    """
    t = tanh_front(x, width)
    sech2 = 1 - t * t
    r2 = x[:, 0] ** 2 + x[:, 1] ** 2
    return sech2 * (4 / width) - 2 * t * sech2 * (4 * r2 / width ** 2)


def tanh_front_fourth_derivatives(x: np.ndarray, width: float = _W) -> np.ndarray:
    """Exact fourth partial derivatives of :func:`tanh_front`, shape (n, 5):
    d^4/dx^4, d^4/dx^3dy, d^4/dx^2dy^2, d^4/dxdy^3, d^4/dy^4 (units 1 / length^4).

    f = g(u) with u = r^2, so D = (1/r) d/dr = 2 d/du and D^k f = 2^k g^(k);
    with a = 1/W and t = tanh(a (u - R^2)): g2 = -2 a^2 t (1 - t^2),
    g3 = a^3 (1 - t^2)(6 t^2 - 2), g4 = 8 a^4 t (1 - t^2)(2 - 3 t^2).
    Eq. B.13 of the paper builds its optimal resolution for m = 4 from these.
    """
    a = 1.0 / width
    t = tanh_front(x, width)
    s = 1 - t * t
    dd = (-8 * a ** 2 * t * s, 8 * a ** 3 * s * (6 * t * t - 2), 128 * a ** 4 * t * s * (2 - 3 * t * t))
    return radial_fourth_all(x[:, :2], dd)


def radial_fourth_all(dx: np.ndarray, dd: tuple) -> np.ndarray:
    """All fourth partial derivatives (n, 5 in 2D, 15 in 3D) of a radial f at offsets
    dx (n, d) from its centre, ordered as :func:`arpy.adapt.resolution.fourth_multi_indices`;
    dd as in :func:`radial_fourth`."""
    idx = [sum(((k,) * p for k, p in enumerate(beta)), ()) for beta in fourth_multi_indices(dx.shape[1])]
    return np.stack([radial_fourth(i, dx, dd) for i in idx], axis=1)


def radial_fourth(idx: tuple, dx: np.ndarray, dd: tuple) -> np.ndarray:
    """d^4 f / dx_idx[0] ... dx_idx[3] (n,) of a radial f at offsets dx (n, d) from its
    centre, from dd = (D^2 f, D^3 f, D^4 f) with D = (1/r) d/dr:
    d_ijkl f = (3 pairings d_ab d_cd) D^2 f + (6 terms d_ab x_c x_d) D^3 f + x_i x_j x_k x_l D^4 f."""
    d2, d3, d4 = dd
    pairings = sum(idx[p] == idx[q] and idx[u] == idx[v] for p, q, u, v in ((0, 1, 2, 3), (0, 2, 1, 3), (0, 3, 1, 2)))
    mixed = np.zeros(dx.shape[0])
    for p, q in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)):
        if idx[p] == idx[q]:
            u, v = (k for k in range(4) if k not in (p, q))
            mixed = mixed + dx[:, idx[u]] * dx[:, idx[v]]
    return pairings * d2 + mixed * d3 + np.prod(dx[:, list(idx)], axis=1) * d4
