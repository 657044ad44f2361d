"""Simulation options on ranks that one process took first: reused lists (``verlet_skin``) and
fixed particles (``reorganize_every=0``), bitwise the one-process run on thread ranks."""

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
    those of new lists at every stage (verlet_skin=0, one process) on one process and on 2 and 3
    thread ranks, through a re-organization (the lists built again on the new particles)."""
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
    for parts in (2, 3):
        assert _same(run_threads(parts, lambda comm: run(comm, 0.4)[0])[0], fresh), parts
