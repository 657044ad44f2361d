"""arpy: adaptive-resolution particle methods with a Fortran core.

Public API
----------
neighbor_list(x, rc, *, method, symmetric, skin) -> NeighborList
    Neighbour lists under the rule |x_p - x_q| <= min(rc_p, rc_q) + skin.
NeighborList
    CSR container (offsets, indices) with pairs(), counts(), neighbors(p).
ar_benchmark(n_small, lam, d)
    The two-resolution benchmark distribution of Awile et al. (2012), §3.1.

Pure NumPy references of the core algorithms live in :mod:`arpy.reference`.
"""

from ._errors import ArpyError
from .distributions import ar_benchmark
from .neighbors import METHODS, NeighborList, neighbor_list

__version__ = "0.1.0"

__all__ = ["ArpyError", "METHODS", "NeighborList", "ar_benchmark", "neighbor_list", "__version__"]
