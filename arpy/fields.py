"""Analytic test fields of the papers, with their exact derivatives."""

from __future__ import annotations

import numpy as np

__all__ = ["tanh_front", "tanh_front_gradient", "tanh_front_laplacian"]

# Eq. (4.1) of Reboux et al. (2012): f = tanh((x^2 + y^2 - R^2) / W), on [-1, 1]^2
_R2, _W = 0.2 ** 2, 0.01


def tanh_front(x: np.ndarray) -> np.ndarray:
    """The test function of Sec. 4.1, Eq. (4.1): tanh((x^2 + y^2 - 0.2^2) / 0.01); x (n, 2) -> (n,).

    A steep circular front of radius 0.2 (the paper prints the argument as
    (x^2 + y^2 - 0.2^2)/0.01).
    """
    return np.tanh((x[:, 0] ** 2 + x[:, 1] ** 2 - _R2) / _W)


def tanh_front_gradient(x: np.ndarray) -> np.ndarray:
    """Exact gradient of :func:`tanh_front`, shape (n, 2)."""
    t = tanh_front(x)
    return (1 - t * t)[:, None] * 2 * x[:, :2] / _W


def tanh_front_laplacian(x: np.ndarray) -> np.ndarray:
    """Exact Laplacian of :func:`tanh_front`, shape (n,).

    With g = (r^2 - R^2)/W: lap f = sech^2(g) lap g - 2 tanh(g) sech^2(g) |grad g|^2.
    """
    t = tanh_front(x)
    sech2 = 1 - t * t
    r2 = x[:, 0] ** 2 + x[:, 1] ** 2
    return sech2 * (4 / _W) - 2 * t * sech2 * (4 * r2 / _W ** 2)
