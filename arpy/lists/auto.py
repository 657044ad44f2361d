"""How ``method="auto"`` chooses between the uniform and the AR cell list: a cost model of both lists
(:func:`auto_work`) evaluated on statistics of the particles that the core gathers in one call
(:func:`auto_terms`), and its constants, calibrated by ``benchmarks/auto_calibration.py``
(``benchmarks/results/auto_calibration.md``).  :func:`arpy.lists.search.neighbor_list` takes the AR list
where the uniform list's estimated time is more than :data:`AUTO_AR_WORK` times the AR list's, under
every cutoff rule (the max and sum rules' search from the fine side: ``benchmarks/results/auto_rules.md``).
"""

from __future__ import annotations

import math
from typing import Any, cast

import numpy as np

from .. import _bridge
from .._codes import RULES

__all__ = ["AUTO_AR_WORK", "auto_terms", "auto_work", "model_times"]

#: method="auto" uses the AR list when the uniform list's estimated time (:func:`auto_work`) is more
#: than this many times the AR list's, else the uniform list.  Above 1: the AR list gains less from more
#: threads (its tree build is partly serial; from one thread to two the calibration's AR lists ran a
#: median 1.13 to 1.72 times faster, the uniform lists 1.26 to 1.84), so where the model sees a near tie
#: the uniform list is taken (benchmarks/results/auto_calibration.md: with 1.0 one set, 1.34 times the
#: faster list at two threads; 1.05 to 1.15 keep every set within 1.2 times at one and two threads).
AUTO_AR_WORK = 1.05
#: The cost model :func:`auto_work` evaluates, nanoseconds of one thread's CPU time on the calibration
#: machine: the uniform list's cost per particle (2D, 3D) and per distance check; the AR list's per
#: particle (2D, 3D), per check on the particle's own level, per check on a finer level and per cell of
#: a finer level's stencil looked up by a descending particle, plus "lookup_decade" per decade of N
#: above "lookup_from" (the hashed levels' tables outgrow the caches); and its tree's tables: per cell a
#: particle enters on a hashed level ("hashed", plus "hashed_decade" per decade of N) and per cell of its
#: dense levels beyond one per particle ("empty").  Fitted by least squares (relative errors,
#: non-negative) on the CPU times of the random polydisperse sets and the AR paper's benchmark, 2D and 3D,
#: N = 1e4 to 1e6, and the tables' costs on what that leaves of the AR lists of sparse bimodal sets (one
#: neighbour per particle) (``benchmarks/auto_calibration.py --fit``).  Under the max and sum rules
#: "coarse" and "up" take the place of "finer" and the lookup costs: per check on a coarser level and per
#: cell of a coarser level's stencil looked up, fitted on what the other costs leave of the AR lists of
#: random sets with log-uniform and bimodal radii under both rules (``benchmarks/auto_rules.py --fit``).
AUTO_CELL_COST: dict[str, Any] = {"particle": {2: 32.55, 3: 64.71}, "check": 1.50}
#: The AR list's costs in the model of :func:`auto_work` (ns; see :data:`AUTO_CELL_COST`).
AUTO_AR_COST: dict[str, Any] = {"particle": {2: 34.85, 3: 30.13}, "own": 1.68, "finer": 5.22, "lookup": 5.80,
                                "lookup_decade": 4.98, "lookup_from": 1e4, "hashed": 83.12, "hashed_decade": 120.22,
                                "empty": 16.83, "coarse": 0.72, "up": 10.33}
#: Cutoffs and positions :func:`auto_work` samples (by a hash of each position) for the levels, the box
#: and the crowding.
AUTO_SAMPLE = 1024
#: ... but at most one in AUTO_SAMPLE_SHARE of them, and no fewer than AUTO_SAMPLE_LEAST: the
#: statistics cost about 0.1 us per sampled particle and a list 35 to 65 ns per particle, so the
#: samples add at most about 4 % to the faster list (the pass that draws them about 3 ns per particle).
AUTO_SAMPLE_SHARE = 64
AUTO_SAMPLE_LEAST = 128
#: Particles :func:`auto_work` bins (a larger sample by the same hash, holding the first) to see which
#: levels lie near each sampled one, on a grid of at most AUTO_FINE_CELLS cells per particle binned;
#: at most one in AUTO_FINE_SHARE of them (about 20 ns each).
AUTO_FINE_SAMPLE = 1024
AUTO_FINE_SHARE = 16
AUTO_FINE_CELLS = 4
#: The crowding is counted on the sampled particles whose hash is below a q-th of the sample's bound, q
#: as large as leaves about this many pairs of them in one another's blocks when evenly spread (its
#: relative noise about 1 / sqrt(this)).
AUTO_CROWD_PAIRS = 1000.0
#: The grids on which :func:`auto_work` counts have at most this many cells per position binned (their
#: memory: 8 bytes a cell).  Coarser cells count the particles of a coarse block as if evenly spread
#: within it, which misses crowding on smaller scales: with one cell per sampled position (a former
#: bound) the adapted pulse's particles in half its box (what a rank holds at P = 2) looked 2.5 times
#: less crowded than they are.
AUTO_CROWD_CELLS = 64
#: The grid of each level on which :func:`auto_work` counts the sampled particles of that level near
#: one another has at most this many cells per particle (a level's grid spans its particles' box).
AUTO_LEVEL_CELLS = 16

#: The statistics of :func:`auto_terms`: (W_cell, W_own, W_finer, W_look, W_hash, W_dense).
Terms = tuple[float, float, float, float, float, float]


def auto_work(x: np.ndarray, rc: np.ndarray, skin: float = 0.0, rule: str = "min") -> tuple[float, float]:
    """The times of the uniform and of the AR list on particles ``x`` with cutoffs ``rc``, estimated
    from cheap statistics (nanoseconds of one thread on the calibration machine): what
    ``method="auto"`` compares.

    The statistics come from a sample of about m particles, those whose position hash falls below
    m / n (m = :data:`AUTO_SAMPLE`, but at most one in :data:`AUTO_SAMPLE_SHARE` of them and no fewer
    than :data:`AUTO_SAMPLE_LEAST`; all of them when there are no more), each standing for n / m.
    (Not every (n/m)-th particle: particles given in lattice order would give a sample on a coarser
    lattice, none of them near another, and another order of the same particles another sample.)
    ``occ(c, k)`` is the number of k particles spread evenly over the sample's bounding box (each edge
    at least the largest cutoff) that fall in a block of ``3**d`` cells of edge c.  The crowding f_s of
    a sampled particle s is the number of sampled particles in the block of ``3**d`` cells of edge r_max
    around it, scaled to n, over ``occ(r_max, n)`` (1 for evenly spread particles); it is counted on the
    sampled particles whose hash is below a q-th of the sample's bound, q as large as leaves about
    :data:`AUTO_CROWD_PAIRS` pairs among evenly spread ones, and F is its mean.

    - Uniform list, cells of edge r_max = max(rc) + skin, each pair tested once:
      ``T_cell = A_d n + B W_cell``, ``W_cell = n / 2 * occ(r_max, n) * F`` checks
      (:data:`AUTO_CELL_COST`: A_d per particle, B per check).
    - AR list (:data:`AUTO_AR_COST`): a particle of cutoff r (+ skin) sits on the level k whose cell
      edge ``c_k = r_min * 2**k`` is the smallest above r (r_min just above min(rc) + skin).  A pair is
      found from its coarser particle, which tests the later particles of its own level's stencil and
      the stencils of finer levels, descending only while they hold finer particles:
      ``T_ar = C_d n + E_own W_own + E_finer W_finer + (E_look + E_decade log10(max(n, n_0) / n_0)) W_look
      + (E_hash + E_hash_decade log10(max(n, n_0) / n_0)) W_hash + E_empty max(W_dense - n, 0)``
      with ``W_own = n / 2 * (n / m) * mean_s o_s`` (o_s: the other sampled particles of s's level in
      the ``3**d`` cells of edge c_k around it), ``W_finer = n * mean_s f_s * sum_{i < k_s} occ(c_i,
      n_i)`` (n_i: the particles on level i, from the sample) and ``W_look = n * mean_s 3**d (k_s -
      k'_s)``, k'_s the finest level (at most k_s) among the particles of a larger sample in the ``3**d``
      cells of edge r_max around s: the levels s descends through.  That sample is drawn by the same hash
      (the particles whose hash is below m_f / n, m_f = :data:`AUTO_FINE_SAMPLE` but at most one in
      :data:`AUTO_FINE_SHARE` and no fewer than :data:`AUTO_SAMPLE_LEAST`), so the smaller of the two
      samples lies within the larger (with these constants, the first within the second); s itself, on
      its own level, does not change k'_s.  The tree's tables: from its coarsest level below its root
      (edge ``r_min * 2**K``, K the fewest doublings that reach the sample's largest extent) to the
      finest, a level is kept dense (an array over its box) when the box of the sampled particles on it or
      finer has at most 4 cells per such particle (their number scaled to n) plus 1024, within a total of
      4 n + 4096 cells, and is hashed otherwise; ``W_dense`` is the dense levels' cells, ``W_hash = n *
      mean_s`` (the hashed levels among s's own and the coarser ones, each of which it enters a cell of).
      Both grow where the particles are sparse against their cutoffs (a few neighbours each or fewer),
      where the AR list costs several times more per particle.  With one level, the terms of W_own,
      W_finer and W_look are ``E_own n / 2 * occ(c_k, n) * F``.
    - Under the max and sum rules (``rule``) a particle's cutoff r above is its level reach, rc + skin
      (max) or 2 rc + skin (sum), so the uniform list's cells (edge r_max) are as wide as the largest
      reach of a pair; the AR list finds a pair from its finer particle, which tests the later particles
      of its own level's stencil and the particles of the full stencil on every coarser level that holds
      particles, so W_finer and W_look give way to ``W_coarse = n * mean_s f_s * sum_{j > k_s} occ(c_j,
      N_j)`` and ``W_up = n * mean_s 3**d * #{j > k_s: N_j > 0}``, costed "coarse" and "up"
      (:data:`AUTO_AR_COST`), where N_j is the number of all the particles on level j (not of the
      sample: a few large particles, which a sample misses, make a level every particle searches; one
      more pass over the cutoffs).

    The counts run in the core (arpy_crowding.auto_terms, one call) on grids of at most
    :data:`AUTO_CROWD_CELLS`, :data:`AUTO_LEVEL_CELLS` (a level's grid spans its sampled particles'
    box) and :data:`AUTO_FINE_CELLS` cells per position binned; where a grid would have more, its cells
    are coarser (edge ``(prod(edges) / most)**(1 / d)``) and the counts are scaled to the wanted block
    as if evenly spread within the coarse one.  Their cost: one pass over every particle's cutoff and
    position (the samples are drawn by a hash of the position, so the same particles in any order give
    the same statistics; in parallel) and a few over the samples: about 0.06 ms at N = 1e4, 0.5 ms at
    1e5 and 3.5 ms at 1e6 on the calibration machine (one thread; benchmarks/results/auto_calibration.md
    lists them for every set).

    Parameters
    ----------
    x : array (n, d), n >= 1
        Positions (length).
    rc : array (n,)
        Cutoffs (length).
    skin : float
        Added to every cutoff (length, >= 0).
    rule : {"min", "max", "sum"}
        The cutoff rule of the lists (:func:`arpy.neighbor_list`).

    Returns
    -------
    (T_cell, T_ar) : floats
        Estimated times of the uniform and of the AR list (ns); (0, 0) if the cutoffs are not all
        finite and > 0, the per-particle terms alone if a sampled position is not finite (the search
        then reports them).  :func:`auto_terms` gives the six W, :func:`model_times` the T from them.
    """
    n, d = x.shape
    w = auto_terms(x, rc, skin, rule)
    if w[0] < 0:
        return 0.0, 0.0
    return model_times(n, d, *w, rule=rule)


def auto_terms(x: np.ndarray, rc: np.ndarray, skin: float = 0.0, rule: str = "min") -> Terms:
    """(W_cell, W_own, W_finer, W_look, W_hash, W_dense) of :func:`auto_work`'s model for particles ``x``
    (n, d) with cutoffs ``rc`` (n,) and ``skin`` under ``rule``: the uniform list's distance checks
    (crowded), the AR list's checks on the particles' own levels and on finer levels, its descending
    particles' stencil cells looked up, the cells its particles enter on its tree's hashed levels and the
    cells of its dense levels; under the max and sum rules W_coarse and W_up in place of W_finer and W_look.
    (-1, ...) if the cutoffs are not all finite and > 0, zeros if a sampled position is not finite."""
    w = _bridge.auto_terms(x, rc, skin, [AUTO_SAMPLE, AUTO_SAMPLE_LEAST, AUTO_SAMPLE_SHARE, AUTO_FINE_SAMPLE,
                                          AUTO_FINE_CELLS, AUTO_CROWD_PAIRS, AUTO_CROWD_CELLS, AUTO_LEVEL_CELLS,
                                          AUTO_FINE_SHARE], RULES[rule])
    return cast(Terms, tuple(float(v) for v in w))


def n_decades(n: int, ar: dict[str, Any] | None = None) -> float:
    """log10(max(n, n_0) / n_0), n_0 = ``ar["lookup_from"]`` (default :data:`AUTO_AR_COST`): the decades of
    n over which the AR list's hashed tables outgrow the caches, in :func:`model_times`."""
    n0 = (AUTO_AR_COST if ar is None else ar)["lookup_from"]
    return math.log10(max(n, n0) / n0)


def model_times(n: int, d: int, w_cell: float, w_own: float, w_finer: float, w_look: float, w_hash: float,
                w_dense: float, cell: dict[str, Any] | None = None, ar: dict[str, Any] | None = None,
                rule: str = "min") -> tuple[float, float]:
    """(T_cell, T_ar) in ns: :func:`auto_work`'s cost model (``cell``, ``ar``: its costs, by default
    :data:`AUTO_CELL_COST` and :data:`AUTO_AR_COST`) applied to n particles in d dimensions with the
    statistics of :func:`auto_terms` under ``rule``."""
    cell = AUTO_CELL_COST if cell is None else cell
    ar = AUTO_AR_COST if ar is None else ar
    decades = n_decades(n, ar)
    if rule == "min":
        search = ar["finer"] * w_finer + (ar["lookup"] + ar["lookup_decade"] * decades) * w_look
    else:
        search = ar["coarse"] * w_finer + ar["up"] * w_look
    return (cell["particle"][d] * n + cell["check"] * w_cell,
            ar["particle"][d] * n + ar["own"] * w_own + search
            + (ar["hashed"] + ar["hashed_decade"] * decades) * w_hash + ar["empty"] * max(w_dense - n, 0.0))
