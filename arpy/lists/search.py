"""Neighbour searches: :func:`neighbor_list` (methods "cell", "ar", "brute" and "auto"), the lists
of particles in the search's own cell order, cross-set lists, and the cache (Morton) order.

Particles p and q are neighbours iff ``|x_p - x_q| <= reach(p, q)``, the reach of the pair under
the cutoff rule: ``min(rc_p, rc_q) + skin`` (``rule="min"``, the default: the adaptive-resolution
"gather" rule; with one cutoff it is the usual fixed-radius rule), ``max(rc_p, rc_q) + skin``
(``"max"``, the symmetric rule of SPH with per-particle smoothing lengths) or
``(rc_p + rc_q) + skin`` (``"sum"``, contacts of spheres of radii rc: granular and DEM codes).  One
skin is added to the pair's reach, not to each cutoff (under the sum rule that is a skin, not two).
The reach is evaluated in this order in double precision and compared with the squared distance,
summed axis by axis, by every method (:mod:`arpy.reference.neighbors` does the same in NumPy).  A
particle is never its own neighbour; coincident particles are neighbours of each other.  The lists
come back in a :class:`arpy.lists.neighborlist.NeighborList`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from .. import _bridge
from .._bridge import core_exponent, lengths_exponent, raise_for_info, scaled
from .._codes import METHODS, RULES, STATUS
from .._errors import TreeDepthError
from .._validate import as_cutoffs, as_positions, column_extremes, non_finite_rows, resolve_full
from ..domain import Domain, as_domain
from .ar import ARCellList
from .auto import AUTO_AR_WORK, auto_work
from .neighborlist import NeighborList, collect_list, pair_order

__all__ = ["METHODS", "RULES", "cache_order", "cross_neighbor_list", "neighbor_list", "neighbor_list_in_cell_order"]




def neighbor_list(
    x: np.ndarray,
    rc: float | np.ndarray,
    *,
    method: str = "cell",
    full: bool = False,
    skin: float = 0.0,
    domain: Domain | None = None,
    rule: str = "min",
    symmetric: bool | None = None,
) -> NeighborList:
    """Build neighbour lists of particles with one or per-particle cutoff radii.

    Parameters
    ----------
    x : array, shape (n, d), d = 2 or 3
        Particle positions (any length unit).
    rc : float or array, shape (n,)
        Cutoff radii, same unit as ``x``; finite and > 0.
    method : {"cell", "ar", "auto", "brute"}
        ``"cell"``: uniform cell list (cell edge = the largest reach of a pair:
        largest cutoff + skin, under the sum rule twice the largest cutoff +
        skin), counting sort and half-shell pair iteration.  ``"ar"``:
        adaptive-resolution cell list (Awile et al. 2012), whose cost does not
        grow with the spread of cutoffs.  ``"auto"``: ``"ar"`` where the uniform
        list's estimated time under ``rule`` exceeds AUTO_AR_WORK times the AR
        list's (:func:`arpy.lists.auto.auto_work`, calibrated on particles with about 16
        neighbours each and on sparse ones, and under the max and sum rules on
        log-uniform and bimodal radii: the user guide says where it errs), else ``"cell"``.
        ``"brute"``: all pairs, O(n^2), for small sets and checks.
    full : bool
        False (default): a half list, each unordered pair once, in the row of either particle.  True:
        a full list, each pair in both rows.
    skin : float
        Verlet skin added to the reach of every pair (>= 0; same unit as ``x``).
    domain : Domain or None
        Where the particles live (default: free space).  Along periodic axes the
        lists hold the pairs by the minimum image; the particles must lie inside
        the box along those axes, and the largest reach of a pair (max(rc) +
        skin; sum rule: 2 max(rc) + skin) must be below half the smallest
        periodic edge.  The uniform list wraps its grid around the box (when
        that leaves 3 cells or more along every periodic axis); under the min
        rule the AR list queries the periodic images of the particles near the
        faces against the particles' own tree, and brute force (and a uniform
        grid too coarse to wrap) searches the particles with their images
        (:func:`arpy.periodic_ghosts`); under the max and sum rules every
        method lists the particles together with their images (those within
        their cutoff + the largest cutoff + skin of a face) and keeps the pairs
        of two particles and of a particle with an image.  Walls do not change
        the lists.
    rule : {"min", "max", "sum"}
        The cutoff rule (see the module's notes): p and q are neighbours iff
        ``|x_p - x_q| <= min(rc_p, rc_q) + skin`` (default),
        ``max(rc_p, rc_q) + skin`` or ``(rc_p + rc_q) + skin``.  The AR list
        finds a min-rule pair from its coarser particle (Algorithm 3: finer
        levels' stencils), a max- or sum-rule pair from its finer one: each
        particle searches its own level's half stencil and the full 3**d
        stencil around its cell on every coarser level; under the sum rule a
        particle's level is that of 2 rc + skin (see the user guide).
    symmetric : bool, optional
        Deprecated name of ``not full`` (a DeprecationWarning).

    Returns
    -------
    NeighborList
        CSR lists; ``pairs()`` gives the sorted unordered pairs.  The list holds ``x`` (a reference,
        see :class:`~arpy.lists.neighborlist.NeighborList`) and ``domain``: its ``distances()``,
        ``vectors()``, ``shifts()`` and ``to_sparse()`` need no arguments, and
        ``quantities("ijdDS")`` gives ASE's and vesin's per-pair arrays in one pass.

    Raises
    ------
    ValueError, TypeError
        On bad shapes, dtypes, non-finite positions or non-positive cutoffs.

    Examples
    --------
    Uniform random points with one cutoff, then cutoffs that differ by a factor 10:

    >>> import numpy as np
    >>> import arpy
    >>> x = np.random.default_rng(0).random((1000, 2))
    >>> nl = arpy.neighbor_list(x, 0.05)
    >>> i, j = nl.pairs()
    >>> bool(np.all(i < j)), len(i) == len(nl)
    (True, True)
    >>> full = arpy.neighbor_list(x, 0.05, full=True)
    >>> len(full) == 2 * len(nl)
    True
    >>> rc = np.where(x[:, 0] < 0.5, 0.01, 0.1)
    >>> ar = arpy.neighbor_list(x, rc, method="ar")
    >>> brute = arpy.neighbor_list(x, rc, method="brute")
    >>> all(np.array_equal(a, b) for a, b in zip(ar.pairs(), brute.pairs()))
    True

    In a periodic unit square, pairs across the edges are found by the minimum image:

    >>> torus = arpy.Domain([1.0, 1.0], periodic=True)
    >>> arpy.neighbor_list(np.array([[0.01, 0.5], [0.99, 0.5]]), 0.05, domain=torus).pairs()
    (array([0]), array([1]))

    Two spheres of radii 0.5 and 0.25 touching (distance 0.75): a contact under the sum rule only:

    >>> touching = np.array([[0.0, 0.0], [0.75, 0.0]])
    >>> [len(arpy.neighbor_list(touching, [0.5, 0.25], rule=r)) for r in ("min", "max", "sum")]
    [0, 0, 1]
    """
    full = resolve_full(full, symmetric, "neighbor_list")
    xs, rcs, skin = list_input(x, rc, method, skin, "neighbor_list", rule)
    dom = as_domain(domain, xs.shape[1])
    x0, n = xs, xs.shape[0]
    if n == 0:
        return NeighborList(np.zeros(1, np.int64), np.zeros(0, np.int32), full=full, x=x0, domain=domain)
    method, auto = resolve_method(method, xs, rcs, skin, rule)
    code = RULES[rule]
    # the periodic box, if any (walls do not change the lists)
    pbox = dom if dom.any_periodic else None
    if pbox is None:
        return free_list(xs, rcs, skin, method, auto, full, in_cells=False, domain=domain, rule=code)[0]
    # one pass for the extremes of the positions (per axis) and of the cutoffs: they give the
    # scaling and the checks of the box
    x_min, x_max = column_extremes(xs)
    r_ext = np.array([rcs.min(), rcs.max()])
    k = lengths_exponent([x_min, x_max, skin, pbox.lo, pbox.hi], [r_ext])
    if k:                      # (the images x +- (hi - lo) must not overflow either)
        xs, rcs, skin = scaled(k, xs), scaled(k, rcs), scaled(k, skin)
        x_min, x_max, r_ext = scaled(k, x_min), scaled(k, x_max), scaled(k, r_ext)
        pbox = pbox.scaled(k)
    box = pbox.for_dim(xs.shape[1])
    # the particles in the box, the box large enough
    box.check_images(xs, rcs, skin, extremes=(x_min, x_max, float(r_ext[0]), float(r_ext[1])), rule=rule)
    lo, hi = box.lo, box.hi
    assert lo is not None and hi is not None
    handle, nnz = searched(
        lambda m: _bridge.periodic_neighbors(xs, rcs, skin, m, not full, lo, hi, box.periodic, code),
        method, auto, "neighbor_list")
    return collect_list(handle, n, nnz, full=full, x=x0, domain=domain)


def neighbor_list_in_cell_order(
    x: np.ndarray,
    rc: float | np.ndarray,
    *,
    method: str = "cell",
    full: bool = False,
    skin: float = 0.0,
    domain: Domain | None = None,
    rule: str = "min",
    symmetric: bool | None = None,
) -> tuple[np.ndarray, NeighborList]:
    """The particles' cell order and their neighbour list in it.

    The search sorts the particles into its cells anyway (``"cell"``: the uniform grid's cells;
    ``"ar"``: the AR tree's levels and cells, :attr:`ARCellList.order`); :func:`neighbor_list` then
    puts every row back into input order and renames every entry, a pass that writes the list at
    random.  This function skips that pass: it returns the cell order and the list of the
    particles in that order, so a caller who keeps its particles sorted this way reads and writes
    memory in order.  Particles already in the returned order give that order back unchanged (the
    identity), and their list in one sequential pass.

    Parameters
    ----------
    x, rc, method, full, skin, rule, symmetric
        As for :func:`neighbor_list` (``"brute"`` keeps the input order).
    domain : Domain or None
        As for :func:`neighbor_list`.  With periodic axes the order is the Morton order of the box
        (:func:`cache_order`: the search images particles across the faces, so its cells are not
        one order of the particles), and the list is :func:`neighbor_list` of the particles in it.

    Returns
    -------
    order : int64 array, shape (n,)
        ``x[order]`` are the particles in cell order; reorder every per-particle array the same
        way.  ``np.argsort(order)`` maps back.
    nl : NeighborList
        The list of ``x[order]``: row ``a`` and entry ``a`` mean particle ``order[a]`` of the input.
        Its positions ``nl.x`` are ``x[order]`` (x itself when the order is the identity).

    Examples
    --------
    >>> import numpy as np
    >>> import arpy
    >>> x = np.random.default_rng(0).random((1000, 2))
    >>> order, nl = arpy.neighbor_list_in_cell_order(x, 0.05)
    >>> x_sorted = x[order]
    >>> same = arpy.neighbor_list(x_sorted, 0.05)
    >>> all(np.array_equal(a, b) for a, b in zip(nl.pairs(), same.pairs()))
    True
    >>> bool(np.array_equal(arpy.neighbor_list_in_cell_order(x_sorted, 0.05)[0], np.arange(1000)))
    True
    """
    full = resolve_full(full, symmetric, "neighbor_list_in_cell_order")
    xs, rcs, skin = list_input(x, rc, method, skin, "neighbor_list_in_cell_order", rule)
    n = xs.shape[0]
    if n == 0:
        return np.zeros(0, np.int64), NeighborList(np.zeros(1, np.int64), np.zeros(0, np.int32), full=full, x=xs,
                                                   domain=domain)
    if as_domain(domain, xs.shape[1]).any_periodic:
        order = cache_order(xs, domain=domain)
        if not np.array_equal(order, np.arange(n)):
            xs, rcs = xs[order], rcs[order]
        return order, neighbor_list(xs, rcs, method=method, full=full, skin=skin, domain=domain, rule=rule)
    method, auto = resolve_method(method, xs, rcs, skin, rule)
    nl, order = free_list(xs, rcs, skin, method, auto, full, in_cells=True, domain=domain, rule=RULES[rule])
    assert order is not None
    return order, nl


def list_input(x: np.ndarray, rc: float | np.ndarray, method: str, skin: float,
               context: str, rule: str = "min") -> tuple[np.ndarray, np.ndarray, float]:
    """(positions (n, d), cutoffs (n,), skin) of a list search, checked; ValueError on a bad method,
    rule or skin (the positions and cutoffs are checked by as_positions and as_cutoffs)."""
    if method not in METHODS and method != "auto":
        raise ValueError(f"unknown method {method!r}; choose one of {sorted(METHODS) + ['auto']}")
    check_rule(rule, context)
    xs = as_positions(x)
    rcs = as_cutoffs(rc, xs.shape[0])
    skin = float(skin)
    if not (np.isfinite(skin) and skin >= 0.0):
        raise ValueError(f"{context}: skin must be a finite number >= 0, got {skin}")
    return xs, rcs, skin


def check_rule(rule: str, context: str) -> None:
    """ValueError unless ``rule`` names a cutoff rule of :data:`RULES`."""
    if not (isinstance(rule, str) and rule in RULES):
        raise ValueError(f"{context}: unknown rule {rule!r}; choose one of {sorted(RULES)}")


def free_list(xs: np.ndarray, rcs: np.ndarray, skin: float, method: str, auto: bool, full: bool,
              in_cells: bool, domain: Domain | None = None, rule: int = RULES["min"]
              ) -> tuple[NeighborList, np.ndarray | None]:
    """(the free-space list of checked particles under the rule code ``rule``, None) or,
    ``in_cells``, (the list of the particles in the search's cell order, that order); the list
    holds the positions (in its order) and ``domain`` (one without periodic axes)."""
    order = np.empty(xs.shape[0] if in_cells else 0, np.int64)         # (written by the core)

    def run(xk: np.ndarray, rk: np.ndarray, sk: float, code: int) -> tuple[int, int, int, int]:
        return _bridge.neighbors(xk, rk, sk, code, not full, in_cells, order, rule)

    handle, nnz = searched_in_range(run, xs, rcs, skin, method, auto, "neighbor_list")
    if in_cells and not np.array_equal(order, np.arange(xs.shape[0])):
        xs = xs[order]                          # (one gather; none for particles kept in this order)
    nl = collect_list(handle, xs.shape[0], nnz, full=full, x=xs, domain=domain)
    return nl, (order if in_cells else None)


def resolve_method(method: str, xs: np.ndarray, rcs: np.ndarray, skin: float, rule: str = "min"
                   ) -> tuple[str, bool]:
    """(the search method, whether it was chosen by "auto"): "auto" is "ar" where the uniform list's
    estimated time under ``rule`` is more than AUTO_AR_WORK times the AR list's
    (:func:`arpy.lists.auto.auto_work`), else "cell"."""
    if method != "auto":
        return method, False
    w_cell, w_ar = auto_work(xs, rcs, skin, rule)
    return ("ar" if w_cell > AUTO_AR_WORK * w_ar else "cell"), True


def searched(search: Callable[[int], tuple[int, int, int, int]], method: str, auto: bool,
             context: str, on_range: Callable[[], tuple[int, int]] | None = None) -> tuple[int, int]:
    """(handle, entries) of the list ``search(method code)`` publishes; a method chosen by "auto"
    whose AR tree cannot hold the cutoffs' levels is retried with the uniform list.  When the
    core reports lengths out of its range, ``on_range()`` answers instead, if given."""
    handle, nnz, info, bad = search(METHODS[method])
    if info == STATUS["ERR_DEPTH"] and auto:
        # the AR tree's keys cannot hold this many levels: the uniform list can
        handle, nnz, info, bad = search(METHODS["cell"])
    if info == STATUS["ERR_RANGE"] and on_range is not None:
        return on_range()
    raise_for_info(info, bad, context=context)
    return handle, nnz


def searched_in_range(run: Callable[[np.ndarray, np.ndarray, float, int], tuple[int, int, int, int]],
                      xs: np.ndarray, rcs: np.ndarray, skin: float, method: str, auto: bool,
                      context: str) -> tuple[int, int]:
    """:func:`searched` for ``run(positions, cutoffs, skin, method code)`` on the lengths as they
    are: the core checks their range in its first pass over the particles, so the scaling by a
    power of two (:func:`lengths_exponent`, two more passes) happens only when it reports them out
    of it."""
    def rescaled() -> tuple[int, int]:
        k = lengths_exponent([xs, skin], [rcs])
        if not k:                                        # (the core's range error stands)
            return searched(lambda code: run(xs, rcs, skin, code), method, auto, context)
        xk, rk, sk = scaled(k, xs), scaled(k, rcs), scaled(k, skin)
        return searched(lambda code: run(xk, rk, sk, code), method, auto, context)

    return searched(lambda code: run(xs, rcs, skin, code), method, auto, context, on_range=rescaled)


#: Bits per axis of the cache order's grid (2D, 3D): the AR tree's deepest level, 60-bit codes.
CACHE_ORDER_BITS = {2: 30, 3: 20}


def cache_order(x: np.ndarray, *, domain: Domain | None = None) -> np.ndarray:
    """The permutation that puts particles in cache order: along the Morton (Z-order) curve.

    A cube over the particles (the box of a bounded ``domain``, else their bounding box, with
    the longest edge on every axis) is cut into 2**30 (2D) or 2**20 (3D) cells per axis, and
    the particles are sorted by the Morton code of their cell (axis 1 the most significant
    bit), ties by index.  Particles next to each other in this order are close in space, so
    neighbour lists, DC-PSE assembly and the loops over particle pairs read the data of a
    particle's neighbours from nearby memory instead of from anywhere in the arrays.

    Parameters
    ----------
    x : array, shape (n, d), d = 2 or 3
        Particle positions; finite.
    domain : Domain or None
        Its box, if it has one, anchors the curve (points outside it go to the nearest cell).

    Returns
    -------
    perm : int64 array, shape (n,)
        ``x[perm]`` is in cache order; reorder every per-particle array the same way.
        ``np.argsort(perm)`` maps back.

    Examples
    --------
    >>> import numpy as np
    >>> import arpy
    >>> x = np.random.default_rng(0).random((10_000, 2))
    >>> perm = arpy.cache_order(x)
    >>> steps = np.linalg.norm(np.diff(x[perm], axis=0), axis=1)
    >>> bool(np.median(steps) < 0.02 < np.median(np.linalg.norm(np.diff(x, axis=0), axis=1)))
    True
    """
    xs = as_positions(x)
    n, d = xs.shape
    dom = as_domain(domain, d)
    if n < 2:
        return np.arange(n, dtype=np.int64)
    mins, maxs = column_extremes(xs)                        # (NaN and Inf show in them)
    if not (np.all(np.isfinite(mins)) and np.all(np.isfinite(maxs))):
        raise ValueError(f"cache_order: position of particle {non_finite_rows(xs)[0]} is not finite (NaN or Inf)")
    box = dom if dom.bounded else None
    if box is not None:
        assert box.lo is not None and box.hi is not None
        lo, hi = np.asarray(box.lo, np.float64), np.asarray(box.hi, np.float64)
    else:
        lo, hi = mins, maxs
    half = float(np.max(hi / 2 - lo / 2))           # half the cube's edge (never overflows)
    if not half > 0:
        return np.arange(n, dtype=np.int64)
    # lengths brought into the core's range by a power of two (exact): edge and cells finite
    k = core_exponent(float(np.abs(np.concatenate([mins, maxs, lo, hi])).max()), half)
    if k:
        xs, lo, hi = scaled(k, xs), scaled(k, lo), scaled(k, hi)
    edge = float(np.max(hi - lo))
    return _bridge.cache_order(xs, lo, math.ldexp(1.0, CACHE_ORDER_BITS[d]) / edge).astype(np.int64)


def cross_neighbor_list(x_query: np.ndarray, rc_query: float | np.ndarray,
                        x_ref: np.ndarray, rc_ref: float | np.ndarray, *, rule: str = "min",
                        domain: Domain | None = None) -> NeighborList:
    """Cross-set neighbour list: for every query point, the reference particles within reach.

    Query i and reference particle q are neighbours iff ``|x_i - x_q| <= reach``, the reach of the
    pair under ``rule``: ``min(rc_query_i, rc_ref_q)`` (default), ``max(...)`` or
    ``rc_query_i + rc_ref_q`` (see :func:`neighbor_list`; no skin).  Up to
    :data:`BRUTE_CROSS_PAIRS` query-reference pairs in free space, every pair is tested.  Beyond,
    under the min rule in free space, an AR cell list is built on the reference set (queries may
    lie anywhere, also outside its bounding box; where the cutoffs span more levels than its keys
    hold, a uniform cell list).  Otherwise (the max and sum rules, periodic domains) the list of
    both sets together (:func:`neighbor_list`, method "auto", in the domain) gives the pairs of a
    query and a reference particle.

    Parameters
    ----------
    x_query : array (m, d)
        Query points (length).
    rc_query : float or array (m,)
        Their cutoffs (length, > 0).
    x_ref : array (n, d)
        Reference particles (length).
    rc_ref : float or array (n,)
        Their cutoffs (length, > 0).
    rule : {"min", "max", "sum"}
        The cutoff rule.
    domain : Domain or None
        Where both sets live (default: free space).  Along periodic axes the pairs are found by the
        minimum image (both sets inside the box, the largest reach of a pair below half the
        smallest periodic edge); walls do not change the list.

    Returns
    -------
    NeighborList
        One row per query point, ``indices`` into the reference set, each row ascending
        (``cross=True``; ``pairs()`` gives (query, reference) pairs); it holds both sets' positions
        (``x``, ``x_ref``) and the domain, so its ``distances()`` and ``to_sparse()`` need no arguments.

    Examples
    --------
    >>> import numpy as np
    >>> import arpy
    >>> x_ref = np.array([[0.0, 0.0], [1.0, 0.0]])
    >>> x_query = np.array([[0.05, 0.0], [0.5, 0.0], [0.9, 0.0]])
    >>> cross = arpy.cross_neighbor_list(x_query, 0.2, x_ref, 0.2)
    >>> cross
    NeighborList(n=3, entries=2, cross, n_ref=2)
    >>> cross.pairs()
    (array([0, 2]), array([0, 1]))

    Across the faces of a periodic box:

    >>> torus = arpy.Domain([1.0, 1.0], periodic=True)
    >>> arpy.cross_neighbor_list([[0.98, 0.5]], 0.05, [[0.02, 0.5]], 0.05, domain=torus).pairs()
    (array([0]), array([0]))
    """
    check_rule(rule, "cross_neighbor_list")
    periodic = domain is not None and as_domain(domain, np.shape(x_ref)[-1]).any_periodic
    kept = None if periodic else _refs_in_reach(x_query, rc_query, x_ref, rc_ref, RULES[rule])
    if kept is not None:            # (the same rows from the references that can be in them)
        near, xq, xr, rr = kept
        if near.size == 0:
            return NeighborList(np.zeros(xq.shape[0] + 1, np.int64), np.zeros(0, np.int32), full=True,
                                n_ref=xr.shape[0], x=xq, x_ref=xr)
        sub = cross_neighbor_list(xq, rc_query, xr[near], rr[near], rule=rule)
        return NeighborList(sub.offsets, near[sub.indices].astype(np.int32), full=True, n_ref=xr.shape[0],
                            x=xq, x_ref=xr, domain=sub.domain)
    if not periodic:
        few = _cross_brute(x_query, rc_query, x_ref, rc_ref, RULES[rule])
        if few is not None:
            return few
        if rule == "min":
            try:
                tree = ARCellList(x_ref, rc_ref)
            except TreeDepthError:
                return _cross_by_union(x_query, rc_query, x_ref, rc_ref)
            return tree.cross_list(x_query, rc_query)
    return _cross_by_union(x_query, rc_query, x_ref, rc_ref, rule, domain)


#: Over more reference particles than this, :func:`cross_neighbor_list` in free space first keeps those
#: within reach of the queries' bounding box (when that leaves at most half of them): a few queries
#: among many references (a repaired stencil, a small set of new points) build no tree over them all.
FEW_REFS = 4096


def _refs_in_reach(x_query, rc_query, x_ref, rc_ref, rule: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The reference particles that can lie within reach of a query, ascending: all but those farther
    than R (1 + 1e-6) along an axis from the queries' bounding box, R the largest reach a pair can
    have under ``rule`` (the margin lies above the rounding of the pair test |x_i - x_q|^2 <= r^2: the
    lists are the same), with the queries' positions and the references' positions and cutoffs as the
    search takes them: (indices, x_query, x_ref, rc_ref).  None if that keeps more than half of them
    (or under :data:`FEW_REFS`), and for input the search must judge (it raises the errors; references
    not finite are kept)."""
    try:
        xq, xr = as_positions(x_query), as_positions(x_ref)
        m, n = xq.shape[0], xr.shape[0]
        if n <= FEW_REFS or m == 0 or xq.shape[1] != xr.shape[1]:
            return None
        lo, hi = column_extremes(xq)
        big_q = float(as_cutoffs(rc_query, m).max())
        # (queries whose box, grown by their own reach, covers most of the references' box keep most of
        # them: known without reading the references' cutoffs)
        rlo, rhi = column_extremes(xr)
        span = rhi - rlo
        if np.all(span > 0) and np.prod(np.clip(np.minimum(hi + big_q, rhi) - np.maximum(lo - big_q, rlo), 0.0, None)
                                        / span) > 0.5:
            return None
        rr = as_cutoffs(rc_ref, n)
        big_r = float(rr.max())
    except (ValueError, TypeError):
        return None
    reach = {RULES["max"]: max(big_q, big_r), RULES["sum"]: big_q + big_r}.get(rule, min(big_q, big_r))
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.isfinite(reach)):
        return None
    near = near_box(xr, lo, hi, reach * (1.0 + 1e-6))
    return (near, xq, xr, rr) if 2 * near.size <= n else None


def near_box(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, reach: float) -> np.ndarray:
    """The points of x (n, d) that are not farther than ``reach`` from the box [lo, hi] along any axis,
    by the rounded differences ``lo - x`` and ``x - hi`` (points with NaN kept): indices, ascending.

    A difference rounds monotonically, so a point left out has ``fl(y - x) > reach`` along some axis
    for every point y of the box: its squared distance to each of them, as the list builders and
    :func:`arpy.nearest` compute it, is at least ``reach**2`` rounded (callers add a margin).
    """
    far = np.zeros(x.shape[0], dtype=bool)
    for axis in range(x.shape[1]):
        far |= (lo[axis] - x[:, axis] > reach) | (x[:, axis] - hi[axis] > reach)
    return np.flatnonzero(~far)


#: Up to this many query-reference pairs, :func:`cross_neighbor_list` tests them all instead of
#: building a tree on the references (a few queries, or two small sets: the build would cost more).
BRUTE_CROSS_PAIRS = 1 << 17


def _cross_brute(x_query, rc_query, x_ref, rc_ref, rule: int = RULES["min"]) -> NeighborList | None:
    """The cross list by testing every pair (the rows the tree gives, bit for bit), when there are
    at most :data:`BRUTE_CROSS_PAIRS` of them; None otherwise, and for input the tree's path must
    judge (it raises the errors)."""
    try:
        xq0, xr0 = xq, xr = as_positions(x_query), as_positions(x_ref)
        m, n = xq.shape[0], xr.shape[0]
        if not (0 < m * n <= BRUTE_CROSS_PAIRS and xq.shape[1] == xr.shape[1]):
            return None
        rq, rr = as_cutoffs(rc_query, m), as_cutoffs(rc_ref, n)
        k = lengths_exponent([xq, xr], [rq, rr])
    except (ValueError, TypeError):
        return None
    if k:
        xq, rq, xr, rr = scaled(k, xq), scaled(k, rq), scaled(k, xr), scaled(k, rr)
    handle, nnz, info, _ = _bridge.cross_brute(xq, rq, xr, rr, rule)
    if info != STATUS["OK"]:
        return None
    nl = collect_list(handle, m, nnz, full=True)
    return NeighborList(nl.offsets, nl.indices, full=True, n_ref=n, x=xq0, x_ref=xr0)


def source_rows(x_src: np.ndarray, rc_src: np.ndarray, n: int, itself: bool = True) -> NeighborList:
    """The rows of the first n sources against all of them, each row ascending, from the half
    list of the sources, which tests each pair once and shares each cell's stencil among its
    particles.  With ``itself`` these are ``cross_neighbor_list(x_src[:n], rc_src[:n], x_src,
    rc_src)`` (the particles of a DC-PSE operator at the particles, ahead of their ghosts); without,
    and n = m, the full list of the sources, canonical (``neighbor_list(x_src, rc_src,
    full=True).canonical()``).

    Row p holds every source q with ``|x_p - x_q| <= min(rc_p, rc_q)`` by the list builders' test
    (the cross list's, bit for bit), p itself only with ``itself``.

    Parameters
    ----------
    x_src : array (m, d)
        Source positions (length); the first n are the rows' points.
    rc_src : array (m,)
        Their cutoffs (length, > 0).
    n : int
        The rows: the first n sources (0 <= n <= m).
    itself : bool
        Each row holds its own source.
    """
    xs = as_positions(x_src)
    m = xs.shape[0]
    rcs = as_cutoffs(rc_src, m)
    if not 0 <= n <= m:
        raise ValueError(f"source_rows: n must lie in [0, {m}], got {n}")
    n_ref = None if (n == m and not itself) else m
    x_rows, x_ref = (xs, None) if n_ref is None else (xs[:n], xs)
    if m == 0:
        return NeighborList(np.zeros(1, np.int64), np.zeros(0, np.int32), full=True, n_ref=n_ref, x=x_rows,
                            x_ref=x_ref)
    # (DC-PSE's sources are adapted particles, the small cutoffs crowded where the particles are:
    # auto_work counts that crowding)
    method, auto = resolve_method("auto", xs, rcs, 0.0)
    handle, nnz = searched_in_range(
        lambda xk, rk, _, code: _bridge.source_rows(xk, rk, n, code, itself),
        xs, rcs, 0.0, method, auto, "source_rows")
    nl = collect_list(handle, n, nnz, full=True)
    return NeighborList(nl.offsets, nl.indices, full=True, n_ref=n_ref, x=x_rows, x_ref=x_ref)


def _cross_by_union(x_query, rc_query, x_ref, rc_ref, rule: str = "min", domain: Domain | None = None,
                    method: str = "cell") -> NeighborList:
    """The cross list from the list of both sets together (:func:`neighbor_list` under ``rule`` in
    ``domain``; method "cell" under the min rule in free space, where it serves cutoffs too widely
    spread for the AR tree's levels, else "auto"): the pairs between a reference particle and a
    query, rows ascending."""
    xr, xq = as_positions(x_ref), as_positions(x_query)
    if xq.shape[1] != xr.shape[1]:
        raise ValueError(f"query points must have d = {xr.shape[1]} columns, got shape {xq.shape}")
    n_ref, m = xr.shape[0], xq.shape[0]
    rr, rq = as_cutoffs(rc_ref, n_ref), as_cutoffs(rc_query, m)
    if rule != "min" or domain is not None:
        method = "auto"
    i, j = neighbor_list(np.concatenate([xr, xq]), np.concatenate([rr, rq]), method=method, rule=rule,
                         domain=domain).pairs()
    cross = (i < n_ref) & (j >= n_ref)              # i < j: the reference particle is i
    q, r = j[cross] - n_ref, i[cross]
    order = pair_order(q, r, n_ref)
    offsets = np.zeros(m + 1, np.int64)
    np.cumsum(np.bincount(q, minlength=m), out=offsets[1:])
    return NeighborList(offsets, r[order].astype(np.int32), full=True, n_ref=n_ref, x=xq, x_ref=xr,
                        domain=domain)
