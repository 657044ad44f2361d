"""Simulation options on ranks that one process took first: reused lists (``verlet_skin``), fixed
particles (``reorganize_every=0``) and the paper's stencil rule (on the initial set too), bitwise the
one-process run on thread ranks."""

from __future__ import annotations

import numpy as np
import pytest

import arpy
from arpy.distributed import run_threads


def _same(a, b) -> bool:
    return all(u.tobytes() == v.tobytes() for u, v in zip(a, b))


@pytest.fixture(scope="module")
def vortex_set():
    """Particles of a blob in a box periodic along x with walls along y (periodic images and mirror
    images both), and the RK4 options of the reversing vortex."""
    from arpy.cases.reversing_vortex import blob, blob_monitor, vortex

    box = arpy.Domain([1.0, 1.0], periodic=(True, False))
    ps = arpy.self_organize(np.random.default_rng(1).random((300, 2)), resolution=lambda p: blob_monitor(p, 0.15),
                            domain=box, seed=1)
    return ps, blob, dict(velocity=vortex(2.5), nu=1e-3, D0=0.15, integrator="rk4", dt=0.004, seed=1)


def test_verlet_skin_on_ranks_is_bitwise_the_run_without_it(vortex_set):
    """verlet_skin in a box keeps the ghost layer and the rows (KeptGhosts) across stages and steps:
    the lists are built fewer times than the operators, yet the particles and the field are bitwise
    those of new lists at every stage (verlet_skin=0, one process) on one process and on 3 thread
    ranks, through a re-organization (the lists built again on the new particles)."""
    ps, blob, kw = vortex_set

    def run(comm, skin):
        sim = arpy.Simulation(ps, blob, reorganize_every=3, verlet_skin=skin, comm=comm, **kw)
        for _ in range(3):
            sim.step()
        return sim.gather(), getattr(sim._lists, "builds", None)

    fresh, _ = run(None, 0.0)
    kept, builds = run(None, 0.4)
    assert builds < 8                                     # 12 operators at the particles (3 RK4 steps)
    assert _same(kept, fresh)
    assert _same(run_threads(3, lambda comm: run(comm, 0.4)[0])[0], fresh)


def _rule_set():
    """A jittered lattice with a hole holding 36 collinear particles (singular moments: displaced) and
    a lone one (too few neighbours: new particles around it), and a coarser old set."""
    rng = np.random.default_rng(3)
    g = np.stack(np.meshgrid(np.linspace(0.025, 0.975, 20), np.linspace(0.025, 0.975, 20)), -1).reshape(-1, 2)
    g = g + 0.005 * rng.standard_normal(g.shape)
    g = g[np.abs(g - 0.5).max(axis=1) >= 0.15]
    x = np.vstack([g, np.column_stack([np.linspace(0.38, 0.62, 36), np.full(36, 0.5)]), [[0.5, 0.4]]])
    D = np.concatenate([np.full(len(g), 0.05), np.full(37, 0.03)])
    return x, D, (g[::3], np.full(len(g[::3]), 0.14))


@pytest.mark.parametrize("with_old", [False, True])
def test_the_papers_rule_on_ranks_is_the_one_process_rule(with_old):
    """displace_on_ranks (the rule of Sec. 2.2 over the ranks: rows by key, the one process's draws,
    new particles numbered after their parents' keys) on 2 and 3 thread ranks: the particles, their D
    and keys, and the figures are bitwise those of displace_until_valid on one process, in a box
    periodic along x with walls along y, with and without an old set to interpolate from."""
    from arpy.dcpse.displace import displace_on_ranks, displace_until_valid
    from arpy.distributed import bisect, migrate

    x, D, old = _rule_set()
    box = arpy.Domain([1.0, 1.0], periodic=(True, False))
    old = old if with_old else None
    xr, Dr, done = displace_until_valid(x, D, 2.0, domain=box, rng=7, old=old)
    assert done["displaced"] > 0 and done["inserted"] > 0

    def rank(comm):
        mine = np.arange(comm.rank, len(x), comm.size)
        dec, _ = bisect(x[mine], comm.size, domain=box, comm=comm)
        xs, ks, fl = migrate(comm, dec, x[mine], mine.astype(np.int64), {"D": D[mine]})
        own_old = None
        if old is not None:
            deal = np.arange(comm.rank, len(old[0]), comm.size)
            xo, ko, fo = migrate(comm, dec, old[0][deal], deal.astype(np.int64), {"eps": old[1][deal]})
            own_old = (xo, fo["eps"], ko)
        xn, Dn, kn, got = displace_on_ranks(comm, dec, xs, fl["D"], ks, 2.0, domain=box, rng=7, old=own_old)
        assert np.all(dec.locate(xn) == comm.rank) and np.array_equal(kn, np.sort(kn))
        parts = comm.allgather((kn, xn, Dn))
        k = np.concatenate([p[0] for p in parts])
        order = np.argsort(k)
        return k[order], np.concatenate([p[1] for p in parts])[order], np.concatenate([p[2] for p in parts])[order], got

    for parts in (2, 3):
        k, xn, Dn, got = run_threads(parts, rank)[0]
        assert got == done and np.array_equal(k, np.arange(len(xr)))
        assert xn.tobytes() == xr.tobytes() and Dn.tobytes() == Dr.tobytes(), parts


def test_a_simulation_with_the_papers_rule_on_ranks_is_the_one_process_run():
    """Simulation(stencil_rule="displace") re-organizing at every step (forward Euler; Eq. 2.9 read
    pointwise, which leaves particles with too few neighbours: the rule inserts some): bitwise the
    one-process run on 2 thread ranks."""
    from arpy.cases.reversing_vortex import blob, blob_monitor, vortex

    box = arpy.Domain([1.0, 1.0], periodic=(True, False))
    ps = arpy.self_organize(np.random.default_rng(1).random((150, 2)), resolution=lambda p: blob_monitor(p, 0.2),
                            domain=box, seed=1, max_iter=100)
    kw = dict(velocity=vortex(2.5), nu=1e-3, D0=0.2, Dmin=0.03, dt=0.004, seed=2, reorganize_every=1,
              stencil_rule="displace", reading="pointwise")

    def run(comm):
        sim = arpy.Simulation(ps, blob, comm=comm, **kw)
        for _ in range(2):
            sim.step()
        return sim.gather(), sim.history()["inserted"]

    one, inserted = run(None)
    assert inserted.sum() > 0
    two, got = run_threads(2, run)[0]
    assert _same(two, one) and np.array_equal(got, inserted)


def test_the_papers_rule_on_an_initial_set_in_shares_is_the_one_process_rule():
    """displace_set on each rank's share of an adapted set (no rank holding the whole set) displaces and
    inserts over the ranks exactly what it does on the whole set on one process (Eq. 2.9 read pointwise
    leaves stencils to fix), on 2 thread ranks, each keeping its share; and the advection case under
    stencil_rule="displace" on 2 thread ranks, its initial set adapted and displaced in shares, is
    bitwise the one-process run."""
    from arpy.adapt.organize import displace_set
    from arpy.cases import advection
    from arpy.cases.reversing_vortex import blob_monitor

    box = arpy.Domain([1.0, 1.0])
    whole = arpy.self_organize(np.random.default_rng(2).random((100, 2)), resolution=lambda p: blob_monitor(p, 0.4),
                               domain=box, seed=1, reading="pointwise", max_iter=100)   # (it cycles: unconverged)
    one, done = displace_set(whole, rng=3)
    assert done["failed"] > 0 and done["inserted"] > 0

    def shares(comm):                                  # (each rank's share, keyed by index, in its box)
        share = arpy.Particles.dealt(whole.x, whole.D, np.zeros((whole.n, 0)), (), domain=box, rstar=whole.rstar,
                                     comm=comm)
        got, did = displace_set(share, rng=3)
        return got.n, did, got.gather()

    for n, did, got in run_threads(2, shares):
        assert 0 < n < one.n and did == done
        assert _same(got, (np.arange(one.n), one.x, one.D))
    case = dict(D0=0.25, T=0.025, reorganize_every=1, stencil_rule="displace")
    serial = advection(**case)
    two = run_threads(2, lambda comm: advection(**case, comm=comm))
    assert all(0 < r["particles"].n < serial["particles"].n and r["error"] == serial["error"] for r in two)
    order = np.argsort(np.concatenate([r["keys"] for r in two]), kind="stable")
    assert all(np.concatenate([r[k] for r in two])[order].tobytes() == serial[k].tobytes() for k in ("x", "f", "D"))


def test_fixed_particle_stepping_on_ranks(vortex_set):
    """reorganize_every=0, the fixed-particle stepping: on 2 thread ranks the particles keep their keys,
    D and (without motion) positions, bit for bit; the field diffused by forward Euler is bitwise the
    one-process run's, and its change is one explicit step of the DC-PSE Laplacian of the initial set
    built on one process (arpy.DomainDCPSE with the simulation's repair), to rounding."""
    ps, blob, _ = vortex_set

    def run(comm):
        sim = arpy.Simulation(ps, blob, nu=1e-3, dt=0.01, D0=0.15, reorganize_every=0, comm=comm)
        sim.step()
        return sim.gather(), sim.history()["reorganized"]

    (keys, x, D, F), reorganized = run_threads(2, run)[0]
    assert not reorganized.any()
    assert np.array_equal(keys, np.arange(ps.n)) and x.tobytes() == ps.x.tobytes() and D.tobytes() == ps.D.tobytes()
    one, _ = run(None)
    assert _same((keys, x, D, F), one)
    from arpy.dcpse.domain import REPAIR

    op = arpy.DomainDCPSE(ps.x, ps.eps, domain=ps.domain, strict=False, **REPAIR)
    f0 = blob(ps.x)
    step = 0.01 * 1e-3 * (op.laplacian() @ op.extend(f0))
    assert np.abs(step).max() > 1e-4
    np.testing.assert_allclose(F[:, 0] - f0, step, rtol=0, atol=1e-12 * np.abs(step).max())
