"""Balance by cost (arpy.distributed.balance): the weighted bisection against a plain NumPy weighted
median split, the measured densities and the collective decision, and a run whose boxes are cut by
uneven costs, bitwise the one-process run."""

from __future__ import annotations

import numpy as np
import pytest

import arpy
from arpy.distributed import bisect, run_threads
from arpy.distributed import balance
from arpy.distributed.balance import WEIGHT_UNIT, CostBalance, densities
from arpy.reference import weighted_bisection


@pytest.mark.parametrize("d, parts", [(2, 2), (2, 3), (3, 4), (3, 7)])
def test_weighted_bisection_is_the_numpy_weighted_median_split(d, parts):
    """bisect(weights=) gives the boxes and owners of a sort-and-cumsum weighted median split
    (arpy.reference.weighted_bisection), ties, zero weights and heavy particles included, on one
    process and on 3 thread ranks holding the particles at random; each box's weight is within the
    heaviest particle (and the ties at a cut) of its share."""
    rng = np.random.default_rng(10 * d + parts)
    x = rng.random((1500, d)) * np.arange(1.0, d + 1)
    x[:200, 0] = x[0, 0]                                   # a plane of ties
    w = rng.integers(0, 10, len(x)) * np.where(x[:, -1] > 0.6 * d, 20, 1)   # zeros and a heavy region
    lo, hi = x.min(axis=0), x.max(axis=0)
    want_lo, want_hi, want_owner = weighted_bisection(x, parts, w, lo, hi)
    dec, owner = bisect(x, parts, weights=w)
    np.testing.assert_array_equal(dec.lo, want_lo)
    np.testing.assert_array_equal(dec.hi, want_hi)
    np.testing.assert_array_equal(owner, want_owner)
    deal = rng.integers(0, 3, len(x))
    for r, (got_lo, got_hi, got_owner) in enumerate(run_threads(3, lambda comm: (lambda dec_o: (
            dec_o[0].lo, dec_o[0].hi, dec_o[1]))(bisect(x[deal == comm.rank], parts, weights=w[deal == comm.rank],
                                                        comm=comm)))):
        np.testing.assert_array_equal(got_lo, want_lo)
        np.testing.assert_array_equal(got_hi, want_hi)
        np.testing.assert_array_equal(got_owner, want_owner[deal == r])
    if parts == 2:                  # one cut: the weights below it reach half, less its last value's
        per = np.bincount(owner, weights=w, minlength=parts)
        axis = int(np.argmax(hi - lo))
        v0 = x[owner == 0, axis].max()
        assert per[0] >= w.sum() / 2 > per[0] - w[x[:, axis] == v0].sum()


def test_bisect_leaves_no_reference_cycle_holding_its_arrays():
    """The positions and weights given to bisect, and its work arrays, are freed when bisect returns,
    without waiting for the garbage collector (which large NumPy runs seldom trigger): the rank's
    memory at its peak must not hold every earlier call's copies."""
    import gc
    import weakref

    rng = np.random.default_rng(3)
    x, w = rng.random((2000, 2)), rng.integers(1, 5, 2000)
    seen = [weakref.ref(x), weakref.ref(w)]
    enabled = gc.isenabled()
    gc.disable()
    try:
        dec, owner = bisect(x, 5, weights=w)
        assert owner.shape == (2000,) and dec.parts == 5
        del x, w
        assert [ref() is None for ref in seen] == [True, True]
    finally:
        if enabled:
            gc.enable()


class _Ranks:
    """A communicator of P ranks seen from rank ``rank``, the others' gathered values given."""

    def __init__(self, rank: int, others: list, work: float) -> None:
        self.rank, self.size, self._others, self._work = rank, len(others) + 1, others, work

    def work(self) -> float:
        return self._work

    def allgather(self, value):
        return self._others[:self.rank] + [value] + self._others[self.rank:]

    def gather_arrays(self, value):
        parts = self.allgather(np.asarray(value).ravel())
        return np.concatenate(parts), np.concatenate([[0], np.cumsum([q.size for q in parts])])


def _survey_of(counts: np.ndarray, spent: float) -> np.ndarray:
    """What CostBalance.survey sends for a rank with these particles by box and this work: the bits of
    the work, the boxes it has particles for, its counts for them."""
    to = np.flatnonzero(counts)
    return np.concatenate([np.array([spent]).view(np.int64), to, np.asarray(counts, np.int64)[to]])


def test_measured_densities_predict_the_boxes_work_and_the_ranks_decide_alike():
    """CostBalance.survey: each rank's particles cost its measured seconds per particle over the mean
    particle's (a rank without particles the mean); a box's predicted work is the sum over the
    particles it will own, the same on every rank; cut anew above the threshold, with integer weights
    WEIGHT_UNIT times the density."""
    counts = np.array([[100, 0, 0], [10, 90, 0], [0, 0, 0]])         # rank r's particles by box
    spent = np.array([1.0, 3.0, 0.5])                                # rank 2 holds none
    mean = spent.sum() / counts.sum()
    want_density = np.array([1.0 / 100 / mean, 3.0 / 100 / mean, 1.0])
    np.testing.assert_allclose(densities(counts.sum(axis=1), spent), want_density, rtol=1e-15)
    for rank in range(3):
        others = [_survey_of(counts[r], spent[r]) for r in range(3) if r != rank]
        bal = CostBalance(_Ranks(rank, others, 0.0), threshold=1.1)
        bal.mark = -spent[rank]                                      # (work() - mark = spent)
        assert bal.survey(counts[rank])                              # (rank 1 has particles for box 0)
        np.testing.assert_allclose(bal.loads, want_density @ counts, rtol=1e-15)
        assert bal.due()                                             # (box 1 holds the dear particles)
        assert np.all(bal.weights(5) == max(1, round(WEIGHT_UNIT * want_density[rank])))
    # a clock of its own (the work outside the phases shared by cost): measured from it, not from comm.work
    clock = [5.0]
    own = CostBalance(_Ranks(0, [_survey_of(counts[1][:2], 2.0)], 100.0), work=lambda: clock[0])
    clock[0] = 7.0
    assert own.survey(counts[0][:2])
    np.testing.assert_allclose(own.density, densities(np.array([100, 100]), np.array([2.0, 2.0])), rtol=1e-15)
    even = CostBalance(_Ranks(0, [_survey_of(np.array([0, 50]), 9.0)], 0.0), measured=False)
    assert not even.survey(np.array([50, 0]))                       # (each rank keeps its own)
    assert not even.due() and np.all(even.weights(3) == WEIGHT_UNIT)   # (the count model: ones)
    assert list(densities(np.array([0, 0]), np.array([1.0, 1.0]))) == [1.0, 1.0]


def test_a_run_cut_by_uneven_costs_is_bitwise_the_one_process_run(monkeypatch):
    """The pulse self-organized and simulated on 3 thread ranks whose particles are made to cost
    1, 4 and 0.5 units (the measured densities replaced): the boxes are cut by those weights (seen by
    bisect, unequal per rank) and the run is bitwise the one-process run: particles, D, f, counts."""
    from arpy.cases.pulse import pulse_setup

    setup = pulse_setup(2, 1000.0)
    box = arpy.Domain(setup["box"])
    x0 = np.random.default_rng(1).uniform(*setup["box"], (800, 2))
    kw = dict(flow=setup["flow"], nu=1e-3, D0=0.2, integrator="euler", reorganize_every=2, seed=1)
    f0 = lambda p: setup["exact"](p, 0.0)  # noqa: E731
    ps = arpy.self_organize(x0, grad_f=setup["grad0"], D0=0.2, domain=box, seed=1)
    one = arpy.Simulation(ps, f0, **kw).run(0.08)
    assert sum(one.history()["reorganized"]) >= 2
    monkeypatch.setattr(balance, "densities", lambda counts, spent: np.array([1.0, 4.0, 0.5]))
    import arpy.adapt.view as view

    cuts = []

    def spied(x, parts, *, weights=None, **kw):
        cuts.append(None if weights is None else np.unique(weights).tolist())
        return bisect(x, parts, weights=weights, **kw)

    monkeypatch.setattr(view, "bisect", spied)

    def run(comm):
        adapted = arpy.self_organize(x0, grad_f=setup["grad0"], D0=0.2, domain=box, seed=1, comm=comm)
        sim = arpy.Simulation(adapted, f0, comm=comm, **kw).run(0.08)
        return adapted.x.tobytes(), adapted.D.tobytes(), sim.gather(), sim.history()["n"]

    out = run_threads(3, run, timeout=300)
    ax, aD, (keys, x, D, F), n = out[0]
    assert ax == ps.x.tobytes() and aD == ps.D.tobytes()
    np.testing.assert_array_equal(keys, np.arange(one.n))
    assert x.tobytes() == one.x.tobytes() and D.tobytes() == one.D.tobytes() and F[:, 0].tobytes() == one.f.tobytes()
    np.testing.assert_array_equal(n, one.history()["n"])
    weighted = [c for c in cuts if c is not None]
    assert weighted and all(len(c) == 1 for c in weighted)          # one weight per rank's particles
    assert {c[0] for c in weighted} >= {WEIGHT_UNIT * 4}           # (rank 1's, seen by its bisect)
