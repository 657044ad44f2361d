"""arpy: adaptive-resolution particle methods with a Fortran core.

Public API
----------
``Domain(box=None, *, periodic=False)``
    Free space, or a box whose axes are periodic or end at rigid walls; every
    function below that takes ``domain=`` takes one.
``neighbor_list(x, rc, *, method, full, skin, domain) -> NeighborList``
    Neighbour lists under the rule ``|x_p - x_q| <= min(rc_p, rc_q) + skin``;
    methods "cell" (uniform cell list), "ar" (adaptive-resolution cell list),
    "auto", "brute"; periodic axes by the minimum image.
``ARCellList(x, rc, *, domain, skin)``
    The AR cell tree (levels, cells, Op1-Op5), its Verlet lists and cross lists.
``cache_order(x, *, domain) -> perm``
    The permutation that sorts particles along the Morton curve (neighbours close in memory).
``neighbor_list_in_cell_order(x, rc, *, method, full, skin, domain) -> (order, NeighborList)``
    The search's own cell order and the list of the particles in it (no pass back to input order).
``cross_neighbor_list(x_query, rc_query, x_ref, rc_ref) -> NeighborList``
    Cross-set lists (rows = query points, indices into the reference set).
``periodic_ghosts(x, rc, domain, skin) -> (x_ghost, source)``
    Ghost particles for periodic boundaries.
``DCPSE(src_x, src_eps, col_x, col_eps, *, order, neighbors)``
    DC-PSE derivative, Laplacian and interpolation operators (scipy.sparse), free space.
``DomainDCPSE(x, eps, col_x, col_eps, *, domain, order, widen, max_lebesgue)``
    DC-PSE in a domain (periodic and mirror images) with the repair of failing stencils.
``NeighborList``
    CSR container (offsets, indices, half or full) that remembers its positions and domain: pairs(),
    counts() and neighbors(p) (every particle's neighbours), stored_counts() and stored_row(p) (the
    stored rows), distances(), vectors(), shifts() (minimum image), to_sparse() (scipy.sparse).
``nearest(x, k, *, y, domain) -> (dist, idx)``
    The k nearest neighbours (of every particle, or of query points y), minimum image.
``ar_benchmark(n_small, lam, d)``
    The two-resolution benchmark distribution of Awile et al. (2012), §3.1.
``bud_benchmark(h0, lam)``
    The budding-cell distribution of Awile et al. (2012), §3.2 (3D, spacing from curvature).
``quadtree_particles(spacing, lo, hi)``
    An adaptive 2D particle set following a wanted spacing function.
``surface.Bud(L, R, r, r_neck)``
    A sphere, a bud and a neck as an exact level set: curvatures, thickness, the
    monitor of Eq. 4.14, narrow bands (§4.6 of Reboux et al.).
``fields``
    Analytic test fields with exact derivatives (the tanh front of Eq. 4.1).
``adapt.resolution``
    The target resolution: monitors (Eq. 2.8, Eq. B.13), Eq. 2.9, r*, N*.
``adapt.forces``
    The pseudo-force potentials and the energy W with its gradient.
``self_organize(x, resolution | grad_f, *, D0, potential, domain, region, ...) -> Particles``
    The adaptation loop: fusion, insertion, gradient descent with line search.
``SampledResolution(x, D, rstar, domain)``, ``field_resolution(x, f, D, D0=...)``
    D_p given on an old particle set (from a DC-PSE gradient of f), for self_organize.
``Particles(x, D, rstar, ...)``
    A particle set, or a rank's share of one: positions, D, keys, fields, the domain, the ranks.
``plotting.plot_particles(ps)``
    Particle sets drawn as in the paper's figures.
``Simulation(particles, f, *, velocity | flow, nu, D0, integrator, reorganize_every)``
    The adaptive simulation of §3.2.2; cases (§4.1-4.3), remesh.RemeshedLPM (baseline).

``set_num_threads(n)``, ``get_num_threads()``, ``num_threads(n)`` (a ``with`` block)
    Threads of the core's parallel loops (default: OMP_NUM_THREADS, else every core); results
    do not depend on them, and every core call releases the GIL.  ``set_huge_pages(on)``: the
    core's large arrays on transparent huge pages (Linux; default on).

Pure NumPy references of the core algorithms live in :mod:`arpy.reference`.

``import arpy`` loads NumPy and the core only; each name above, and each submodule (``arpy.cases``,
``arpy.plotting``, ``arpy.distributed``, ...), is imported on first use.

Layout, by concept: :mod:`arpy.lists` (neighbour lists: the container, the searches, the AR cell
list, lists kept across calls), :mod:`arpy.dcpse` (DC-PSE operators, their repair, boundary
conditions), :mod:`arpy.adapt` (the target resolution, the pseudo-forces, self-organization),
:mod:`arpy.simulation`, :mod:`arpy.distributed` (the same over MPI ranks), :mod:`arpy.threads`
(the core's threads), :mod:`arpy.domain`, and the cases, references and I/O beside them.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from ._errors import ArpyError, TreeDepthError
from ._version import __version__
from .threads import get_num_threads, num_threads, set_huge_pages, set_num_threads

if TYPE_CHECKING:                                  # what the lazy names below are, for type checkers
    from . import adapt, cases, dcpse, fields, lists, surface
    from .adapt.organize import NotConvergedWarning, self_organize
    from .adapt.resolution import SampledResolution, field_resolution
    from .dcpse.domain import DomainDCPSE
    from .dcpse.kernel import DCPSE, DegenerateStencilError
    from .distributions import ar_benchmark, bud_benchmark, quadtree_particles
    from .domain import Domain, nearest, periodic_ghosts
    from .equations import NonFiniteError, StabilityError
    from .lists.ar import ARCellList
    from .lists.neighborlist import NeighborList
    from .lists.auto import AUTO_AR_WORK
    from .lists.search import METHODS, cache_order, cross_neighbor_list, neighbor_list, neighbor_list_in_cell_order
    from .particles import Particles
    from .simulation import Simulation

#: The public names imported on first use (module ``__getattr__``), each from its module: ``import arpy``
#: loads only NumPy and the core, not SciPy, the cases, plotting or MPI (tests/test_layout.py).
_LAZY = {
    "self_organize": "adapt.organize", "NotConvergedWarning": "adapt.organize", "SampledResolution": "adapt.resolution",
    "field_resolution": "adapt.resolution", "DomainDCPSE": "dcpse.domain", "DCPSE": "dcpse.kernel",
    "DegenerateStencilError": "dcpse.kernel", "ar_benchmark": "distributions", "bud_benchmark": "distributions",
    "quadtree_particles": "distributions", "Domain": "domain", "nearest": "domain", "periodic_ghosts": "domain",
    "NonFiniteError": "equations", "StabilityError": "equations", "ARCellList": "lists.ar", "NeighborList": "lists.neighborlist",
    "AUTO_AR_WORK": "lists.auto", "METHODS": "lists.search", "cache_order": "lists.search",
    "cross_neighbor_list": "lists.search", "neighbor_list": "lists.search",
    "neighbor_list_in_cell_order": "lists.search", "Particles": "particles", "Simulation": "simulation",
}

__all__ = [
    "ARCellList",
    "AUTO_AR_WORK",
    "ArpyError",
    "DCPSE",
    "DegenerateStencilError",
    "Domain",
    "DomainDCPSE",
    "METHODS",
    "NeighborList",
    "NonFiniteError",
    "NotConvergedWarning",
    "Particles",
    "SampledResolution",
    "Simulation",
    "StabilityError",
    "TreeDepthError",
    "ar_benchmark",
    "bud_benchmark",
    "cache_order",
    "cross_neighbor_list",
    "field_resolution",
    "get_num_threads",
    "nearest",
    "neighbor_list",
    "neighbor_list_in_cell_order",
    "num_threads",
    "periodic_ghosts",
    "quadtree_particles",
    "self_organize",
    "set_huge_pages",
    "set_num_threads",
    "__version__",
]


def __getattr__(name: str) -> object:
    """A public name of :data:`_LAZY` or a submodule (``arpy.cases``, ``arpy.plotting``, ...), imported
    on first use and kept."""
    if name in _LAZY:
        value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    elif name == "ParticleSet":                        # the earlier name of Particles: same arguments
        import warnings

        warnings.warn("arpy.ParticleSet is now arpy.Particles (same arguments and attributes)", DeprecationWarning,
                      stacklevel=2)
        return __getattr__("Particles")
    elif name.startswith("__"):
        raise AttributeError(f"module 'arpy' has no attribute {name!r}")
    else:
        try:
            value = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":
                raise
            raise AttributeError(f"module 'arpy' has no attribute {name!r}") from None
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__) | {"adapt", "cases", "dcpse", "fields", "lists", "surface"})
