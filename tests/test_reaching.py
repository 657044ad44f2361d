"""Decomposition.reaching: the ranks whose boxes a search over points tests (locate, halo, the
self-organization's exchanges), so that a rank does not pass over its points once per rank of the
run.  It may name more ranks than needed, never fewer: the searches give what they give when every
rank is tested."""

import numpy as np
import pytest

import arpy
from arpy.adapt.view import Confinement, View
from arpy.distributed import Decomposition, bisect, halo, run_threads

BOX = arpy.Domain([[-1.0, 0.25], [2.0, 1.25]], periodic=[True, False])


def every_rank(self, lo, hi, reach=0.0, period=None):
    """The searches without the filter: every rank."""
    return np.arange(self.parts)


def numpy_locate(dec: Decomposition, x: np.ndarray) -> np.ndarray:
    """Decomposition.locate written out in NumPy: the first box holding each point (the upper faces of
    the decomposed box belonging to the boxes there), -1 if none."""
    top = dec.hi.max(axis=0)
    out = np.full(x.shape[0], -1, np.int64)
    for r in range(dec.parts):
        lo, hi = dec.box(r)
        inside = np.all((x >= lo) & ((x < hi) | ((hi == top) & (x <= top))), axis=1) & (out < 0)
        out[inside] = r
    return out


def positions(rng: np.random.Generator, dec: Decomposition, n: int) -> np.ndarray:
    """Points in and around the boxes: random, on the boxes' faces and corners, just past the
    decomposed box (on its open and its periodic faces), and a few that are not finite."""
    lo, hi = dec.lo.min(axis=0), dec.hi.max(axis=0)
    x = lo + (hi - lo) * rng.uniform(-0.05, 1.05, (n, 2))
    faces = np.concatenate([dec.lo, dec.hi, np.stack([dec.lo[:, 0], dec.hi[:, 1]], axis=1)])
    x[: faces.shape[0]] = faces                                  # (corners of every box)
    x[faces.shape[0]: 2 * faces.shape[0], 0] = faces[:, 0]       # (on a face, anywhere along it)
    x[-3:] = [[np.nan, 0.5], [np.inf, 0.5], [0.5, -np.inf]]
    return x


@pytest.mark.parametrize("parts", [5, 64])
def test_searches_over_the_reaching_boxes_equal_searches_over_every_box(monkeypatch, parts):
    """locate (points on the boxes' faces and corners, outside the decomposed box, NaN, and infinite
    along the open axis, which the outer boxes reach) and halo (free space and the periodic axis of a
    shifted box; cutoffs over two decades, some reaching past several boxes; all particles, and one
    rank's, near few boxes) equal their search over every box, bit for bit."""
    rng = np.random.default_rng(parts)
    dec, _ = bisect(rng.uniform(BOX.lo, BOX.hi, (4000, 2)), parts, domain=BOX)
    x = positions(rng, dec, 600)
    inside = BOX.wrap(x[np.all(np.isfinite(x), axis=1)])
    rc = 0.002 * np.exp(rng.uniform(0, np.log(100.0), inside.shape[0]))
    got = {}
    for name in ("filtered", "every"):
        if name == "every":
            monkeypatch.setattr(Decomposition, "reaching", every_rank)
        owner = dec.locate(inside)
        got[name] = [dec.locate(x), owner]
        for domain in (None, BOX):
            got[name] += [a for g in halo(inside, rc, dec, owner, domain=domain) for a in g]
            mine = owner == 3                                   # (one rank's particles: few boxes near)
            got[name] += [a for g in halo(inside[mine], rc[mine], dec, owner[mine], domain=domain) for a in g]
    assert len(got["filtered"]) == len(got["every"])
    for a, b in zip(got["filtered"], got["every"]):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    assert got["every"][0].tolist() == numpy_locate(dec, x).tolist()
    assert np.all(got["every"][0][-3:-1] == -1) and got["every"][0][-1] >= 0   # (-inf along the open axis: an outer box)


def test_reaching_names_the_boxes_near_a_box_and_its_periodic_images():
    """The ranks within the reach of a box, against the gaps between the boxes written out: boxes of a
    4 x 4 grid, a query box in one cell, without and with a periodic axis; and a query box with infinite
    sides (points at infinity along an open axis)."""
    g = np.arange(4) / 4
    lo = np.array([[a, b] for a in g for b in g])
    dec = Decomposition(lo, lo + 0.25)
    q_lo, q_hi = np.array([0.05, 0.3]), np.array([0.1, 0.4])  # (inside box (0, 1))
    for reach, period in ((0.0, None), (0.16, None), (0.16, np.array([1.0, 0.0])), (2.0, None)):
        want = []
        for r in range(16):
            gap = []
            for i in range(2):
                shifts = (-1.0, 0.0, 1.0) if period is not None and period[i] > 0 else (0.0,)
                gap.append(min(max(dec.lo[r, i] - (q_hi[i] + s), (q_lo[i] + s) - dec.hi[r, i], 0.0) for s in shifts))
            want += [r] if np.hypot(*gap) <= reach else []
        assert dec.reaching(q_lo, q_hi, reach, period).tolist() == want, (reach, period)
    walls = Decomposition(lo, lo + 0.25, open=np.array([True, True]))
    assert walls.reaching(np.array([-np.inf, 0.3]), np.array([-np.inf, 0.4])).tolist() == [1]


def test_the_self_organizations_exchanges_over_the_reaching_boxes_equal_those_over_every_box(monkeypatch):
    """View.around, the homes of insertion sites and the ranks holding their copies on 6 thread ranks,
    with and without the filter: the same particles and sites, bit for bit."""
    rng = np.random.default_rng(7)
    x = rng.uniform(BOX.lo, BOX.hi, (900, 2))
    sites = np.concatenate([BOX.lo + (BOX.hi - BOX.lo) * rng.uniform(-0.1, 1.1, (60, 2)), [[np.nan, 0.5]]])
    Ds = rng.uniform(0.01, 0.2, sites.shape[0])

    def run(comm):
        dec, _ = bisect(x[comm.rank::comm.size], comm.size, domain=BOX, comm=comm)
        mine = dec.locate(x) == comm.rank
        view = View(Confinement(BOX, None), comm, dec)
        keys = np.flatnonzero(mine).astype(np.int64)
        around = view.around(x[mine], keys, 0.05 * (1 + comm.rank), x[mine, 0])
        mine_sites = sites[comm.rank::comm.size]
        copies = view._site_copies(mine_sites, Ds[comm.rank::comm.size], np.arange(mine_sites.shape[0]) * 7 + comm.rank)
        return [a for part in (around, copies[:5]) for a in part]

    filtered = run_threads(6, run)
    monkeypatch.setattr(Decomposition, "reaching", every_rank)
    every = run_threads(6, run)
    for f, e in zip(filtered, every):
        assert all(a.tobytes() == b.tobytes() and a.shape == b.shape for a, b in zip(f, e))


@pytest.mark.parametrize("domain", [BOX, arpy.Domain([[-1.0, 0.25], [2.0, 1.25]])], ids=["periodic", "walls"])
def test_particles_held_outside_their_boxes_see_every_particle_within_reach(domain):
    """View.hold: own particles held on their rank after a move took them out of its box (as the
    self-organization holds them after a descent until the next migration).  On 3 thread ranks, Near's
    own rows are the lists of brute force (min rule, minimum image along the periodic axis), by key,
    and around brings every particle within its width of an own one.  Without the hold's slack some
    pairs are missed."""
    rng = np.random.default_rng(11)
    n = 1500
    x = rng.uniform(domain.lo, domain.hi, (n, 2))
    moved = domain.confine(x + rng.uniform(-0.06, 0.06, (n, 2)))
    rc = rng.uniform(0.04, 0.12, n)
    keys = np.arange(n, dtype=np.int64)
    period = np.where(domain.periodic, domain.hi - domain.lo, 0.0)
    diff = moved[:, None, :] - moved[None, :, :]
    diff -= period * np.round(diff / np.where(period > 0, period, 1.0))
    dist = np.sqrt((diff ** 2).sum(axis=2))
    pairs = (dist <= np.minimum(rc[:, None], rc[None, :])) & ~np.eye(n, dtype=bool)
    width = 0.1

    def run(comm):
        dec, _ = bisect(x, comm.size, domain=domain, comm=comm) if comm.rank == 0 else \
            bisect(x[:0], comm.size, domain=domain, comm=comm)
        mine = np.flatnonzero(dec.locate(x) == comm.rank)          # (owners by the positions before the move)
        view = View(Confinement(domain, None), comm, dec)
        view.hold(moved[mine])
        near = view.near(moved[mine], rc[mine], keys[mine], rc[mine])
        rows = [np.sort(near.keys[near.nl.indices[near.nl.offsets[i]:near.nl.offsets[i + 1]]])
                for i in range(near.n)]
        xa, ka = view.around(moved[mine], keys[mine], width, keys[mine].astype(float))
        return mine, view.slack, rows, ka.astype(np.int64)

    got = run_threads(3, run)
    assert min(g[1] for g in got) > 0.01                           # (the move took particles out of their boxes)
    assert sorted(np.concatenate([g[0] for g in got]).tolist()) == list(range(n))
    for mine, _, rows, ka in got:
        for p, row in zip(mine.tolist(), rows):
            assert row.tolist() == np.flatnonzero(pairs[p]).tolist()
        within = np.flatnonzero((dist[mine] <= width).any(axis=0))
        assert np.isin(within, ka).all()
