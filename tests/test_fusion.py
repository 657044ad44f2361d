"""The self-organization's fusion on thread ranks: _scan fuses on every rank count exactly the pairs that
greedy_matching takes of every rank's candidates together (itself checked against the greedy by brute
force), while each rank receives only the candidates at the particles within its reach."""

import numpy as np
import pytest

import arpy
from arpy.adapt.adaptation import INSERT_MARGIN, _scan
from arpy.adapt.resolution import r_star
from arpy.adapt.view import Confinement, View
from arpy.distributed import Decomposition, bisect, run_threads
from conftest import Held

#: Seconds a test of this module may take (pytest-timeout): ranks that wait forever fail the test.
pytestmark = pytest.mark.timeout(60)

RS = r_star(2)
DOMAINS = {"free space": arpy.Domain().for_dim(2), "periodic": arpy.Domain([1.0, 1.0], periodic=True)}
#: The points the boxes are bisected from (whatever the particles): an 8 x 8 grid in the unit square.
GRID = (np.stack(np.meshgrid(np.arange(8), np.arange(8)), -1).reshape(-1, 2) + 0.5) / 8


def greedy(x, D, keys, domain):
    """The pairs (ka, kb) that fuse, by brute force: every pair closer than half the smaller D (minimum
    image along periodic axes) in the order of (r / D_pq, smaller key, larger key), taken when neither
    particle is in a pair taken before."""
    i, j = np.triu_indices(len(x), 1)
    e = x[i] - x[j]
    e -= domain.period * np.round(e / np.where(domain.period > 0, domain.period, 1.0))
    rho = np.sqrt((e * e).sum(axis=1)) / np.minimum(D[i], D[j])
    close = rho < 0.5
    pairs = sorted(zip(rho[close], np.minimum(keys[i], keys[j])[close], np.maximum(keys[i], keys[j])[close]))
    used, taken = set(), []
    for _, a, b in pairs:
        if a not in used and b not in used:
            used |= {a, b}
            taken.append((a, b))
    return taken


def scanned(x, D, keys, parts, domain, comm_of=lambda comm: comm, dec=None):
    """_scan on ``parts`` thread ranks, each particle on the rank whose box (``dec``, or bisected from
    GRID) holds it: (positions after fusion, alive, neighbours alive, fusions) of every particle, and per
    rank what ``comm_of`` returned (the scan's communicator; the particles within reach come by ``comm``)."""
    dec = dec or bisect(GRID, parts, domain=domain)[0]
    owner = dec.locate(x)

    def rank(comm):
        mine = np.flatnonzero(owner == comm.rank)
        mine = mine[np.argsort(keys[mine])]
        near = View(Confinement(domain, None), comm, dec).near(x[mine], D[mine], keys[mine], RS * D[mine])
        c = comm_of(comm)
        return mine, _scan(near, domain.period, INSERT_MARGIN * RS, View(Confinement(domain, None), c, dec)), c

    xo, alive, cnt = np.full_like(x, np.nan), np.zeros(len(x), bool), np.full(len(x), -1)
    got = run_threads(parts, rank)
    for mine, out, _ in got:
        xo[mine], alive[mine], cnt[mine] = out[0], out[1], out[3]
    assert len({out[5] for _, out, _ in got}) == 1              # (the count of fusions: a sum over the ranks)
    return (xo, alive, cnt, got[0][1][5]), [c for _, _, c in got]


def spiral(dec, D, turns=4, r0=0.07):
    """Points along a spiral round a point on a face of box 0 (of the boxes ``dec``; the middle of the
    square on one box), its arms 0.6 D apart, from radius r0 (beyond the particles within reach of the
    other side) on: the path crosses the face twice a turn.  The points are 0.3 D apart along it and a
    little farther at each step, more than the bend shortens them."""
    ax = int(np.flatnonzero(dec.hi[0] < dec.hi.max(axis=0))[0]) if dec.parts > 1 else 0
    centre = np.full(2, 0.5)
    if dec.parts > 1:
        centre[ax] = dec.hi[0][ax]
        centre[1 - ax] = 0.5 * (max(dec.lo[0][1 - ax], 0.0) + min(dec.hi[0][1 - ax], 1.0))
    b = 0.6 * D / (2 * np.pi)
    theta = np.linspace(0.0, 2 * np.pi * turns, 200000)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(r0 + b * theta[1:], b) * np.diff(theta))])
    step = 0.3 * D * (1.0 + 1e-3 * np.arange(int(arc[-1] / (0.3 * D))))
    u = np.cumsum(step) - step[0]
    t = np.interp(u[u < arc[-1]], arc, theta)
    return centre + (r0 + b * t)[:, None] * np.stack([np.cos(t), np.sin(t)], axis=1)


def chains(rng, dec, domain):
    """Chains of close pairs (each particle close to its two neighbours in the chain only): a spiral
    across a face of box 0 whose spacing grows along it, so that each link waits for the one before
    (D = 2^-5); and with every link as close (ties in r / D_pq): a ring round the periodic axis, across
    its face (D = 0.04), or a line across the boxes (D = 2^-5).  Keys along the chain, reversed and
    shuffled."""
    D = 2.0 ** -5
    t = np.arange(64)
    sets = [(spiral(dec, D), D)]
    if domain.any_periodic:
        sets.append((np.stack([(t + 0.5) / 64, np.full(64, 0.3)], axis=1), 0.04))
    else:
        sets.append((np.stack([0.125 + 0.375 * D * t, np.full(64, 0.53125)], axis=1), D))
    for x, D in sets:
        m = len(x)
        for keys in (np.arange(m), np.arange(m)[::-1], rng.permutation(m)):
            yield x, np.full(m, D), keys.astype(np.int64)


def patches(rng, dec, domain):
    """A square lattice spaced 0.375 D (D = 2^-5: every close pair exactly as close) over the middle of
    the square, and a cloud of D over a decade with coincident particles (r = 0 for every pair among
    them) in clusters across the middle, no particle in box 0 from three ranks on (a rank without
    particles); keys shuffled."""
    D = 2.0 ** -5
    g = 0.5 + 0.375 * D * (np.arange(9) - 4.0)
    x = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    yield x, np.full(len(x), D), rng.permutation(len(x)).astype(np.int64)
    n = 500
    x = rng.random((n, 2))
    x[:60] = np.repeat(0.5 + rng.normal(size=(12, 2)) * 0.003, 5, axis=0)
    D = 0.01 * 10.0 ** rng.random(n)
    keep = dec.locate(x) != 0 if dec.parts >= 3 else np.ones(n, bool)
    yield x[keep], D[keep], rng.permutation(10 * n)[: keep.sum()].astype(np.int64)


def padded(x, D, keys):
    """The set with the points of GRID farther than 0.15 from every particle added (D = 2^-5, keys after
    the others): particles on every rank (the scan's core takes no empty set), none close to another."""
    far = np.sqrt(((GRID[:, None, :] - x[None]) ** 2).sum(axis=2)).min(axis=1) > 0.15
    return (np.concatenate([x, GRID[far]]), np.concatenate([D, np.full(far.sum(), 2.0 ** -5)]),
            np.concatenate([keys, keys.max() + 1 + np.arange(far.sum())]))


@pytest.mark.parametrize("where", list(DOMAINS))
def test_fusion_on_ranks_takes_what_the_whole_set_takes(where):
    """_scan on 2 to 5 thread ranks fuses exactly the pairs the greedy by brute force takes of the whole
    set, with the one-process scan's positions bit for bit and the same counts of neighbours alive (the
    fates of the particles of other ranks too): chains across boxes whose links are decided one after
    the other, a chain round the periodic axis, ties in r / D_pq (a lattice, coincident particles), keys
    in any order, a rank without particles."""
    domain = DOMAINS[where]
    rng = np.random.default_rng([55, list(DOMAINS).index(where)])
    for parts in (2, 3, 4, 5):
        dec, _ = bisect(GRID, parts, domain=domain)
        for make in (chains, patches):
            for x, D, keys in make(rng, dec, domain):
                x, D, keys = padded(x, D, keys)
                (xo, alive, cnt, fused), _ = one = scanned(x, D, keys, 1, domain)
                taken = greedy(x, D, keys, domain)
                assert fused == len(taken) > 5 and alive.sum() == len(x) - fused
                assert np.array_equal(np.sort(keys[~alive]), np.sort([b for _, b in taken]))
                got, _ = scanned(x, D, keys, parts, domain)
                for a, b in zip(got, one[0]):
                    assert np.array_equal(a, b, equal_nan=True), (parts, make.__name__)


def test_a_pair_one_owner_decides_first_reaches_every_rank_holding_a_particle():
    """Three ranks side by side, u | s | t (boxes of widths 0.4, 0.1, 0.5): p on s holds u within its
    reach (D = 0.1), its close partner q on t does not (D = 0.01), and q's closer partner z (D = 0.0015)
    lies beyond s's reach.  t decides (q, z), then (p, q) in its first round; s cannot (it does not hold
    z) and learns (p, q) from t, and must pass it on to u, which holds p but not q.  The same fusions as
    on one process, and as the greedy by brute force."""
    domain = DOMAINS["free space"]
    x = np.array([[0.4976, 0.5], [0.5025, 0.5], [0.503, 0.5], [0.1, 0.5]])          # p, q, z and one on u
    D = np.array([0.1, 0.01, 0.0015, 0.05])
    keys = np.arange(len(x), dtype=np.int64)
    dec = Decomposition(np.array([[0.0, 0.0], [0.4, 0.0], [0.5, 0.0]]), np.array([[0.4, 1.0], [0.5, 1.0], [1.0, 1.0]]))
    assert dec.locate(x).tolist() == [1, 2, 2, 0]
    one, _ = scanned(x, D, keys, 1, domain)
    assert greedy(x, D, keys, domain) == [(1, 2)] and one[3] == 1 and one[1].tolist() == [1, 1, 0, 1]
    got, _ = scanned(x, D, keys, 3, domain, dec=dec)
    for a, b in zip(got, one):
        assert np.array_equal(a, b, equal_nan=True)


def test_no_rank_receives_every_candidate():
    """At P = 4 in the periodic square, 2500 close pairs apart from each other (no chains; D = 0.003,
    some across the faces of the boxes) fuse as on one process, and no rank receives in the scan's
    exchanges a tenth of what a gather of every rank's candidates (r / D_pq and two keys each) brings
    each rank, while every rank receives some (the pairs at the particles of other ranks within its
    reach, and their states)."""
    rng = np.random.default_rng(12)
    domain, D = DOMAINS["periodic"], 0.003
    centres = (np.stack(np.meshgrid(np.arange(50), np.arange(50)), -1).reshape(-1, 2) + 0.5) / 50
    centres += rng.uniform(-0.007, 0.007, centres.shape)
    angle = 2 * np.pi * rng.random(len(centres))
    half = 0.2 * D * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    x = domain.wrap(np.concatenate([centres - half, centres + half]))
    keys = rng.permutation(len(x)).astype(np.int64)
    one, _ = scanned(x, np.full(len(x), D), keys, 1, domain)
    assert one[3] == 2500
    got, held = scanned(x, np.full(len(x), D), keys, 4, domain, Held)
    for a, b in zip(got, one):
        assert np.array_equal(a, b, equal_nan=True)
    gathered = 3 * 2500 * 3 // 4
    numbers = [h.numbers for h in held]
    assert 30 < min(numbers) and max(numbers) < gathered / 10, numbers
