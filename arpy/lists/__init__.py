"""Neighbour lists: the container, the searches, the AR cell list and lists kept across calls.

* :mod:`~arpy.lists.neighborlist`: :class:`~arpy.lists.neighborlist.NeighborList`, the CSR container;
* :mod:`~arpy.lists.search`: :func:`~arpy.lists.search.neighbor_list` (methods "cell", "ar", "brute",
  "auto"), lists in the search's cell order, cross-set lists and the cache (Morton) order;
* :mod:`~arpy.lists.auto`: how ``method="auto"`` chooses between the uniform and the AR list;
* :mod:`~arpy.lists.ar`: :class:`~arpy.lists.ar.ARCellList`, the adaptive-resolution cell tree of
  Awile et al. (2012);
* :mod:`~arpy.lists.reuse`: :class:`~arpy.lists.reuse.ReusedLists`, the lists of DC-PSE operators at
  moving particles, kept across calls (Verlet lists with a skin).
"""

from .ar import MAX_LEVEL, ARCellList, halo_bits
from .auto import AUTO_AR_WORK
from .neighborlist import NeighborList, collect_list, pair_order
from .reuse import ReusedLists
from .search import METHODS, cache_order, cross_neighbor_list, neighbor_list, neighbor_list_in_cell_order

__all__ = ["ARCellList", "AUTO_AR_WORK", "MAX_LEVEL", "METHODS", "NeighborList", "ReusedLists", "cache_order",
           "collect_list", "cross_neighbor_list", "halo_bits", "neighbor_list", "neighbor_list_in_cell_order",
           "pair_order"]
