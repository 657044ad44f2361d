"""Work shared between ranks by cost (arpy.distributed.share): the transfer plan against plans worked
out by hand, the shared map against a NumPy brute force over every source on 2-4 thread ranks, and the
self-organization with its phases shared (and its insertion's wider search) bitwise the one-process
run."""

from __future__ import annotations

import numpy as np
import pytest

import arpy
from arpy.distributed import run_threads
from arpy.distributed import share
from arpy.distributed.share import Sharing, transfers


def test_transfers_move_each_surplus_to_the_ranks_below_the_mean():
    """Givers and takers in rank order, each giver's surplus in items of its unit, capped by its items;
    transfers below ``least`` items left out; nothing when every rank is at the mean."""
    assert transfers(np.array([10.0, 2.0, 6.0]), np.array([0.5, 1.0, 1.0]), np.array([20, 2, 6])) == []
    assert transfers(np.array([10.0, 2.0, 6.0]), np.array([0.5, 1.0, 1.0]), np.array([20, 2, 6]),
                     least=1) == [(0, 1, 8)]                             # surplus 4, 0.5 an item
    # two givers, two takers: 0 -> 1 and 2 -> 3 (the mean is 5)
    assert transfers(np.array([9.0, 1.0, 9.0, 1.0]), np.full(4, 0.01), np.full(4, 900)) == \
        [(0, 1, 400), (2, 3, 400)]
    # one giver feeding two takers; its items run out after the first
    assert transfers(np.array([12.0, 0.0, 0.0]), np.full(3, 0.01), np.array([500, 0, 0])) == \
        [(0, 1, 400), (0, 2, 100)]
    assert transfers(np.array([3.0, 3.0]), np.ones(2), np.array([3, 3]), least=1) == []


def _brute(items: np.ndarray, reach: np.ndarray, x: np.ndarray, v: np.ndarray, period: np.ndarray):
    """Per item: min over the sources within its reach (minimum image) of value + distance, and their count."""
    delta = np.abs(items[:, None] - x[None])
    delta = np.where(period > 0, np.minimum(delta, np.where(period > 0, period, np.inf) - delta), delta)
    dist = np.sqrt((delta ** 2).sum(-1))
    inside = dist <= reach[:, None]
    return np.where(inside, v[None] + dist, np.inf).min(axis=1), inside.sum(axis=1)


@pytest.mark.parametrize("periodic, corner", [(True, 0.0), (False, -7.25), ((True, False), 2.5)])
def test_shared_map_equals_the_brute_force_and_ships_only_near_sources(periodic, corner):
    """Sharing.map on 2-4 thread ranks whose items are very uneven (rank 0 holds most): two calls of a
    work whose result depends on the sources within each item's reach (the second call plans by the
    costs the first measured); the results equal a brute force over every source, items went to other
    ranks with fewer sources than the rank holds, and a rank that gave reports the work done for it."""
    rng = np.random.default_rng(11)
    box = arpy.Domain((corner + np.zeros(2), corner + np.ones(2)), periodic=periodic)
    period = np.asarray(box.period)
    x = rng.random((3000, 2)) + corner
    v = rng.normal(size=x.shape[0])
    for parts in (2, 3, 4):
        items = [rng.random((1500 if r == 0 else 40 * r, 2)) + corner for r in range(parts)]
        reach = [0.02 + 0.05 * rng.random(it.shape[0]) for it in items]
        calls: list[tuple[int, int]] = []

        def work(it, rc, xs, vs):
            calls.append((it.shape[0], xs.shape[0]))
            out = _brute(it, rc, xs, vs, period)
            return out[0], out[1], it * 2.0                          # (float, int and (n, d) results)

        def rank(comm):
            s = Sharing(comm, period, threshold=1.0, least=1)
            got = [s.map("phase", work, (items[comm.rank], reach[comm.rank]), items[comm.rank],
                         reach[comm.rank], (x, v)) for _ in range(2)]
            assert Sharing(comm, period).rates == s.rates != {}                # (kept for the communicator)
            return got, dict(s.given), dict(s.taken), dict(s.units)

        out = run_threads(parts, rank)
        for r, (got, given, taken, units) in enumerate(out):
            low, count = _brute(items[r], reach[r], x, v, period)
            for g in got:
                assert g[0].tobytes() == low.tobytes()
                np.testing.assert_array_equal(g[1], count)
                np.testing.assert_array_equal(g[2], items[r] * 2.0)
        assert out[0][1].get("phase", 0) > 0                          # rank 0 gave items away
        assert sum(o[2].get("phase", 0) for o in out) == out[0][1]["phase"] + sum(o[1].get("phase", 0) for o in out[1:])
        assert "phase" in out[0][3]                                    # (what its items cost elsewhere)
        assert min(m for _, m in calls) < x.shape[0]                   # shipped with the near sources only


def test_the_plan_evens_out_the_work_after_the_exchange(monkeypatch):
    """On a clock that counts work (each item 1, handing a slab out 100): after a first call has measured
    the costs, 2 thread ranks holding 1000 and 200 equal items each compute 600 after the exchange.  The
    handing out, which the taker waits for at the exchange in any case, is no part of the items' cost
    (counted in, rank 0 would give 50 items more than the balance)."""
    import threading

    ticks, me = [0.0, 0.0], threading.local()
    gap = share.box_gap

    def slow_gap(*a):
        ticks[me.rank] += 100.0
        return gap(*a)

    monkeypatch.setattr(share, "box_gap", slow_gap)
    rng = np.random.default_rng(5)
    items = [rng.random((1000, 2)), rng.random((200, 2))]
    x = rng.random((50, 2))

    def rank(comm):
        me.rank = comm.rank
        comm.clock = lambda: ticks[comm.rank]
        s = Sharing(comm, None, least=1)
        computed = []

        def work(it, xs):
            ticks[comm.rank] += float(it.shape[0])
            computed[-1] += it.shape[0]
            return (it.sum(axis=1),)

        for _ in range(2):
            computed.append(0)
            got, = s.map("p", work, (items[comm.rank],), items[comm.rank], np.full(len(items[comm.rank]), 0.1), (x,))
            np.testing.assert_array_equal(got, items[comm.rank].sum(axis=1))
        # the work spent in the maps is the communicator's: every Sharing of it counts another's
        other = Sharing(comm, None)
        computed.append(0)
        other.map("q", work, (items[comm.rank][:10],), items[comm.rank][:10], np.full(10, 0.1), (x,))
        return computed, s.spent, other.spent, ticks[comm.rank]

    out = run_threads(2, rank)
    first, second = (tuple(o[0][i] for o in out) for i in (0, 1))
    assert first == (600, 600)                  # (planned from no costs: every item the same)
    assert second == (600, 600)
    for _, spent, other, clock in out:
        assert spent == other == clock         # (here every tick is spent in a map)


def test_one_rank_computes_everything_itself():
    """P = 1: the work on every item with every source, nothing planned or measured."""
    from arpy.distributed import SerialComm

    s = Sharing(SerialComm(), None)
    seen = []
    out = s.map("p", lambda a, b: (seen.append(b.shape[0]) or a + 1,), (np.arange(5.0),), np.zeros((5, 1)),
                np.ones(5), (np.zeros(7),))
    np.testing.assert_array_equal(out[0], np.arange(5.0) + 1)
    assert seen == [7] and s.rates == {} and s.given == {}


def _share_everything(monkeypatch) -> list[Sharing]:
    """Share at any imbalance, one item at least; returns the list every Sharing made from here joins."""
    monkeypatch.setattr(share, "SHARE", 1.0)
    monkeypatch.setattr(share, "MIN_ITEMS", 1)
    made: list[Sharing] = []
    init = Sharing.__init__

    def spied(self, *a, **k):
        init(self, *a, **k)
        made.append(self)

    monkeypatch.setattr(Sharing, "__init__", spied)
    return made


def test_shared_field_resolution_is_bitwise_the_one_process_run(monkeypatch):
    """field_resolution on 2 and 3 thread ranks (every P-th particle of an adapted set, keyed by index),
    its grade of Eq. 2.9 and the interpolation of the sampled D shared at any imbalance: the sampled D at
    the particles is bitwise the one-process value, also in a second call, planned by the costs the first
    measured (kept for the ranks; rank 0's made ten times as dear), where grades and interpolations were
    computed on other ranks."""
    box = arpy.Domain(([-2.0, 1.0], [-1.0, 2.0]), periodic=(True, False))
    ps = arpy.self_organize(np.random.default_rng(2).uniform(box.lo, box.hi, (400, 2)),
                            lambda p: np.full(len(p), 0.04), domain=box, seed=3)
    f = np.tanh(40.0 * (ps.x[:, 0] + 1.6)) + ps.x[:, 1]
    one = arpy.field_resolution(ps.x, f, ps.D, D0=0.06, Dmin=0.01, domain=box)(ps.x)
    made = _share_everything(monkeypatch)
    for parts in (2, 3):
        made.clear()

        def rank(comm):
            mine = np.arange(comm.rank, ps.n, parts)
            out = []
            for _ in range(2):
                res = arpy.field_resolution(ps.x[mine], f[mine], ps.D[mine], D0=0.06, Dmin=0.01, domain=box,
                                            comm=comm, keys=mine)
                out.append(res(ps.x[mine]))
                # rank 0's grades and interpolations made ten times as dear as measured (the costs are
                # kept for the ranks)
                for phase in ("monitor grade", "shepard"):
                    Sharing(comm, None).rates[phase] *= 10.0 if comm.rank == 0 else 1.0
            return out, mine

        for values, mine in run_threads(parts, rank):
            assert all(v.tobytes() == one[mine].tobytes() for v in values)
        for phase in ("monitor grade", "shepard"):
            assert sum(s.given.get(phase, 0) for s in made) > 0


def test_shared_self_organization_is_bitwise_the_one_process_run(monkeypatch):
    """The pulse start self-organized on 2 and 3 thread ranks with every imbalance shared (threshold 1,
    one item at least; the first calls planned as if rank 0's items were dear) and the insertion's first
    reach cut to one D_p (so that many parents need the wider search): the particles and D are bitwise
    the one-process run's, both phases were shared, and the wider search ran."""
    import arpy.adapt.adaptation as adaptation
    from arpy.cases.pulse import pulse_setup

    setup = pulse_setup(2, 1000.0)
    box = arpy.Domain(setup["box"])
    x0 = np.random.default_rng(3).uniform(*setup["box"], (600, 2))
    kw = dict(grad_f=setup["grad0"], D0=0.15, domain=box, seed=4)
    one = arpy.self_organize(x0, **kw)
    made = _share_everything(monkeypatch)
    monkeypatch.setattr(adaptation, "INSERT_REACH", 1.0)
    wider = []
    sites = adaptation._sites

    def counted(xp, Dp, kp, slack, *a):
        wider.append(bool(slack.size and np.isinf(slack).all()))
        return sites(xp, Dp, kp, slack, *a)

    monkeypatch.setattr(adaptation, "_sites", counted)
    for parts in (2, 3):
        made.clear()
        wider.clear()
        def rank(comm):
            # the first calls planned as if rank 0's items cost ten times the others' (then as measured)
            for phase in ("insertion", "grade"):
                Sharing(comm, None).rates[phase] = 1e-5 if comm.rank == 0 else 1e-6
            return arpy.self_organize(x0, comm=comm, **kw).gather()

        out = run_threads(parts, rank)
        keys, x, D = out[0][0], out[0][1], out[0][2]
        np.testing.assert_array_equal(keys, np.arange(one.n))
        assert x.tobytes() == one.x.tobytes() and D.tobytes() == one.D.tobytes()
        for phase in ("insertion", "grade"):
            assert sum(s.given.get(phase, 0) for s in made) > 0
        assert any(wider)
