"""The self-organization's insertion conflicts on thread ranks: View.sites keeps exactly the sites that
site_conflicts keeps of every rank's sites together (the greedy, checked by brute force), while each rank
receives only the sites that can conflict with its own."""

import numpy as np
import pytest

import arpy
from arpy.adapt.view import Confinement, View, site_conflicts
from arpy.distributed import Decomposition, bisect, run_threads
from conftest import Held

#: Seconds a test of this module may take (pytest-timeout): ranks that wait forever fail the test.
pytestmark = pytest.mark.timeout(60)

#: Where the boxes are cut: free space (the outer boxes reach on to infinity), a periodic unit square,
#: and boxes that stop at the faces of the decomposed box (no open axis), sites lying beyond them.
DOMAINS = {"free space": arpy.Domain(), "periodic": arpy.Domain([1.0, 1.0], periodic=True), "closed boxes": None}


def greedy(x, D):
    """The greedy by brute force, sites in their order: a site stays unless an earlier site that stays
    lies closer than half the smaller of their D (free space)."""
    kept = np.zeros(len(x), bool)
    for i in range(len(x)):
        r = np.sqrt(((x[:i][kept[:i]] - x[i]) ** 2).sum(axis=1))
        kept[i] = not np.any(r < 0.5 * np.minimum(D[:i][kept[:i]], D[i]))
    return kept


def whole_set(x, D, pk, deal, parts):
    """The mask over every site that the ranks' masks must give: site_conflicts of every rank's sites in
    rank order, sorted by parent key (stable), as View.sites took it from a gather; and that is the
    greedy in that order."""
    cat = np.concatenate([np.flatnonzero(deal == r) for r in range(parts)])
    order = cat[np.argsort(pk[cat], kind="stable")]
    kept = np.empty(len(pk), bool)
    kept[order] = site_conflicts(x[order], D[order])
    assert np.array_equal(kept[order], greedy(x[order], D[order]))
    return kept


#: The points the boxes are bisected from (whatever the sites): an 8 x 8 grid in the unit square.
GRID = (np.stack(np.meshgrid(np.arange(8), np.arange(8)), -1).reshape(-1, 2) + 0.5) / 8


def boxes(comm, parts, domain):
    """The boxes of ``parts`` ranks bisected from GRID (comm None: on this process alone); domain None:
    free space, the boxes closed at the grid's bounding box."""
    dec, _ = bisect(GRID if comm is None else GRID[comm.rank::parts], parts, domain=domain, comm=comm)
    return Decomposition(dec.lo, dec.hi) if domain is None else dec


def decided_on_ranks(x, D, pk, deal, parts, domain, comm_of=lambda comm: comm):
    """View.sites on ``parts`` thread ranks, rank r holding the sites ``deal == r``: (the mask over
    every site, per rank what ``comm_of`` returned)."""
    def rank(comm):
        c = comm_of(comm)
        mine = deal == comm.rank
        view = View(Confinement(domain or arpy.Domain(), None), c, boxes(comm, parts, domain))
        return view.sites(x[mine], D[mine], pk[mine]), c

    got = run_threads(parts, rank)
    kept = np.zeros(len(pk), bool)
    for r, (k, _) in enumerate(got):
        assert k.dtype == bool and k.shape == (np.count_nonzero(deal == r),)
        kept[deal == r] = k
    return kept, [c for _, c in got]


def chain(rng, parts, domain):
    """Chains of sites, each conflicting with its two neighbours in the chain only (D = 0.05): on a line
    across the boxes (spaced 0.998 of the conflict distance), and zigzagging across a face of box 0 (each
    link crossing it), dealt to the ranks in turn (most outside their rank's box); parent keys along the
    chain (a chain that alternates between ranks at every link), reversed, or shuffled."""
    D = 0.05
    t = np.arange(0.01, 0.99, 0.998 * 0.5 * D)
    lines = [np.stack([t, 0.5 + 1e-3 * np.sin(7 * t)], axis=1)]
    if parts > 1:
        dec = boxes(None, parts, domain)
        ax = int(np.flatnonzero(dec.hi[0] < dec.hi.max(axis=0))[0])        # a face of box 0 inside
        along = np.arange(max(dec.lo[0][1 - ax], 0.02), min(dec.hi[0][1 - ax], 0.98), 0.0235)
        zig = np.empty((along.size, 2))
        zig[:, ax], zig[:, 1 - ax] = dec.hi[0][ax] + 0.004 * (-1.0) ** np.arange(along.size), along
        lines.append(zig)
    for x in lines:
        m = len(x)
        for pk in (np.arange(m), np.arange(m)[::-1].copy(), rng.permutation(m)):
            yield x, np.full(m, D), pk.astype(np.int64), np.arange(m) % parts


def straddling(rng, parts, domain):
    """Pairs of sites across a face of box 0 (D of 0.02 to 0.05), one 0.002 D inside the box and one
    0.496 D beyond the face (0.498 D apart: a conflict that a reach short of 0.5 D misses), far from
    the other pairs, dealt at random, parent keys shuffled."""
    if parts == 1:
        return
    dec = boxes(None, parts, domain)
    ax = int(np.flatnonzero(dec.hi[0] < dec.hi.max(axis=0))[0])
    along = np.arange(max(dec.lo[0][1 - ax], 0.0) + 0.06, min(dec.hi[0][1 - ax], 1.0) - 0.06, 0.12)
    D = np.repeat(rng.uniform(0.02, 0.05, along.size), 2)
    x = np.empty((2 * along.size, 2))
    x[:, 1 - ax] = np.repeat(along, 2)
    x[:, ax] = dec.hi[0][ax] + np.tile([-0.002, 0.496], along.size) * D
    yield x, D, rng.permutation(len(D)).astype(np.int64), rng.integers(0, parts, len(D))


def cloud(rng, parts, domain):
    """Scattered sites with D over a decade (spread beyond the unit square where the boxes are closed),
    parent keys repeated within and across ranks, dealt at random (rank 0 without sites when there are
    three ranks or more), and pairs of sites at opposite faces of the unit square (closer by the periodic
    image, apart in free space, as site_conflicts takes them)."""
    n = 240
    x = rng.random((n, 2)) * 1.6 - 0.3 if domain is None else rng.random((n, 2))
    x[:20] = np.stack([np.full(20, 0.002), rng.random(20)], axis=1)
    x[20:40] = x[:20] + [0.995, 0.0]
    D = 0.02 * 10.0 ** rng.random(n)
    pk = rng.integers(0, 40, n).astype(np.int64)
    deal = rng.integers(1 if parts > 2 else 0, parts, n)
    yield x, D, pk, deal


@pytest.mark.parametrize("where", list(DOMAINS))
def test_sites_on_ranks_keep_what_the_whole_set_keeps(where):
    """View.sites on 1 to 5 thread ranks gives every rank the mask of its sites that site_conflicts (equal
    to the greedy by brute force) gives over every rank's sites together in the order of their parents'
    keys (repeats by rank, then place on the rank): chains alternating between ranks at every link,
    conflicts across a face as far apart as a conflict can be, repeated keys, sites outside their rank's
    box, a rank without sites, sites at opposite periodic faces."""
    rng = np.random.default_rng([5, list(DOMAINS).index(where)])
    for parts in (1, 2, 3, 4, 5):
        for make in (chain, straddling, cloud):
            for x, D, pk, deal in make(rng, parts, DOMAINS[where]):
                want = whole_set(x, D, pk, deal, parts)
                assert 0 < want.sum() < len(want)
                kept, _ = decided_on_ranks(x, D, pk, deal, parts, DOMAINS[where])
                assert np.array_equal(kept, want), (parts, make.__name__)


def test_no_rank_receives_every_site():
    """At P = 4, sites near their parents (each inside its rank's box, the sites up to D beyond it) are
    decided as over the whole set, and no rank receives in View.sites' exchanges a tenth of what the
    gather of every rank's sites brought each rank (their positions, D and parent keys)."""

    rng = np.random.default_rng(8)
    domain, D = DOMAINS["periodic"], 0.02
    parents = rng.random((2000, 2))
    angle, rho = 2 * np.pi * rng.random(2000), D * rng.uniform(0.5, 1.0, 2000)
    x = domain.wrap(parents + rho[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1))
    pk = np.arange(2000, dtype=np.int64)
    deal = boxes(None, 4, domain).locate(parents)
    want = whole_set(x, np.full(2000, D), pk, deal, 4)
    kept, held = decided_on_ranks(x, np.full(2000, D), pk, deal, 4, domain, Held)
    assert np.array_equal(kept, want)
    gathered = 2000 * (2 + 1 + 1)
    assert max(h.numbers for h in held) < gathered / 10, [h.numbers for h in held]
