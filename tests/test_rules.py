"""The cutoff rules min, max and sum of the neighbour lists, against pure-NumPy brute force.

Every rule x method (brute, cell, ar) x domain (free space, periodic box, periodic along one axis with
walls along the others, a periodic box with lo != 0 and unequal edges) x form (half, full list) x skin
(0 and 2**-9) must list exactly the pairs of :func:`arpy.reference.brute_force_pairs` (minimum image
along the periodic axes).  The sets are adversarial and built from dyadic numbers, so that every
coordinate difference, image shift, squared distance and reach is exact and the reference and the core
must agree at the last bit: pairs exactly at the reach of each rule (also across periodic faces) and
one grid step beyond it, coincident particles, particles on the periodic faces (at lo and at hi: the
same point of the torus), cutoffs over six decades (five in 3D, where the AR tree's keys hold 20
levels), the largest reach of a pair just below half the smallest periodic edge.  Cross lists the same,
by both of their paths; lists at 1 and 2 threads are bitwise equal.
"""

from __future__ import annotations

import contextlib
import itertools

import numpy as np
import pytest

import arpy
from arpy import _bridge
from arpy.lists import search
from arpy.reference import brute_force_cross_pairs, brute_force_pairs, pair_reach

RULES = ("min", "max", "sum")
METHODS = ("brute", "cell", "ar")
SKINS = (0.0, 2.0 ** -9)
#: positions are multiples of this (and of the cutoffs' sums): every difference is exact
UNIT = 2.0 ** -12


def boxes(d: int) -> dict[str, tuple[np.ndarray, np.ndarray, list[bool] | None]]:
    """The domains of the matrix: name -> (lo, hi, periodic axes or None for free space)."""
    zero, two = np.zeros(d), np.full(d, 2.0)
    lo = np.array([-0.75, 0.5, -3.0])[:d]
    return {"free": (zero, two, None),
            "periodic": (zero, two, [True] * d),
            "mixed": (zero, two, [True] + [False] * (d - 1)),
            "shifted": (lo, lo + np.array([2.0, 3.0, 2.5])[:d], [True] * d)}


def as_domain(lo: np.ndarray, hi: np.ndarray, periodic: list[bool] | None) -> arpy.Domain | None:
    return None if periodic is None else arpy.Domain((lo, hi), periodic=periodic)


def period_of(lo: np.ndarray, hi: np.ndarray, periodic: list[bool] | None) -> np.ndarray | None:
    return None if periodic is None else np.where(periodic, hi - lo, 0.0)


def adversarial(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, periodic: list[bool] | None,
                rule: str, skin: float, decades: int, n: int = 120) -> tuple[np.ndarray, np.ndarray]:
    """(positions (m, d), cutoffs (m,)): n random grid points of the box, some on its faces, some
    coincident, with power-of-two cutoffs over 2**decades whose largest reach of a pair under
    ``rule`` lies just below half the smallest edge; then for each rule, pairs exactly at its reach
    and one grid step beyond it (wrapped across the faces of periodic axes)."""
    d = lo.size
    edge = float(np.min(hi - lo))
    # the largest cutoff: its pair's reach (2 rmax + skin under the sum rule) 2**-8 below edge / 2
    rmax = ((edge / 2 - 2.0 ** -8 - skin) / (2.0 if rule == "sum" else 1.0)) // UNIT * UNIT
    steps = np.round((hi - lo) / UNIT).astype(np.int64)
    x = lo + rng.integers(0, steps + 1, size=(n, d)) * UNIT
    x[: n // 8, 0] = lo[0]                               # on the faces (lo and hi of axis 0)
    x[n // 8: n // 4, 0] = hi[0]
    x[n // 4: n // 4 + n // 10] = x[n // 2: n // 2 + n // 10]       # coincident with others
    rc = rmax * 2.0 ** -rng.integers(0, decades + 1, size=n).astype(float)
    extra_x, extra_r = [], []
    for r in RULES:
        for p in rng.choice(n, size=12, replace=False):
            q_rc = rmax * 2.0 ** -float(rng.integers(0, decades + 1))
            reach = float(pair_reach(rc[p], q_rc, skin, r))
            for beyond in (0.0, UNIT):
                axis = int(rng.integers(d))
                y = x[p].copy()
                y[axis] += reach + beyond
                if periodic is not None and periodic[axis]:
                    y[axis] = lo[axis] + (y[axis] - lo[axis]) % (hi[axis] - lo[axis])
                elif y[axis] > hi[axis]:
                    y[axis] = x[p, axis] - reach - beyond
                    if y[axis] < lo[axis]:
                        continue
                extra_x.append(y)
                extra_r.append(q_rc)
    x = np.concatenate([x, np.array(extra_x)])
    rc = np.concatenate([rc, np.array(extra_r)])
    order = rng.permutation(x.shape[0])
    return np.ascontiguousarray(x[order]), rc[order]


def stored_pairs(nl: arpy.NeighborList) -> tuple[np.ndarray, np.ndarray]:
    """The (row, entry) pairs a list stores, sorted, from its CSR arrays alone."""
    rows = np.repeat(np.arange(nl.offsets.size - 1), np.diff(nl.offsets))
    cols = nl.indices.astype(np.int64)
    order = np.lexsort((cols, rows))
    return rows[order], cols[order]


def check_form(nl: arpy.NeighborList, ref: tuple[np.ndarray, np.ndarray], full: bool, what: str) -> None:
    """A half list stores each reference pair once (either way round), a full list both ways."""
    i, j = stored_pairs(nl)
    if full:
        want_i, want_j = np.concatenate([ref[0], ref[1]]), np.concatenate([ref[1], ref[0]])
    else:
        i, j = np.minimum(i, j), np.maximum(i, j)
        want_i, want_j = ref
    got, want = np.lexsort((j, i)), np.lexsort((want_j, want_i))
    assert np.array_equal(i[got], want_i[want]) and np.array_equal(j[got], want_j[want]), what


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("rule", RULES)
def test_every_method_domain_form_and_skin_lists_the_brute_force_pairs(d, rule):
    rng = np.random.default_rng(53 + d + 7 * RULES.index(rule))
    decades = 20 if d == 2 else 17
    for name, (lo, hi, periodic) in boxes(d).items():
        for skin in SKINS:
            x, rc = adversarial(rng, lo, hi, periodic, rule, skin, decades)
            ref = brute_force_pairs(x, rc, skin, period=period_of(lo, hi, periodic), rule=rule)
            assert ref[0].size > 30
            for method, full in itertools.product(METHODS, (False, True)):
                nl = arpy.neighbor_list(x, rc, method=method, full=full, skin=skin, rule=rule,
                                        domain=as_domain(lo, hi, periodic))
                check_form(nl, ref, full, f"{name} skin={skin} {method} full={full}")


def test_the_sets_hold_ties_that_tell_the_rules_apart():
    """The reference sees each rule's ties (pairs exactly at the reach, kept) and the pairs one step
    beyond (dropped), and the three rules give different lists on the same set."""
    rng = np.random.default_rng(1)
    lo, hi, periodic = boxes(2)["periodic"]
    x, rc = adversarial(rng, lo, hi, periodic, "sum", 0.0, 20)
    period = period_of(lo, hi, periodic)
    e = x[:, None, :] - x[None, :, :]
    e -= period * np.round(e / period)
    dist = np.sqrt((e ** 2).sum(axis=2))
    lists = {}
    for rule in RULES:
        reach = pair_reach(rc[:, None], rc[None, :], 0.0, rule)
        assert np.count_nonzero(np.triu(dist == reach, 1)) >= 5           # exact ties
        i, j = brute_force_pairs(x, rc, period=period, rule=rule)
        assert np.all(dist[i, j] <= reach[i, j])
        lists[rule] = set(zip(i.tolist(), j.tolist()))
    assert lists["min"] < lists["max"] < lists["sum"]
    assert np.count_nonzero(np.triu(dist == 0, 1)) > 5                   # coincident (also across faces)


@pytest.mark.parametrize("d", [2, 3])
def test_cross_lists_of_every_rule_and_domain_equal_brute_force(d, monkeypatch):
    """Query and reference sets cut from one adversarial set: every rule and domain, by testing
    every pair (few pairs) and by the lists of trees and of both sets together (many)."""
    rng = np.random.default_rng(11 + d)
    decades = 20 if d == 2 else 17
    for (name, (lo, hi, periodic)), rule in itertools.product(boxes(d).items(), RULES):
        x, rc = adversarial(rng, lo, hi, periodic, rule, 0.0, decades)
        query = rng.random(x.shape[0]) < 0.4
        xq, rq, xr, rr = x[query], rc[query], x[~query], rc[~query]
        ref = brute_force_cross_pairs(xq, rq, xr, rr, period=period_of(lo, hi, periodic), rule=rule)
        assert ref[0].size > 20
        for few in (True, False):
            monkeypatch.setattr(search, "BRUTE_CROSS_PAIRS", 1 << 17 if few else 0)
            nl = arpy.cross_neighbor_list(xq, rq, xr, rr, rule=rule, domain=as_domain(lo, hi, periodic))
            i, j = stored_pairs(nl)
            assert np.array_equal(i, ref[0]) and np.array_equal(j, ref[1]), f"{name} {rule} few={few}"
            assert all(np.all(np.diff(nl.indices[a:b]) > 0) for a, b in zip(nl.offsets[:-1], nl.offsets[1:]))


@pytest.mark.parametrize("d", [2, 3])
def test_few_queries_among_many_references_equal_brute_force(d, monkeypatch):
    """A few queries in a corner of many references (a repaired stencil): the search keeps only the
    references within reach of the queries' box, with the same pairs as brute force under every rule,
    pairs at exactly their reach along an axis across that box's faces included; and the same list
    as the search over all references."""
    rng = np.random.default_rng(40 + d)
    n = search.FEW_REFS + 3000
    xr = rng.random((n, d))
    rr = 10.0 ** rng.uniform(-2.5, -1.2, n)
    xq = 0.2 + 0.05 * rng.random((30, d))
    rq = 10.0 ** rng.uniform(-2.5, -1.2, 30)
    # the query of the largest cutoff lowest along axis 0, and below it references at the largest reach
    # a pair can have under each rule (and just inside it): on the face of the references kept
    top = int(np.argmax(rq))
    xq[top, 0] = xq[:, 0].min() - 0.01
    rr[:8] = rr.max()
    kept = []
    real = search.near_box
    monkeypatch.setattr(search, "near_box", lambda *a: kept.append(real(*a)) or kept[-1])
    for rule in RULES:
        reach = {"min": rq[top], "max": rr[0], "sum": rq[top] + rr[0]}[rule]
        for i, (axis, f) in enumerate(itertools.product(range(2), (1.0, 1 - 1e-9, 1 + 1e-9, 1 - 1e-12))):
            xr[i] = xq[top]
            xr[i, axis] -= f * reach
        ref = brute_force_cross_pairs(xq, rq, xr, rr, rule=rule)
        assert np.isin(np.arange(4), ref[1][ref[0] == top]).sum() >= 2, rule
        nl = arpy.cross_neighbor_list(xq, rq, xr, rr, rule=rule)
        assert 0 < kept[-1].size < n // 2, rule                     # (the search ran on the few)
        assert np.array_equal(stored_pairs(nl)[0], ref[0]) and np.array_equal(stored_pairs(nl)[1], ref[1]), rule
        assert nl.n_ref == n and nl.x_ref.shape == (n, d)
        monkeypatch.setattr(search, "FEW_REFS", 10 * n)             # (the search over all of them)
        whole = arpy.cross_neighbor_list(xq, rq, xr, rr, rule=rule)
        monkeypatch.setattr(search, "FEW_REFS", n - 1)
        assert np.array_equal(whole.offsets, nl.offsets) and np.array_equal(whole.indices, nl.indices)
        assert whole.indices.dtype == nl.indices.dtype
    far = arpy.cross_neighbor_list(xq + 5.0, rq, xr, rr)            # (no reference in reach)
    assert far.offsets.tolist() == [0] * 31 and far.n_ref == n
    # queries spread over the references' box: no filter (it would keep most of them), the same pairs
    calls = len(kept)
    spread = rng.random((30, d))
    nl = arpy.cross_neighbor_list(spread, rq, xr, rr)
    assert len(kept) == calls
    ref = brute_force_cross_pairs(spread, rq, xr, rr)
    assert np.array_equal(stored_pairs(nl)[0], ref[0]) and np.array_equal(stored_pairs(nl)[1], ref[1])


@contextlib.contextmanager
def threads(n: int):
    """n core threads; at 2, the parallel branches from small sizes on (as tests/test_threads.py)."""
    with arpy.num_threads(n):
        before = _bridge.set_parallel_thresholds(*((500, 50) if n > 1 else (0, 0)))
        try:
            yield
        finally:
            _bridge.set_parallel_thresholds(*before)


@pytest.mark.parametrize("d", [2, 3])
def test_lists_of_every_rule_are_bitwise_equal_at_one_and_two_threads(d):
    rng = np.random.default_rng(5 + d)
    n = 3000
    x = rng.random((n, d))
    rc = (0.004 if d == 2 else 0.008) * 2.0 ** (rng.random(n) * 4)       # levels of the AR tree
    torus = arpy.Domain([1.0] * d, periodic=True)
    for rule, method, dom, sym in itertools.product(RULES, ("cell", "ar"), (None, torus), (True, False)):
        got = []
        for t in (1, 2):
            with threads(t):
                nl = arpy.neighbor_list(x, rc, method=method, rule=rule, domain=dom, full=not sym, skin=0.001)
            got.append((nl.offsets, nl.indices))
        assert np.array_equal(got[0][0], got[1][0]) and np.array_equal(got[0][1], got[1][1]), (rule, method, dom)


@pytest.mark.parametrize("rule", RULES)
def test_lists_in_cell_order_follow_the_rule(rule):
    rng = np.random.default_rng(3)
    x = rng.random((300, 2))
    rc = 0.01 * 2.0 ** (rng.random(300) * 4)
    for method in METHODS:
        order, nl = arpy.neighbor_list_in_cell_order(x, rc, method=method, rule=rule)
        check_form(nl, brute_force_pairs(x[order], rc[order], rule=rule), False, method)


def test_the_periodic_limit_is_the_largest_reach_of_a_pair_under_the_rule():
    """Below half the smallest periodic edge: max(rc) + skin (min, max rules), 2 max(rc) + skin (sum
    rule); at or beyond it a clear error."""
    torus = arpy.Domain([2.0, 4.0], periodic=True)
    x = np.array([[0.5, 0.5], [1.5, 0.5]])
    for rule, limit in (("min", 1.0), ("max", 1.0), ("sum", 0.5)):
        arpy.neighbor_list(x, [limit - 2.0 ** -10 - 2.0 ** -9, 0.1], skin=2.0 ** -9, rule=rule, domain=torus)
        with pytest.raises(ValueError, match="periodic box too small" + (".*sum rule" if rule == "sum" else "")):
            arpy.neighbor_list(x, [limit - 2.0 ** -10, 0.1], skin=2.0 ** -9, rule=rule, domain=torus)
        with pytest.raises(ValueError, match="periodic box too small"):
            arpy.cross_neighbor_list(x, limit, x, 0.1, rule=rule, domain=torus)


def test_an_unknown_rule_is_refused():
    x = np.zeros((3, 2))
    for call in (lambda: arpy.neighbor_list(x, 0.1, rule="mean"),
                 lambda: arpy.neighbor_list_in_cell_order(x, 0.1, rule="MIN"),
                 lambda: arpy.cross_neighbor_list(x, 0.1, x, 0.1, rule="avg")):
        with pytest.raises(ValueError, match="unknown rule"):
            call()
