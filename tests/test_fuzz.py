"""Fuzzing every public entry point with hypothesis.

Most generated inputs are valid, built so by the strategies: points clustered at one random scale
2**e (e from -1000 to 1000) with cutoffs near it, jittered lattices of random spacing and jitter
with core sizes from the spacing (DC-PSE), boxes that fit the cutoffs (periodic lists).  A valid
input must give the answer of an independent reference (exact rational arithmetic for the neighbour
rule, exactness on polynomials for DC-PSE); refusing it fails the test, but for the documented
limits on the lengths' range (which a few sets of raw doubles anywhere exceed), which the test
predicts.  The other inputs carry one defect each (NaN or Inf, a bad cutoff, skin or parameter, a box
too small, a point outside it) and must be refused with a documented exception (ValueError,
TypeError, MemoryError, arpy.ArpyError and their subclasses); accepting one fails the test.  Each
test counts the examples that reach its numerical check and requires at least REACH of them to
(:class:`Reach`; its message says what happened to the others).  A watchdog turns a hang into a
failure: faulthandler ends the process after WATCHDOG seconds, even inside a Fortran call that holds
the GIL.
"""

from __future__ import annotations

import faulthandler
import itertools
import math
from collections import Counter
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

import arpy
from arpy._codes import RANGE_EXP
from arpy._errors import TreeDepthError
from arpy.dcpse.kernel import MAX_ORDER, n_unknowns

WATCHDOG = 120.0
DOCUMENTED = (ValueError, TypeError, MemoryError, arpy.ArpyError)
FUZZ = settings(deadline=None, suppress_health_check=[HealthCheck.too_slow])
#: The least share of a test's examples that must reach its numerical check.
REACH = 0.8


@pytest.fixture(autouse=True)
def watchdog():
    faulthandler.dump_traceback_later(WATCHDOG, exit=True)
    yield
    faulthandler.cancel_dump_traceback_later()


class Reach:
    """How many examples of a fuzz test reach its numerical check (counted over the whole run,
    shrinking included; a failing example fails the test before this is asked), and what happened
    to the others (also hypothesis ``event``s)."""

    def __init__(self) -> None:
        self.examples = 0
        self.checked = 0
        self.events: Counter[str] = Counter()

    def example(self) -> None:
        self.examples += 1

    def note(self, what: str) -> None:
        self.events[what] += 1
        event(what)

    def check(self) -> None:
        self.checked += 1
        self.note("reached the numerical check")

    def refused(self, valid: bool, err: BaseException) -> None:
        self.note(f"refused {'a valid input at a documented limit' if valid else 'an invalid input'}: "
                  f"{type(err).__name__}")

    def assert_most(self, share: float = REACH) -> None:
        assert self.examples > 0
        assert self.checked >= share * self.examples, \
            f"only {self.checked} of {self.examples} examples reached the numerical check (need {share:.0%}): " \
            f"{dict(self.events)}"


# ---------------------------------------------------------------- strategies
#: One example in DEFECT_ODDS carries a defect (an input to refuse); one particle set in RAW_ODDS is
#: raw doubles anywhere (valid, but its lengths may span more than the core's range: refused at a
#: documented limit).
DEFECT_ODDS = 10
RAW_ODDS = 32


def one_in(draw, odds: int) -> bool:
    """True about one time in ``odds`` (fewer: hypothesis draws the ends of a range, here 0 and
    odds - 1, more often than its middle, odds // 2, which is the one taken)."""
    return draw(st.integers(0, odds - 1)) == odds // 2


def defective(draw) -> bool:
    """Whether this example carries a defect (one in DEFECT_ODDS)."""
    return one_in(draw, DEFECT_ODDS)


@st.composite
def particle_sets(draw, max_n: int = 14, min_n: int = 0, defects: bool = True, raw: bool = True,
                  d: int | None = None, e: int | None = None):
    """(x (n, d), rc (n,) or scalar, skin): points clustered at one random scale 2**e (e from -1000
    to 1000) with cutoffs and skin near that scale (one set in four: cutoffs over twelve octaves, a
    deep AR tree), or (with ``raw``, one in RAW_ODDS) raw doubles anywhere; with ``defects``, one in
    DEFECT_ODDS with a NaN or Inf position, a bad cutoff or a bad skin."""
    n = draw(st.integers(min_n, max_n))
    d = draw(st.sampled_from([2, 3])) if d is None else d
    e = draw(st.integers(-1000, 1000)) if e is None else e
    if raw and one_in(draw, RAW_ODDS):
        x = np.array(draw(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64),
                                   min_size=n * d, max_size=n * d))).reshape(n, d)
        rc = np.array(draw(st.lists(st.floats(min_value=5e-324, max_value=1.7e308), min_size=n, max_size=n)))
        skin = 0.0
    else:
        x = np.ldexp(np.array(draw(st.lists(st.floats(-4, 4), min_size=n * d, max_size=n * d))).reshape(n, d), e)
        rc = np.ldexp(np.array(draw(st.lists(st.floats(0.05, 4), min_size=n, max_size=n))), e)
        if one_in(draw, 4):
            rc = np.ldexp(rc, -np.array(draw(st.lists(st.integers(0, 12), min_size=n, max_size=n)), dtype=int))
        skin = math.ldexp(draw(st.sampled_from([0.0, 0.0, 0.1, 0.5])), e)
    if n and draw(st.booleans()) and np.all(rc == rc[0]):
        rc = float(rc[0])
    if defects and defective(draw):
        what = draw(st.sampled_from(["x", "rc", "skin"] if n else ["skin"]))
        if what == "x":
            bad = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
            x[draw(st.integers(0, n - 1)), draw(st.integers(0, d - 1))] = bad
        elif what == "rc":
            bad = draw(st.sampled_from([np.nan, np.inf, 0.0, -0.0, -1.0]))
            if isinstance(rc, float):
                rc = bad
            else:
                rc[draw(st.integers(0, n - 1))] = bad
        else:
            skin = draw(st.sampled_from([-1.0, -5e-324, np.nan, np.inf]))
    return x, rc, skin


@st.composite
def sets_and_queries(draw):
    """A particle set of at least one particle and query points (no defects, no raw doubles) in the
    same dimension, at the same scale but one time in eight (up to 2**+-60 away)."""
    d = draw(st.sampled_from([2, 3]))
    e = draw(st.integers(-960, 960))
    data = draw(particle_sets(max_n=8, min_n=1, d=d, e=e))
    other = one_in(draw, 8)
    eq = e + draw(st.integers(-60, 60)) if other else e
    queries = draw(particle_sets(max_n=6, defects=False, raw=False, d=d, e=eq))
    return data, queries


@st.composite
def periodic_sets(draw, max_n: int = 10):
    """(x, rc, skin, box): a periodic box of edges 2**E times 1, 1.25, 1.5 or 2 - 2**-52 (E from -1000
    to 1000), points
    anywhere in it (on its faces too), cutoffs down to 2**-12 of the edge with cutoff + skin at most
    0.45 of the shortest edge; one in DEFECT_ODDS with a defect: a cutoff of half the edge or more, a
    point outside the box, a NaN or Inf position, a bad cutoff or skin."""
    n = draw(st.integers(1, max_n))
    d = draw(st.sampled_from([2, 3]))
    box = np.ldexp(np.array(draw(st.lists(st.sampled_from([1.0, 1.0, 1.5, 1.25, 2.0 - 2.0 ** -52]),
                                          min_size=d, max_size=d))), draw(st.integers(-1000, 1000)))
    x = np.array(draw(st.lists(st.floats(0, 1), min_size=n * d, max_size=n * d))).reshape(n, d) * box
    short = float(box.min())
    skin = short * draw(st.sampled_from([0.0, 0.0, 0.01, 0.05]))
    rc = (0.45 * short - skin) * np.array(draw(st.lists(st.floats(2.0 ** -12, 1), min_size=n, max_size=n)))
    if defective(draw):
        what = draw(st.sampled_from(["small", "outside", "x", "rc", "skin"]))
        k, a = draw(st.integers(0, n - 1)), draw(st.integers(0, d - 1))
        if what == "small":
            rc[k] = short * draw(st.floats(0.5, 4))
        elif what == "outside":
            x[k, a] = box[a] * draw(st.sampled_from([-0.25, -1e-9, 1.0 + 2.0 ** -40, 1.5, 3.0]))
        elif what == "x":
            x[k, a] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
        elif what == "rc":
            rc[k] = draw(st.sampled_from([np.nan, np.inf, 0.0, -1.0]))
        else:
            skin = draw(st.sampled_from([-1.0, np.nan, np.inf]))
    return x, rc, skin, box


@st.composite
def lattices(draw):
    """DC-PSE inputs (x, eps, col, order, c, max_cond): a jittered lattice (spacing h = 2**e times 1
    to 2, e from -300 to 300, jitter up to 0.35 h, its origin up to 50 h from 0) of enough points per
    axis for a full stencil at its middle, core sizes from the spacing (a radius holding about twice
    the stencil's unknowns, times 1 to 1.25, and each particle's times 1 to 1.2), orders 2 to 6 in 2D
    and 2 to 4 in 3D (drawn uniformly: hypothesis favours small integers); the
    collocation points (off the particles, half the time) inside it; one in DEFECT_ODDS with a
    defect: an order, c or max_cond out of range, a NaN position, a bad core size, coincident
    sources (off the particles) or no source."""
    d = draw(st.sampled_from([2, 3]))
    rng = np.random.default_rng(draw(st.integers(0, 2 ** 32 - 1)))
    order = int(rng.integers(2, 7 if d == 2 else 5))
    need = n_unknowns(d, order, True)
    radius = math.sqrt(2 * need / math.pi) if d == 2 else (1.5 * need / math.pi) ** (1 / 3)   # in spacings
    radius *= rng.uniform(1.0, 1.25)
    m = math.ceil(2 * radius) + int(rng.integers(1, 3))
    h = math.ldexp(draw(st.floats(1, 2)), draw(st.integers(-300, 300)))
    jitter = draw(st.floats(0, 0.35))
    origin = h * np.array(draw(st.lists(st.floats(-50, 50), min_size=d, max_size=d)))
    grid = np.array(list(itertools.product(range(m), repeat=d)), dtype=float)
    x = origin + (grid + rng.uniform(-jitter, jitter, grid.shape)) * h
    eps = radius * h * rng.uniform(1.0, 1.2, len(x))
    col = origin + rng.uniform(0.0, m - 1.0, (draw(st.integers(1, 12)), d)) * h if draw(st.booleans()) else None
    c = draw(st.sampled_from([2.0, 1.0, 0.5, 4.0]))
    max_cond = draw(st.sampled_from([1e12, 1e10, np.inf]))
    if defective(draw):
        what = draw(st.sampled_from(["order", "c", "max_cond", "x", "eps", "coincident", "empty"]))
        if what == "order":
            order = draw(st.sampled_from([-1, 0, 1, MAX_ORDER + 1, 2.5, True, "4"]))
        elif what == "c":
            c = draw(st.sampled_from([0.0, -1.0, np.inf, np.nan]))
        elif what == "max_cond":
            max_cond = draw(st.sampled_from([1.0, 0.5, np.nan]))
        elif what == "x":
            x[draw(st.integers(0, len(x) - 1)), draw(st.integers(0, d - 1))] = draw(st.sampled_from([np.nan, np.inf]))
        elif what == "eps":
            eps[draw(st.integers(0, len(x) - 1))] = draw(st.sampled_from([np.nan, np.inf, 0.0, -1.0]))
        elif what == "coincident":                    # (a collocation point reads them)
            x[1] = x[0]
            col = np.vstack([x[:1] + 0.25 * h, origin + h * np.ones((2, d)) if col is None else col])
        else:
            x, eps = x[:0], eps[:0]
    return x, eps, col, order, c, max_cond


def exact_pairs(x: np.ndarray, rc: np.ndarray, skin: float, box: np.ndarray | None = None):
    """Pairs under |x_p - x_q| <= min(rc_p, rc_q) + skin in exact rational arithmetic (with a
    periodic box of edges ``box``: the minimum image over shifts of -1, 0, 1 edges).
    Returns (sure, near): ``near`` are the pairs within rounding of the rule's boundary, where
    the core may decide either way: 2**-40 of the cutoff, plus with a box one unit in the last
    place of its edge (the core's images x +- L are rounded)."""
    n, d = x.shape
    fx = [[Fraction(float(v)) for v in row] for row in x]
    shifts = (0,) if box is None else (-1, 0, 1)
    fbox = [Fraction(0)] * d if box is None else [Fraction(float(b)) for b in box]
    slack_abs = Fraction(0) if box is None else Fraction(float(np.spacing(np.max(box))))
    sure, near = set(), set()
    for p in range(n):
        for q in range(p + 1, n):
            r = Fraction(float(min(rc[p], rc[q]))) + Fraction(skin)
            slack = r / 2 ** 40 + slack_abs
            # (the shifts of the axes are independent: the least sum is the sum of each axis' least)
            d2 = sum(min((a - b - s * L) ** 2 for s in shifts) for a, b, L in zip(fx[p], fx[q], fbox))
            if abs(d2 - r * r) <= slack * (2 * r + slack):
                near.add((p, q))
            elif d2 <= r * r:
                sure.add((p, q))
    return sure, near


def valid_input(x, rc, skin) -> bool:
    return bool(np.all(np.isfinite(x)) and np.all(np.isfinite(rc)) and np.all(np.asarray(rc) > 0)
                and np.isfinite(skin) and skin >= 0)


def largest(x, rc, skin=0.0) -> float:
    """The largest |coordinate|, cutoff or skin (0 without points)."""
    if not len(rc):
        return 0.0
    return max(float(np.max(np.abs(x))) if x.size else 0.0, float(np.max(rc)), skin)


def span_log2(x, rc, skin=0.0) -> float:
    """log2 of (largest |coordinate|, cutoff or skin) / smallest cutoff (0 without points)."""
    if not len(rc):
        return 0.0
    return math.log2(largest(x, rc, skin)) - math.log2(float(np.min(rc)))


def at_a_limit(err: BaseException, span: float, tree: bool, big: float = 0.0) -> bool:
    """Whether a valid input's refusal is one of the documented limits: lengths spanning more than
    2**999 (here: 2**990, the coordinates' magnitude standing for the extent), or (``tree``: an AR
    tree was built) more levels than the tree's keys hold (here: a span of 2**19), or a tree's root
    cell beyond the largest double (``big``, the largest length, at least 2**1021)."""
    if isinstance(err, TreeDepthError):
        return tree and span > 19
    if tree and "root cell" in str(err):
        return big >= 2.0 ** 1021
    return "range" in str(err) and span > 990


def as_set(i, j):
    return set(zip(np.asarray(i).tolist(), np.asarray(j).tolist()))


# ---------------------------------------------------------------- neighbour lists
def test_neighbor_list_fuzz():
    reach = Reach()

    @FUZZ
    @given(data=particle_sets(), method=st.sampled_from(["brute", "cell", "ar", "auto"]), full=st.booleans())
    def example(data, method, full):
        reach.example()
        x, rc, skin = data
        rcs = np.broadcast_to(np.asarray(rc, dtype=np.float64), (len(x),))
        valid = valid_input(x, rcs, skin)
        try:
            nl = arpy.neighbor_list(x, rc, method=method, full=full, skin=skin)
        except DOCUMENTED as err:
            reach.refused(valid, err)
            assert not valid or at_a_limit(err, span_log2(x, rcs, skin), method in ("ar", "auto"), largest(x, rcs, skin)), err
            return
        assert valid, "bad input accepted"
        reach.check()
        sure, near = exact_pairs(x, rcs, skin)
        got = as_set(*nl.pairs())
        assert sure <= got <= sure | near
        assert len(nl) == (2 if full else 1) * len(got)

    example()
    reach.assert_most()


def test_cross_list_and_tree_fuzz():
    """AR trees' Verlet lists and cross lists against the exact rule.  Besides the documented limits
    of :func:`at_a_limit`, a cross list refuses query cutoffs below 2**-RANGE_EXP in the tree's frame
    (its lengths times the power of two it was built with), where their squares would underflow: a
    tree whose lengths lie near 2**-480 takes no query cutoffs below 2**-500 (which
    arpy.cross_neighbor_list, scaling both, accepts)."""
    reach = Reach()

    @FUZZ
    @given(sets=sets_and_queries())
    def example(sets):
        reach.example()
        (x, rc, skin), (xq, rq, _) = sets
        rcs = np.broadcast_to(np.asarray(rc, dtype=np.float64), (len(x),))
        rqs = np.broadcast_to(np.asarray(rq, dtype=np.float64), (len(xq),))
        valid = valid_input(x, rcs, 0.0) and valid_input(xq, rqs, 0.0)
        tree = None
        try:
            tree = arpy.ARCellList(x, rc)
            verlet = tree.verlet_list()
            cross = tree.cross_list(xq, rq)
        except DOCUMENTED as err:
            reach.refused(valid, err)
            span = span_log2(np.concatenate([x, xq]), np.concatenate([rcs, rqs])) if valid else 0.0
            frame = tree is not None and len(xq) and "query cutoffs" in str(err) and \
                math.ldexp(float(np.minimum(rqs, rcs.max()).min()), tree._k) < 2.0 ** -RANGE_EXP
            big = largest(np.concatenate([x, xq]), np.concatenate([rcs, rqs])) if valid else 0.0
            assert not valid or at_a_limit(err, span, True, big) or frame, err
            return
        assert valid, "bad input accepted"
        reach.check()
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

    example()
    reach.assert_most()


def test_periodic_fuzz():
    """Periodic lists against the exact minimum-image rule; a valid set is never refused."""
    reach = Reach()

    @FUZZ
    @given(data=periodic_sets())
    def example(data):
        reach.example()
        x, rc, skin, box = data
        valid = bool(valid_input(x, rc, skin) and np.all((x >= 0) & (x <= box)) and rc.max() + skin < 0.5 * box.min())
        try:
            nl = arpy.neighbor_list(x, rc, domain=arpy.Domain(box, periodic=True), skin=skin)
            xg, src = arpy.periodic_ghosts(x, rc, arpy.Domain(box, periodic=True), skin)
        except DOCUMENTED as err:
            reach.refused(valid, err)
            assert not valid, err
            return
        assert valid, "bad input accepted"
        reach.check()
        shift = np.round((xg - x[src]) / box)                         # images: whole periods away
        assert np.all(np.abs(shift) <= 1) and np.all(np.abs(xg - x[src] - shift * box) <= np.spacing(np.abs(xg) + box))
        sure, near = exact_pairs(x, rc, skin, box)
        got = as_set(*nl.pairs())
        assert sure <= got <= sure | near, (x.tolist(), rc.tolist(), box.tolist(), skin)

    example()
    reach.assert_most()


# ---------------------------------------------------------------- DC-PSE
def dcpse_valid(x, eps, col, order, c, max_cond) -> bool:
    """Whether DCPSE must accept these inputs (its documented domain)."""
    if not (isinstance(order, (int, np.integer)) and not isinstance(order, bool) and 2 <= order <= MAX_ORDER):
        return False
    if not (np.isfinite(c) and c > 0 and max_cond > 1) or len(x) == 0:
        return False
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(eps)) and np.all(eps > 0)):
        return False
    return col is None or len(np.unique(x, axis=0)) == len(x)     # (off the particles: no coincident sources)


def test_dcpse_fuzz():
    """DC-PSE on jittered lattices: every row with a valid, well-conditioned stencil (most of them)
    differentiates polynomials of degree below the order exactly (the gradient of a linear function
    and, from order 3, its Laplacian and the gradient and Laplacian of a quadratic one), within
    rounding of its stencil's terms; a valid input is never refused."""
    reach = Reach()
    rows = {"checked": 0, "all": 0}

    @FUZZ
    @given(data=lattices())
    def example(data):
        reach.example()
        x, eps, col, order, c, max_cond = data
        valid = dcpse_valid(*data)
        try:
            op = arpy.DCPSE(x, eps, col, None, order=order, c=c, max_cond=max_cond, strict=False)
            grads = op.gradient()
            lap = op.laplacian() if order >= 3 else None
        except DOCUMENTED as err:
            reach.refused(valid, err)
            assert not valid, err
            return
        assert valid, "bad input accepted"
        for g in grads + ([lap] if lap is not None else []):
            assert np.all(np.isfinite(g.data))
        at = x if col is None else col
        ok = np.setdiff1d(np.flatnonzero(op.cond < 1e8), op.failed)
        rows["checked"] += ok.size
        rows["all"] += len(at)
        if not ok.size:
            reach.note("no well-conditioned row")
            return
        reach.check()
        # polynomials in coordinates centred on the lattice and scaled by its size
        centre, size = x.mean(axis=0), float(np.ptp(x, axis=0).max())
        u, v = (x - centre) / size, (at - centre) / size
        a = np.linspace(1.0, -0.5, x.shape[1])
        tests = [(u @ a, v @ a, np.tile(a / size, (len(at), 1)), 0.0)]
        if order >= 3:
            b = np.linspace(0.5, 1.5, x.shape[1])
            tests.append((u @ a + (u ** 2) @ b, v @ a + (v ** 2) @ b, (a + 2 * v * b) / size, 2 * b.sum() / size ** 2))
        for f, f_at, grad, laplacian in tests:
            for k, g in enumerate(grads):
                check_rows(g, f, f_at, grad[:, k], op.cond, ok)
            if lap is not None:
                check_rows(lap, f, f_at, np.full(len(at), laplacian), op.cond, ok)

    example()
    reach.assert_most()
    assert rows["checked"] >= 0.5 * rows["all"], rows          # most rows have a usable stencil


def check_rows(w, f, f_at, want, cond, ok) -> None:
    """Rows ``ok`` of the operator ``w`` applied to f (values at the sources) equal ``want`` within
    (1e-10 + 1e-13 cond) of the sum of |w_pq| |f_q - f(at_p)|: the rounding of the stencil's terms,
    grown by the conditioning of its moment matrix (the errors seen are below 4e-15 + 4e-17 cond)."""
    w = w.tocsr()
    got = w @ f
    row = np.repeat(np.arange(w.shape[0]), np.diff(w.indptr))
    scale = np.bincount(row, np.abs(w.data) * np.abs(f[w.indices] - f_at[row]), minlength=w.shape[0])[ok]
    err = np.abs(got[ok] - want[ok])
    assert np.all(err <= (1e-10 + 1e-13 * cond[ok]) * scale), (err / scale).max()


# ---------------------------------------------------------------- self-organization
@st.composite
def organize_inputs(draw):
    """(x, D, periodic, adapt, max_particles): 1 to 6 points in the unit box (coincident ones too), a
    uniform resolution D from 2**-6 to 2**10 (below 2**-2 in a periodic box, whose cutoffs must stay
    below half its edge); one in DEFECT_ODDS with a defect: a NaN position, no point, a D not finite
    and > 0, or a max_particles below 1."""
    d = draw(st.sampled_from([2, 3]))
    n = draw(st.integers(1, 6))
    pool = draw(st.lists(st.floats(0, 1), min_size=1, max_size=6))
    x = np.array(draw(st.lists(st.sampled_from(pool) | st.floats(0, 1), min_size=n * d, max_size=n * d))).reshape(n, d)
    periodic = draw(st.booleans())
    D = math.ldexp(draw(st.floats(1, 2)), draw(st.integers(-6, -3 if periodic else 9)))
    adapt = draw(st.booleans())
    max_particles: float = 2000
    if defective(draw):
        what = draw(st.sampled_from(["x", "empty", "D", "max_particles"]))
        if what == "x":
            x[draw(st.integers(0, n - 1)), 0] = np.nan
        elif what == "empty":
            x = x[:0]
        elif what == "D":
            D = draw(st.sampled_from([0.0, -1.0, np.nan, np.inf]))
        else:
            max_particles = draw(st.sampled_from([0, -1, np.nan]))
    return x, D, periodic, adapt, max_particles


def test_self_organize_fuzz():
    reach = Reach()

    @FUZZ
    @given(data=organize_inputs())
    def example(data):
        reach.example()
        x, D, periodic, adapt, max_particles = data
        valid = bool(len(x) and np.all(np.isfinite(x)) and np.isfinite(D) and D > 0 and max_particles >= 1)
        try:
            box = arpy.Domain([1.0] * x.shape[1], periodic=periodic)
            ps = arpy.self_organize(x, lambda p: np.full(len(p), D), domain=box,
                                    adapt_number=adapt, max_iter=2, max_particles=max_particles, seed=1)
        except DOCUMENTED as err:
            reach.refused(valid, err)
            assert not valid, err
            return
        assert valid, "bad input accepted"
        reach.check()
        assert np.all(np.isfinite(ps.x)) and np.all((ps.x >= 0) & (ps.x <= 1))
        assert np.all(np.isfinite(ps.D)) and np.all(ps.D > 0)

    example()
    reach.assert_most()


# ---------------------------------------------------------------- dtypes, memory orders, shapes
REAL = ["float64", "float32", "float16", "int64", "int32", "uint8"]
NOT_REAL = ["bool", "complex128", "object", "U3"]


@st.composite
def arrays_of_points(draw):
    """(n, d, dtype, order, seed): real dtypes, d = 2 or 3, but one in DEFECT_ODDS with a dimension
    other than 2 or 3 or a dtype that is not real numbers."""
    n = draw(st.integers(0, 40))
    d, dtype = draw(st.sampled_from([2, 3])), draw(st.sampled_from(REAL))
    if defective(draw):
        if draw(st.booleans()):
            d = draw(st.sampled_from([0, 1, 4]))
        else:
            dtype = draw(st.sampled_from(NOT_REAL))
    return n, d, dtype, draw(st.sampled_from(["C", "F", "strided", "transposed"])), draw(st.integers(0, 2 ** 16))


def test_dtypes_orders_and_shapes_fuzz():
    """Any array-like: the list of its float64 values, or TypeError / ValueError (shapes other
    than (n, 2) or (n, 3); dtypes that are not real numbers: complex, object, strings, bool)."""
    reach = Reach()

    @FUZZ
    @given(data=arrays_of_points(), method=st.sampled_from(["brute", "cell", "ar", "auto"]))
    def example(data, method):
        reach.example()
        n, d, dtype, order, seed = data
        rng = np.random.default_rng(seed)
        base = rng.integers(0, 6, (n, d)) if dtype in ("uint8", "bool", "int32", "int64") else rng.random((n, d)) * 5
        x = base.astype(dtype)
        if order == "F":
            x = np.asfortranarray(x)
        elif order == "strided":
            x = np.repeat(x, 2, axis=0)[::2]
        elif order == "transposed":
            x = np.ascontiguousarray(x.T).T
        valid = d in (2, 3) and dtype in REAL
        try:
            nl = arpy.neighbor_list(x, 1.5, method=method)
        except (TypeError, ValueError) as err:
            reach.refused(valid, err)
            assert not valid, (d, dtype, err)
            return
        assert valid, (d, dtype)
        reach.check()
        want = arpy.neighbor_list(np.array(x, dtype=np.float64), 1.5, method="brute")
        assert as_set(*nl.pairs()) == as_set(*want.pairs())

    example()
    reach.assert_most()
