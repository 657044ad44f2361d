"""The pseudo-forces of the self-organizing particles (Reboux et al. 2012, §2.3.3, §3.1).

* :func:`pair_potential` -- the normalized potentials V1 (Eq. 2.12) and V2 (Eq. 2.13), both
  replaced below r = 0.5 by a straight line to 0 (particle fusion);
* :func:`energy` -- W = sum_p sum_q D_pq^2 V(r_pq / D_pq) and its gradient (Eqs. 2.10-3.4),
  evaluated in the Fortran core row by row over a full neighbour list in canonical order, W as
  an exact sum: the results do not depend on the list's method, layout or thread count.
"""

from __future__ import annotations


import numpy as np

from .. import _bridge
from .._codes import POTENTIALS
from .._validate import as_cutoffs, as_positions
from ..distributed.reductions import exact_sum
from ..domain import Domain, as_domain
from ..lists.neighborlist import NeighborList, check_layout

__all__ = ["POTENTIALS", "energy", "energy_terms", "pair_potential", "potential_code"]


def potential_code(potential: str) -> int:
    """The core code of a potential name (case-insensitive), else ValueError."""
    try:
        return POTENTIALS[potential.upper()]
    except (KeyError, AttributeError):
        raise ValueError(f"potential must be one of {sorted(POTENTIALS)}, got {potential!r}") from None


def pair_potential(r: np.ndarray, potential: str = "V2") -> tuple[np.ndarray, np.ndarray]:
    """Normalized pair potential V(r) and V'(r).

    V1(r) = 0.8 * 2.5^(1 - 5r) - 2.5^(-4r) (Morse type, minimum at r = 1),
    V2(r) = r^-2 / 2 + r^-6 / 6 (repulsive); below r = 0.5 both follow the line
    V(r) = 2 r V(0.5) down to 0, a short-range attraction that fuses particles
    closer than half the local resolution ("V1-PURE", "V2-PURE": without it).

    Parameters
    ----------
    r : array, any shape
        Distances in units of D_pq (dimensionless), finite and >= 0.
    potential : str
        A key of :data:`POTENTIALS` (case-insensitive).

    Returns
    -------
    V, dV : arrays of the shape of r
        V(r) and V'(r) (dimensionless).
    """
    r = np.ascontiguousarray(r, dtype=np.float64)
    if np.any(~np.isfinite(r)) or np.any(r < 0):
        raise ValueError("r must be finite and >= 0")
    v, dv = _bridge.pair_potential(potential_code(potential), r.ravel())
    return v.reshape(r.shape), dv.reshape(r.shape)


def energy(x: np.ndarray, D: np.ndarray, neighbors: NeighborList, potential: str = "V2",
           grad_D: np.ndarray | None = None, domain: Domain | None = None,
           cutoff: float | None = None) -> tuple[float, np.ndarray]:
    """Self-organization energy W (Eq. 2.11) and its gradient dW/dx (Eq. 3.4).

    Parameters
    ----------
    x : array (n, d)
        Positions (length).
    D : array (n,)
        The resolution D_p (length).
    neighbors : NeighborList
        A list over the same particles, half (each interacting pair once) or full (each pair in
        both rows): the results are the same, bitwise, for every layout of the same pairs.
    potential : str
        A key of :data:`POTENTIALS`.
    grad_D : array (n, d), optional
        Gradient of the resolution field at the particles (dimensionless) for the term
        (2V - rV') grad D_pq; None drops it (the paper neglects it once the field is resolved).
    domain : Domain or None
        Along its periodic axes pairs use the minimum image (None: free space).
    cutoff : float, optional
        The r* of lists built with r_c = r* D: each pair then uses V(r) - V(cutoff), so that W is
        continuous when pairs enter or leave the lists (the gradient is that of the paper's W,
        apart from the grad D term, which uses the shifted V).

    Returns
    -------
    W : float
        The energy (length^2), the correctly rounded sum of the per-particle energies
        ``sum_q D_pq^2 V_pq`` (each row summed in ascending neighbour order).
    grad : array (n, d)
        dW/dx (length).
    """
    xs = as_positions(x)
    n, d = xs.shape
    Ds = as_cutoffs(D, n)
    if not isinstance(neighbors, NeighborList) or neighbors.cross or neighbors.n != n:
        raise ValueError("energy() needs a NeighborList over the same particles (not a cross list)")
    check_layout(neighbors, n, "energy")
    full = (neighbors.canonical() if neighbors.full
            else NeighborList.from_pairs(n, *neighbors.pairs(sort=False), full=True))
    gD = np.zeros((n, d)) if grad_D is None else np.ascontiguousarray(grad_D, dtype=np.float64)
    if gD.shape != (n, d):
        raise ValueError(f"grad_D must have shape ({n}, {d})")
    e, g = energy_terms(xs, Ds, full, potential, gD, domain, cutoff)
    assert g is not None
    return exact_sum(None, e), g


def energy_terms(x: np.ndarray, D: np.ndarray, neighbors: NeighborList, potential: str = "V2",
                 grad_D: np.ndarray | None = None, domain: Domain | None = None,
                 cutoff: float | None = None, gradient: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """The terms of :func:`energy` row by row, for a full list in the summation order wanted (each row
    summed in its order; rows may be empty): per-particle energies ``e_p = sum_q D_pq^2 V_pq`` (n,)
    with W = sum_p e_p, and the gradient dW/dx (n, d), or None without ``gradient`` (the energies are
    the same).  Arrays as :func:`energy` checks them."""
    n, d = x.shape
    gD = np.zeros((n, d)) if grad_D is None else grad_D
    vshift = 0.0
    if cutoff is not None:
        if not (np.isfinite(cutoff) and cutoff > 0):
            raise ValueError("cutoff must be a finite number > 0")
        vshift = float(pair_potential(np.array([float(cutoff)]), potential)[0][0])
    e, g = _bridge.so_energy(x, D, gD, as_domain(domain, d).period, neighbors.offsets, neighbors.indices,
                             potential_code(potential), vshift, gradient, context="energy")
    return e, (g if gradient else None)
