"""Core sizes for DC-PSE on scattered data: points that were not self-organized (measurements, a mesh's
nodes, random samples), whose spacing varies from place to place and grows towards the edge of the data.

A DC-PSE stencil of order m in d dimensions fits N* = C(m - 1 + d, d) moment conditions (the monomials
of degree < m: 10 in 2D and 20 in 3D at m = 4), so every point needs clearly more than N* neighbours
within its core size, and under the min rule ``|x_p - x_q| <= min(eps_p, eps_q)`` a neighbour q counts
only if p also lies within q's own core size.  :func:`core_sizes` takes the core size from the local
spacing, ``eps_p = CORE_FACTOR x`` (the distance from x_p to its k-th nearest other point), with
``k = ceil(CORE_NEIGHBOURS x N*)``:

* the ball of radius r_k holds k = 1.5 N* other points (15 in 2D, 30 in 3D at m = 4), and the factor
  1.5 widens it to about 1.5^d k of them where the density is even (34 in 2D, 100 in 3D); the margin
  keeps more than N* neighbours under the min rule where the density changes (a neighbour in denser
  data has a smaller core size) and where the data end (the ball of a point at the edge is one-sided,
  and its k-th neighbour, further away, makes it wider);
* on points of a density varying tenfold (a Gaussian blob on uniform points; 2,000 to 8,000 points
  in 2D, four seeds at 4,000; 4,000 and 16,000 in 3D), no point of the data lacked a stencil, and the
  interior Laplacian, gradient and interpolation converge at about their orders (tests/test_dcpse.py);
  k = N* with a factor of 1 or 1.25 left 47 to 3,769 points of the 2D sets without a stencil, and
  wider balls (k = 2 N*, factor 2) doubled the interior Laplacian's error.

Operators on such data: ``DomainDCPSE(x, core_sizes(x), widen=3)``; the widening rebuilds the few rows
that still fail (e.g. points queried outside the data) from a wider gather.  Leave ``max_lebesgue`` at
None there: a large Lebesgue constant on smooth scattered data is no defect (see the user guide,
"Scattered data").
"""

from __future__ import annotations

import math

import numpy as np

from .._validate import as_positions
from ..domain import Domain, nearest
from .kernel import n_unknowns

__all__ = ["CORE_FACTOR", "CORE_NEIGHBOURS", "core_sizes"]

#: The core size over the distance to the k-th nearest other point.
CORE_FACTOR = 1.5
#: k over N*, the number of moment conditions of the stencil.
CORE_NEIGHBOURS = 1.5


def core_sizes(x: np.ndarray, *, order: int = 4, domain: Domain | None = None, factor: float = CORE_FACTOR,
               k: int | None = None) -> np.ndarray:
    """Core sizes (cutoff radii) of DC-PSE on scattered points, from the local spacing.

    ``eps_p = factor * |x_p - x_(k)|``, the distance from x_p to its k-th nearest other point (see the
    module docstring for the rule and its measurements).

    Parameters
    ----------
    x : array (n, d)
        The points, d = 2 or 3 (any length unit).
    order : int
        The DC-PSE order m the sizes are for (N* = C(m - 1 + d, d) moment conditions).
    domain : Domain or None
        Distances by the minimum image along its periodic axes (None: free space).
    factor : float
        The core size over the k-th neighbour distance (default :data:`CORE_FACTOR`, 1.5; > 0).
    k : int or None
        The neighbour whose distance sets the size (default ``ceil(CORE_NEIGHBOURS * N*)``: 15 in 2D,
        30 in 3D at order 4).

    Returns
    -------
    array (n,)
        The core sizes, in the unit of x; pass them as ``eps`` (and the sources' sizes) to
        :class:`arpy.DomainDCPSE` or :class:`arpy.DCPSE`.

    Raises
    ------
    ValueError
        Fewer than k + 1 points, a factor that is not a finite number > 0, or a point with more
        than k others at its own position (its size would be 0).

    Examples
    --------
    >>> import numpy as np
    >>> import arpy
    >>> from arpy.dcpse import core_sizes
    >>> rng = np.random.default_rng(0)
    >>> x = np.concatenate([0.5 + 0.1 * rng.standard_normal((1500, 2)), rng.random((500, 2))])
    >>> eps = core_sizes(x)
    >>> op = arpy.DomainDCPSE(x, eps, widen=3)
    >>> inner = np.abs(x - 0.5).max(1) < 0.2
    >>> bool(eps[inner].max() < eps[~inner].max()), op.failed.size
    (True, 0)
    >>> lap = op.laplacian() @ op.extend((x ** 2).sum(1))
    >>> bool(np.allclose(lap, 4.0))
    True
    """
    x = as_positions(x)
    n, d = x.shape
    if not (math.isfinite(factor) and factor > 0):
        raise ValueError(f"core_sizes: factor must be a finite number > 0, got {factor!r}")
    if k is None:
        k = math.ceil(CORE_NEIGHBOURS * n_unknowns(d, int(order), at_sources=False))
    if int(k) != k or k < 1:
        raise ValueError(f"core_sizes: k must be an integer >= 1, got {k!r}")
    k = int(k)
    if n < k + 1:
        raise ValueError(f"core_sizes: needs more than k = {k} points (order {order} in {d}D), got {n}")
    dist, _ = nearest(x, k, domain=domain)      # (each point's k nearest others)
    eps = factor * dist[:, k - 1]
    if not np.all(eps > 0):
        p = int(np.flatnonzero(~(eps > 0))[0])
        raise ValueError(f"core_sizes: point {p} has more than k = {k} others at its own position")
    return eps
