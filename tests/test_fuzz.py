"""Fuzzing every public entry point with hypothesis.

Inputs span the whole range of finite doubles (subnormals included), with
NaN and Inf sprinkled in, random shapes, dtypes and orders.  Each call must
either return the answer of an independent reference (exact rational
arithmetic for the neighbour rule) or raise a documented exception
(ValueError, TypeError, MemoryError, arpy.ArpyError and their subclasses).
A watchdog turns a hang into a failure: faulthandler ends the process after
WATCHDOG seconds, even inside a Fortran call that holds the GIL.
"""

from __future__ import annotations

import faulthandler
import itertools
import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

import arpy
from arpy._errors import TreeDepthError

WATCHDOG = 120.0
DOCUMENTED = (ValueError, TypeError, MemoryError, arpy.ArpyError)
FUZZ = settings(deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(autouse=True)
def watchdog():
    faulthandler.dump_traceback_later(WATCHDOG, exit=True)
    yield
    faulthandler.cancel_dump_traceback_later()


# ---------------------------------------------------------------- strategies
@st.composite
def particle_sets(draw, max_n: int = 14, sprinkle: bool = True):
    """(x (n, d), rc (n,) or scalar, skin): points clustered at one random scale 2**e with cutoffs
    near that scale, or raw doubles anywhere; occasionally NaN/Inf or a bad cutoff."""
    n = draw(st.integers(0, max_n))
    d = draw(st.sampled_from([2, 3]))
    e = draw(st.integers(-1070, 1020))
    if draw(st.booleans()):
        x = np.ldexp(np.array(draw(st.lists(st.floats(-4, 4), min_size=n * d, max_size=n * d))).reshape(n, d), e)
        rc = np.ldexp(np.array(draw(st.lists(st.floats(0.05, 4), min_size=n, max_size=n))), e)
    else:
        x = np.array(draw(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64),
                                   min_size=n * d, max_size=n * d))).reshape(n, d)
        rc = np.array(draw(st.lists(st.floats(min_value=5e-324, max_value=1.7e308), min_size=n, max_size=n)))
    if n and sprinkle and draw(st.integers(0, 9)) == 0:
        x[draw(st.integers(0, n - 1)), draw(st.integers(0, d - 1))] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    if n and sprinkle and draw(st.integers(0, 9)) == 0:
        rc[draw(st.integers(0, n - 1))] = draw(st.sampled_from([np.nan, np.inf, 0.0, -1.0]))
    skin = draw(st.sampled_from([0.0, 0.0, float(np.ldexp(0.1, e)), -1.0, np.nan]))
    if n and draw(st.booleans()) and np.all(rc == rc[0]):
        rc = float(rc[0])
    return x, rc, skin


def exact_pairs(x: np.ndarray, rc: np.ndarray, skin: float, box: np.ndarray | None = None):
    """Pairs under |x_p - x_q| <= min(rc_p, rc_q) + skin in exact rational arithmetic (with a
    periodic box of edges ``box``: the minimum image over shifts of -1, 0, 1 edges).
    Returns (sure, near): ``near`` are the pairs within rounding of the rule's boundary, where
    the core may decide either way: 2**-40 of the cutoff, plus with a box one unit in the last
    place of its edge (the core's images x +- L are rounded)."""
    n, d = x.shape
    fx = [[Fraction(float(v)) for v in row] for row in x]
    shifts = [(0,) * d] if box is None else list(itertools.product((-1, 0, 1), repeat=d))
    fbox = [Fraction(0)] * d if box is None else [Fraction(float(b)) for b in box]
    slack_abs = Fraction(0) if box is None else Fraction(float(np.spacing(np.max(box))))
    sure, near = set(), set()
    for p in range(n):
        for q in range(p + 1, n):
            r = Fraction(float(min(rc[p], rc[q]))) + Fraction(skin)
            slack = r / 2 ** 40 + slack_abs
            d2 = min(sum((a - b - s * L) ** 2 for a, b, s, L in zip(fx[p], fx[q], sh, fbox)) for sh in shifts)
            if abs(d2 - r * r) <= slack * (2 * r + slack):
                near.add((p, q))
            elif d2 <= r * r:
                sure.add((p, q))
    return sure, near


def valid_input(x, rc, skin) -> bool:
    return bool(np.all(np.isfinite(x)) and np.all(np.isfinite(rc)) and np.all(np.asarray(rc) > 0)
                and np.isfinite(skin) and skin >= 0)


def span_log2(x, rc, skin) -> float:
    """log2 of (largest |coordinate|, cutoff or skin) / smallest cutoff."""
    big = max(float(np.max(np.abs(x))) if x.size else 0.0, float(np.max(rc)), skin)
    return math.log2(big) - math.log2(float(np.min(rc)))


def as_set(i, j):
    return set(zip(np.asarray(i).tolist(), np.asarray(j).tolist()))


# ---------------------------------------------------------------- neighbour lists
@FUZZ
@given(data=particle_sets(), method=st.sampled_from(["brute", "cell", "ar", "auto"]), symmetric=st.booleans())
def test_neighbor_list_fuzz(data, method, symmetric):
    x, rc, skin = data
    try:
        nl = arpy.neighbor_list(x, rc, method=method, symmetric=symmetric, skin=skin)
    except DOCUMENTED as err:
        rcs = np.broadcast_to(rc, (len(x),))
        if not valid_input(x, rcs, skin) or len(x) == 0:
            return
        span = span_log2(x, rcs, skin)
        if isinstance(err, TreeDepthError):
            assert method == "ar" and span > 19, err
            return
        assert "range" in str(err) and span > 990, err
        return
    rcs = np.broadcast_to(np.asarray(rc, dtype=np.float64), (len(x),))
    assert valid_input(x, rcs, skin), "bad input accepted"
    sure, near = exact_pairs(x, rcs, skin)
    got = as_set(*nl.pairs())
    assert sure <= got <= sure | near
    assert len(nl) == (1 if symmetric else 2) * len(got)


@FUZZ
@given(data=particle_sets(max_n=10), queries=particle_sets(max_n=8, sprinkle=False))
def test_cross_list_and_tree_fuzz(data, queries):
    x, rc, skin = data
    xq, rq, _ = queries
    assume(len(x) and x.shape[1] == xq.shape[1])
    rcs = np.broadcast_to(np.asarray(rc, dtype=np.float64), (len(x),))
    rqs = np.broadcast_to(np.asarray(rq, dtype=np.float64), (len(xq),))
    try:
        tree = arpy.ARCellList(x, rc)
        verlet = tree.verlet_list()
        cross = tree.cross_list(xq, rq)
    except DOCUMENTED as err:
        if valid_input(x, rcs, 0.0) and valid_input(xq, rqs, 0.0) and len(xq):
            assert isinstance(err, TreeDepthError) or "range" in str(err), err
        return
    sure, near = exact_pairs(x, rcs, 0.0)
    assert sure <= as_set(*verlet.pairs()) <= sure | near
    both_x, both_r = np.concatenate([x, xq]), np.concatenate([rcs, rqs])
    sure, near = exact_pairs(both_x, both_r, 0.0)
    n = len(x)
    keep = lambda s: {(q - n, p) for p, q in s if p < n <= q}          # noqa: E731
    got = as_set(*cross.pairs())
    assert keep(sure) <= got <= keep(sure) | keep(near)
    for p in range(len(xq)):
        cell = tree.find_cell(xq[p], 1)
        inside = np.all(xq[p] >= tree.lo) and np.all(xq[p] <= tree.lo + tree.edge)
        assert (cell is not None) == bool(inside)


@FUZZ
@given(data=particle_sets(max_n=10), box_exp=st.one_of(st.none(), st.integers(-1000, 1000)))
def test_periodic_fuzz(data, box_exp):
    """Periodic lists against the exact minimum-image rule."""
    x, rc, skin = data
    d = x.shape[1]
    if box_exp is None:                 # a box a little over 8 times the largest cutoff
        top = float(np.nanmax(np.where(np.isfinite(rc), rc, 0.0), initial=1.0))
        box_exp = min(math.frexp(top)[1] + 3, 1023)
    box = np.full(d, math.ldexp(1.0, box_exp))
    with np.errstate(invalid="ignore"):
        x = np.mod(x, box)
    try:
        nl = arpy.neighbor_list(x, rc, domain=arpy.Domain(box, periodic=True), skin=skin)
        xg, src = arpy.periodic_ghosts(x, rc, arpy.Domain(box, periodic=True), skin)
    except DOCUMENTED:
        return
    rcs = np.broadcast_to(np.asarray(rc, dtype=np.float64), (len(x),))
    assert valid_input(x, rcs, skin) and np.all((x >= 0) & (x <= box))
    assert np.all(np.max(np.abs(xg - x[src]), axis=1) <= box.max()) if len(xg) else True
    sure, near = exact_pairs(x, rcs, skin, box)
    got = as_set(*nl.pairs())
    assert sure <= got <= sure | near, (x.tolist(), rcs.tolist(), box.tolist(), skin)


# ---------------------------------------------------------------- DC-PSE
@FUZZ
@given(data=particle_sets(max_n=30), order=st.integers(-1, 15), c=st.sampled_from([2.0, 0.5, 0.0, np.inf, np.nan]),
       max_cond=st.sampled_from([1e12, 1e3, 0.5, np.inf, np.nan]), off=st.booleans())
def test_dcpse_fuzz(data, order, c, max_cond, off):
    x, eps, _ = data
    col = x[: len(x) // 2] * 0.5 if off else None
    try:
        op = arpy.DCPSE(x, eps, col, None, order=order, c=c, max_cond=max_cond, strict=False)
        grads = op.gradient()
    except DOCUMENTED:
        return
    assert 2 <= order <= arpy.dcpse.kernel.MAX_ORDER and c > 0 and max_cond > 1
    for g in grads:
        assert np.all(np.isfinite(g.data))
    # rows with a valid, well-conditioned stencil differentiate a linear function exactly
    ok = np.setdiff1d(np.flatnonzero(op.cond < 1e8), op.failed)
    if ok.size and np.max(np.abs(x)) < 1e150:
        f = x[:, 0] - 0.5 * x[:, 1]
        g = grads[0] @ f
        scale = abs(grads[0]) @ np.abs(f - (f.mean() if off else 0.0)) + np.abs(f).max()
        assert np.all(np.abs(g[ok] - 1.0) <= 1e-6 * (1.0 + scale[ok] + op.cond[ok] * 1e-9))


# ---------------------------------------------------------------- self-organization
@FUZZ
@given(data=particle_sets(max_n=8), D=st.floats(min_value=5e-324, max_value=1e308), periodic=st.booleans(),
       adapt=st.booleans(), max_particles=st.sampled_from([2000, 0, np.nan]))
def test_self_organize_fuzz(data, D, periodic, adapt, max_particles):
    x = np.clip(data[0], 0.0, 1.0)                # NaN stays NaN
    box = [1.0] * x.shape[1]
    try:
        ps = arpy.self_organize(x, lambda p: np.full(len(p), D), domain=arpy.Domain(box, periodic=periodic),
                                adapt_number=adapt, max_iter=3, max_particles=max_particles, seed=1)
    except DOCUMENTED + (RuntimeError,) as err:
        if isinstance(err, RuntimeError) and not isinstance(err, arpy.ArpyError):
            assert "max_particles" in str(err)
        return
    assert len(x) and max_particles >= 1 and np.all(np.isfinite(x))
    assert np.all(np.isfinite(ps.x)) and np.all((ps.x >= 0) & (ps.x <= 1))
    assert np.all(np.isfinite(ps.D)) and np.all(ps.D > 0)


# ---------------------------------------------------------------- dtypes, memory orders, shapes
@FUZZ
@given(n=st.integers(0, 40), d=st.integers(0, 4), dtype=st.sampled_from(
    ["float64", "float32", "float16", "int64", "int32", "uint8", "bool", "complex128", "object", "U3"]),
    order=st.sampled_from(["C", "F", "strided", "transposed"]), seed=st.integers(0, 2 ** 16),
    method=st.sampled_from(["brute", "cell", "ar", "auto"]))
def test_dtypes_orders_and_shapes_fuzz(n, d, dtype, order, seed, method):
    """Any array-like: the list of its float64 values, or TypeError / ValueError (shapes other
    than (n, 2) or (n, 3); dtypes that are not real numbers: complex, object, strings, bool)."""
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 6, (n, d)) if dtype in ("uint8", "bool", "int32", "int64") else rng.random((n, d)) * 5
    x = base.astype(dtype)
    if order == "F":
        x = np.asfortranarray(x)
    elif order == "strided":
        x = np.repeat(x, 2, axis=0)[::2]
    elif order == "transposed":
        x = np.ascontiguousarray(x.T).T
    try:
        nl = arpy.neighbor_list(x, 1.5, method=method)
    except (TypeError, ValueError):
        assert d not in (2, 3) or dtype in ("complex128", "object", "U3", "bool"), (d, dtype)
        return
    assert d in (2, 3) and dtype not in ("complex128", "object", "U3", "bool")
    want = arpy.neighbor_list(np.array(x, dtype=np.float64), 1.5, method="brute")
    assert as_set(*nl.pairs()) == as_set(*want.pairs())
