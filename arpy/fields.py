"""Analytic test fields of the papers, with their exact derivatives."""

from __future__ import annotations

import numpy as np

__all__ = ["tanh_front", "tanh_front_gradient", "tanh_front_laplacian"]

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

    With g = (r^2 - R^2)/W: lap f = sech^2(g) lap g - 2 tanh(g) sech^2(g) |grad g|^2.
    """
    t = tanh_front(x, width)
    sech2 = 1 - t * t
    r2 = x[:, 0] ** 2 + x[:, 1] ** 2
    return sech2 * (4 / width) - 2 * t * sech2 * (4 * r2 / width ** 2)
