"""One path for one process and for many: a Simulation runs the same code at P = 1 (no ``comm``) and on
P ranks, so its results are bitwise the same for every rank count, also on a box whose lower corner is
not 0 (where wrapping a position across a periodic face would round it), with mixed periodic and wall
axes (also with a Dirichlet wall), with forward Euler and RK4, with and without re-organization; and the
particle container takes any deal of the particles to the ranks."""

import numpy as np
import pytest

import arpy
from arpy.distributed import SerialComm, run_threads
from arpy.particles import Particles

#: Seconds a test of this module may take (pytest-timeout): ranks that wait forever fail the test.
pytestmark = pytest.mark.timeout(60)

#: x in [-1, 2] periodic, y in [0.25, 1.25] between walls.
BOX = arpy.Domain([[-1.0, 0.25], [2.0, 1.25]], periodic=[True, False])


def shifted_set(n: int = 900, seed: int = 3):
    """Particles self-organized to a uniform spacing in BOX."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(BOX.lo, BOX.hi, (n, 2))
    return arpy.self_organize(x0, lambda p: np.full(len(p), 0.09), domain=BOX, seed=seed)


def velocity(p, t, f):
    """A shear flow along the periodic axis, strong enough to carry particles across its faces."""
    return np.stack([2.0 + np.sin(np.pi * p[:, 1]), 0.05 * np.cos(2 * np.pi * p[:, 0] / 3.0)], axis=1)


def wave(p):
    return np.sin(2 * np.pi * p[:, 0] / 3.0) * np.cos(np.pi * (p[:, 1] - 0.25))


@pytest.fixture(scope="module")
def organized():
    return shifted_set()


def shifted_run(organized, comm, integrator: str, reorganize_every: int, verlet_skin: float = 0.0):
    """Steps of the shear flow in BOX (on the ranks of comm; None: one process): 7 without
    re-organization (particles cross the periodic faces), 4 with one every 3 (two re-organizations);
    returns the whole set in key order (keys, x, D, F) and the particle count of every step."""
    steps = 7 if reorganize_every == 0 else 4
    sim = arpy.Simulation(organized, wave, comm=comm, velocity=velocity, nu=0.02, D0=0.12, dt=0.004,
                          integrator=integrator, reorganize_every=reorganize_every, seed=2, verlet_skin=verlet_skin)
    for _ in range(steps):
        sim.step()
    return sim.gather(), sim.history()["n"]


@pytest.mark.parametrize("integrator", ["euler", "rk4"])
@pytest.mark.parametrize("reorganize_every", [0, 3])
def test_simulation_is_bitwise_the_same_on_any_rank_count_on_a_shifted_mixed_box(organized, integrator,
                                                                                 reorganize_every):
    def run(comm):
        return shifted_run(organized, comm, integrator, reorganize_every)

    (k0, x0, D0, F0), n0 = run(None)
    # the particles crossed the periodic faces, and every position lies in the box, its bits as wrapped
    if reorganize_every == 0:
        assert np.count_nonzero(np.abs(x0[:, 0] - organized.x[:, 0]) > 1.5) >= 5
    assert np.all((x0[:, 0] >= -1.0) & (x0[:, 0] < 2.0))         # (walls confine at re-organizations only)
    assert BOX.wrap(x0).tobytes() == x0.tobytes()
    np.testing.assert_array_equal(k0, np.arange(len(k0)))
    for parts in (1, 2, 3):
        (k, x, D, F), n = run_threads(parts, run, timeout=120)[0]
        np.testing.assert_array_equal(n, n0)
        np.testing.assert_array_equal(k, k0)
        assert x.tobytes() == x0.tobytes() and D.tobytes() == D0.tobytes() and F.tobytes() == F0.tobytes(), parts


def tangential(p, t, f):
    """A shear flow along the periodic axis whose y component vanishes on both walls of BOX."""
    return np.stack([2.0 + np.sin(np.pi * p[:, 1]),
                     0.05 * np.cos(2 * np.pi * p[:, 0] / 3.0) * np.sin(np.pi * (p[:, 1] - 0.25))], axis=1)


def walled_run(organized, comm, integrator: str, reorganize_every: int):
    """2 steps in BOX with a Dirichlet value on the lower wall (moving in x and t) and a Neumann flux on
    the upper one (on the ranks of comm; None: one process); returns the whole set in key order."""
    from arpy.dcpse.boundary import Dirichlet, Neumann

    walls = {"y-": Dirichlet(lambda w, t: np.sin(2 * np.pi * w[:, 0] / 3.0) + t), "y+": Neumann(0.5)}
    sim = arpy.Simulation(organized, wave, comm=comm, velocity=tangential, nu=0.02, D0=0.12, Dmin=0.08, dt=0.004,
                          integrator=integrator, reorganize_every=reorganize_every, seed=2, boundary=walls)
    for _ in range(2):
        sim.step()
    return sim.gather(), sim.history()["n"]


@pytest.mark.parametrize("integrator, reorganize_every", [("rk4", 0), ("euler", 2)])
def test_dirichlet_walls_are_bitwise_the_same_on_any_rank_count(integrator, reorganize_every):
    """Dirichlet walls on ranks (issue 55's last refusal): the boundary particles, the one-sided rows,
    the particles snapped onto the wall and the old -> new operator of the re-organizations run over
    1-3 thread ranks bitwise as one process, on BOX (lo != 0, periodic x, walls in y), RK4 on fixed
    particles and forward Euler with a re-organization."""
    organized = arpy.self_organize(np.random.default_rng(3).uniform(BOX.lo, BOX.hi, (500, 2)),
                                   lambda p: np.full(len(p), 0.12), domain=BOX, seed=3)
    (k0, x0, D0, F0), n0 = walled_run(organized, None, integrator, reorganize_every)
    on_wall = x0[:, 1] == 0.25
    assert on_wall.sum() >= 10 and n0[-1] > (2 * organized.n if reorganize_every else organized.n - 1)
    for parts in (1, 2, 3):
        (k, x, D, F), n = run_threads(parts, lambda comm: walled_run(organized, comm, integrator, reorganize_every),
                                      timeout=120)[0]
        np.testing.assert_array_equal(n, n0)
        np.testing.assert_array_equal(k, k0)
        assert x.tobytes() == x0.tobytes() and D.tobytes() == D0.tobytes() and F.tobytes() == F0.tobytes(), parts


def test_wrapping_keeps_the_bits_of_positions_inside_the_box():
    """lo + (x - lo) mod L rounds x when lo != 0; positions inside the box come back unchanged, those
    outside land inside, and wrapping twice changes nothing."""
    rng = np.random.default_rng(0)
    x = rng.uniform([-0.01, 0.3], [0.01, 1.2], (2000, 2))     # small |x|: x - lo rounds
    rounded = BOX.lo + np.mod(x - BOX.lo, BOX.edge)
    assert np.count_nonzero(rounded[:, 0] != x[:, 0]) > 100    # (the formula alone would move them)
    assert BOX.wrap(x).tobytes() == x.tobytes()
    y = x.copy()
    y[:50, 0] += 3.0
    y[50:100, 0] -= 3.0
    w = BOX.wrap(y)
    assert np.all((w[:, 0] >= -1.0) & (w[:, 0] < 2.0)) and np.abs(w - x).max() < 1e-14
    assert BOX.wrap(w).tobytes() == w.tobytes()
    np.testing.assert_array_equal(w[:, 1], y[:, 1])            # the wall axis is never wrapped


@pytest.mark.parametrize("parts", [2, 3])
def test_any_deal_of_the_particles_gives_the_same_set_and_operators(organized, parts):
    """Particles.dealt with a random deal to the ranks, or every P-th particle: each rank owns the
    particles of its box, its ghost layer holds every neighbour of its particles (brute force), the
    whole set gathers back in key order, and the distributed Laplacian over the container's particles
    and ghosts gives bitwise the one-process values."""
    from arpy.distributed import DistributedDCPSE

    x, D = organized.x, organized.D
    F = wave(x)[:, None]
    deal = np.random.default_rng(parts).integers(0, parts, len(x))

    def laplacian(p: Particles) -> np.ndarray:
        op = DistributedDCPSE(p.comm, p.decomposition, p.x, p.eps, p.keys, domain=BOX, strict=False, reorder=False)
        return op.laplacian() @ op.extend(p.F[:, 0])

    e = x[:, None, :] - x[None, :, :]
    e[..., 0] -= 3.0 * np.round(e[..., 0] / 3.0)                  # minimum image along the periodic x
    eps = organized.rstar * D
    want_rows = np.sqrt((e ** 2).sum(axis=2)) <= np.minimum(eps[:, None], eps[None, :])
    one = Particles.dealt(x, D, F, ["f"], domain=BOX, rstar=organized.rstar)
    assert isinstance(one.comm, SerialComm) and one.n == len(x)
    want = laplacian(one)

    def rank(comm, how):
        p = Particles.dealt(x, D, F, ["f"], domain=BOX, rstar=organized.rstar, comm=comm, deal=how)
        assert np.all(p.decomposition.locate(p.x) == comm.rank)
        lap = laplacian(p)
        keys, xs, Ds, Fs = p.gather()
        from arpy.distributed import gather

        # the ghost layer holds every neighbour (min rule, minimum image) of this rank's particles
        layer = p.ghosts(p.eps)
        known = set(p.keys.tolist()) | set(layer.keys.tolist())
        assert all(set(np.flatnonzero(want_rows[k]).tolist()) <= known for k in p.keys.tolist())
        return keys, xs, Ds, Fs, gather(comm, p.keys, lap)[1], p.total(p.n)

    for how in (deal, None):
        keys, xs, Ds, Fs, lap, total = run_threads(parts, lambda comm: rank(comm, how))[0]
        np.testing.assert_array_equal(keys, np.arange(len(x)))
        assert total == len(x)
        assert xs.tobytes() == x.tobytes() and Ds.tobytes() == D.tobytes() and Fs.tobytes() == F.tobytes()
        assert lap.tobytes() == want.tobytes()
    with pytest.raises(ValueError, match="deal must give each"):
        Particles.dealt(x, D, F, ["f"], domain=BOX, rstar=organized.rstar, deal=np.full(len(x), 1))


def test_a_rank_share_is_taken_to_its_box_or_refused(organized):
    """self_organize and field_resolution with keys= on thread ranks: particles dealt at random are
    migrated to the bisected boxes (without decomposition=) and give the one-process result; with boxes
    that do not own them every rank raises the same clear error; global keys are required."""
    from arpy.distributed import bisect

    x, D = organized.x, organized.D
    f = wave(x)
    one = arpy.field_resolution(x, f, D, D0=0.12, Dmin=0.05, domain=BOX, strict=False)(x)
    deal = np.random.default_rng(9).integers(0, 2, len(x))

    def rank(comm, boxes):
        mine = np.flatnonzero(deal == comm.rank)
        dec = bisect(x, 2, domain=BOX)[0] if boxes else None
        res = arpy.field_resolution(x[mine], f[mine], D[mine], D0=0.12, Dmin=0.05, domain=BOX, strict=False,
                                    comm=comm, keys=mine, decomposition=dec)
        return res(x[mine]), mine

    got = run_threads(2, lambda comm: rank(comm, False))
    for values, mine in got:
        assert values.tobytes() == one[mine].tobytes()
    with pytest.raises(ValueError, match="outside the box of the rank"):
        run_threads(2, lambda comm: rank(comm, True))
    with pytest.raises(ValueError, match="global keys"):
        run_threads(2, lambda comm: arpy.field_resolution(x, f, D, D0=0.12, domain=BOX, comm=comm))


def test_a_self_organized_start_share_has_the_same_keys_on_any_rank_count():
    """self_organize(**start_share(x, comm)): the adapted set's keys (the start's indices, then the
    inserted particles' keys; fused ones gone) and positions are the same on one process and on 2 and 3
    thread ranks.  The keys are not 0 .. N - 1 here (fusion and insertion leave gaps), so a one-process
    run that renumbered them would differ."""
    from arpy.adapt.organize import start_share
    from arpy.distributed import gather

    box = arpy.Domain([[0.0, 0.0], [1.0, 1.0]])
    x = np.random.default_rng(5).uniform(0, 1, (600, 2))

    def run(comm):
        ps = arpy.self_organize(**start_share(x, comm), resolution=lambda p: 0.03 + 0.1 * np.abs(p[:, 0] - 0.5),
                                domain=box, seed=3, comm=comm)
        return gather(comm or SerialComm(), ps.keys, ps.x)[:2]

    keys, pos = run(None)
    assert not np.array_equal(keys, np.arange(keys.size))
    for parts in (2, 3):
        k, p = run_threads(parts, run)[0]
        assert k.tobytes() == keys.tobytes() and p.tobytes() == pos.tobytes(), parts
