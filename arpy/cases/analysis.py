"""What several cases share in their analysis: convergence orders from least-squares fits."""

from __future__ import annotations

import numpy as np

__all__ = ["equal_error_ratio", "slope"]


def slope(h: np.ndarray, err: np.ndarray) -> float:
    """Least-squares slope of log(err) against log(h).

    Parameters
    ----------
    h : (k,) array
        Resolutions (or any positive abscissa).
    err : (k,) array
        Positive errors at those resolutions.

    Returns
    -------
    float
        The fitted order p of err ~ h^p.
    """
    return float(np.polyfit(np.log(h), np.log(err), 1)[0])


def equal_error_ratio(n_ref: np.ndarray, err_ref: np.ndarray, n: np.ndarray, err: np.ndarray) -> np.ndarray:
    """N_ref(err) / N for each (N, err): the reference method's particle count (or any
    cost) at the same error, from the least-squares power law log err = a + b log N_ref.

    Parameters
    ----------
    n_ref, err_ref : (k,) arrays
        Costs and errors of the reference method (the fit).
    n, err : (m,) arrays
        Costs and errors of the method compared with it.

    Returns
    -------
    (m,) array
        The reference's cost at each error ``err`` over ``n``.
    """
    b, a = np.polyfit(np.log(n_ref), np.log(err_ref), 1)
    return np.exp((np.log(err) - a) / b) / np.asarray(n, dtype=np.float64)
