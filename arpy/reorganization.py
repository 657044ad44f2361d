"""Step 4 of §3.2.2 (Reboux et al. 2012): the re-organization of a simulation's particles.

The monitor gives the target resolution from the fields (:func:`arpy.field_resolution`), the
particles self-organize to it (:func:`arpy.self_organize`, started from the old positions), and the
fields move from the old particles to the new ones by DC-PSE interpolation, with the right-hand side
at the new particles computed from the old values (variant (ii) of §2.2).  Every part runs over the
simulation's ranks; one process is P = 1.
"""

from __future__ import annotations

import time
from typing import Any, Mapping

import numpy as np

from .adapt.organize import seed64, self_organize
from .adapt.resolution import field_resolution
from .dcpse.displace import displace_on_ranks
from .dcpse.domain import DomainDCPSE
from .distributed import DistributedDCPSE
from .distributed.balance import CostBalance
from .distributed.reductions import key_places
from .lists.search import cache_order as morton_permutation
from .particles import Particles

__all__ = ["reorganize", "settle", "transfer"]


def transfer(sim: Any, old: tuple[np.ndarray, np.ndarray, np.ndarray], x: np.ndarray, eps: np.ndarray,
             operators: list, bc: Any) -> DomainDCPSE | DistributedDCPSE:
    """The DC-PSE operators ``operators`` of a simulation ``sim`` from its particles ``old`` = (x, core
    sizes, keys) of this rank to the points x (m, d) with core sizes eps (m,) in this rank's box (the new
    particles of a re-organization, the particles snapped onto a Dirichlet face), with the conditions
    ``bc`` (Dirichlet faces: boundary particles and one-sided rows).  One process: :class:`DomainDCPSE`;
    on several ranks :class:`DistributedDCPSE` (collective), bitwise the same."""
    ranks = sim.particles
    if ranks.parallel:
        return DistributedDCPSE(ranks.comm, ranks.decomposition, *old, x, eps, domain=sim.domain, order=sim.order,
                                strict=False, operators=operators, dirichlet=bc, **sim._repair)
    return DomainDCPSE(old[0], old[1], x, eps, domain=sim.domain, order=sim.order, strict=False, operators=operators,
                       dirichlet=bc, **sim._repair)


def settle(sim: Any, x: np.ndarray, F: np.ndarray, t: float, given: Mapping | None = None
           ) -> tuple[np.ndarray, np.ndarray]:
    """A simulation's (x, F) with the particles closer than SNAP core sizes to a Dirichlet face moved onto
    it, their values interpolated (order m) from the particles where they were (or, ``given`` the
    initial callables, evaluated there), and the values on Dirichlet faces set."""
    xs = sim.eq.snap(x, sim.eps)
    moved = np.flatnonzero(np.any(xs != x, axis=1))
    if sim.particles.total(moved.size):            # (on ranks: collective)
        F = F.copy()
        eps = sim.eps

        def op_of(wanted, bc):
            return transfer(sim, (x, eps, sim.keys), xs[moved], eps[moved], ["interpolation"], bc)

        ops = sim.eq.operators(op_of, t, xs[moved], F, x, F)
        for j, name in enumerate(sim.names):
            v = None if given is None else given[name]
            F[moved, j] = np.asarray(v(xs[moved]), dtype=np.float64) if callable(v) else ops.interpolate(name)
    return xs, sim.eq.pin(F, xs, t)


def reorganize(sim: Any) -> dict:
    """Step 4 of §3.2.2: adapt the particles to the fields and interpolate them (old -> new).

    Returns the right-hand side at the new particles computed from the old values
    (variant (ii)) and the adaptation's figures.  With ``comm`` every step runs over the ranks
    (:func:`arpy.field_resolution` and :func:`arpy.self_organize` with ``comm``,
    :class:`arpy.distributed.DistributedDCPSE` old -> new), the new particles numbered as one
    process numbers them.
    """
    x_old, F_old, eps_old, keys_old = sim.x, sim.F, sim.eps, sim.keys
    t0 = time.perf_counter()
    watched = sim._watched
    fields = F_old[:, watched] if len(watched) > 1 else F_old[:, watched[0]]
    bc = [sim.eq.bcs[sim.names[j]] for j in watched]
    ranks = sim.particles
    field = field_resolution(x_old, fields, sim.D, D0=sim.D0, Dmin=sim.Dmin, order=sim.order, domain=sim.domain,
                             strict=False, reach=sim.reach, monitor=sim.monitor, bc=bc, t=sim.t,
                             reading=sim.reading, comm=ranks.comm, keys=keys_old, decomposition=ranks.decomposition,
                             **sim._repair)
    sim._degenerate = max(sim._degenerate, field.degenerate)
    t1 = time.perf_counter()
    x_new, D_new, keys_new, log, converged = _adapted(sim, field, x_old, keys_old)
    t2 = time.perf_counter()
    needs_rhs = sim.eq.moves
    x_new, moved = sim.eq.snap(x_new, sim.rstar * D_new), {}
    # the old particles to the boxes of the new ones (one rank: they stay)
    old = Particles(x_old, sim.D, sim.rstar, domain=sim.domain, keys=keys_old, F=F_old, names=sim.names,
                    decomposition=ranks.decomposition, comm=ranks.comm)
    old.migrate()
    x_old, keys_old, F_old, eps_old = old.x, old.keys, old.F, old.eps
    if sim.stencil_rule == "displace":
        x_new, D_new, keys_new, done = displace_on_ranks(ranks.comm, ranks.decomposition, x_new, D_new, keys_new,
                                                         sim.rstar, domain=sim.domain, order=sim.order,
                                                         old=(x_old, eps_old, keys_old), rng=sim.rng)
        moved = dict(displaced=done["displaced"], inserted=done["inserted"])
    if sim.cache_order or ranks.parallel:
        perm = morton_permutation(x_new, domain=sim.domain)
        x_new, D_new, keys_new = x_new[perm], D_new[perm], keys_new[perm]
    eps_new = sim.rstar * D_new

    def op_of(wanted, bc):
        return transfer(sim, (x_old, eps_old, keys_old), x_new, eps_new, ["interpolation"] + (wanted if needs_rhs else []),
                        bc)

    ops = sim.eq.operators(op_of, sim.t, x_new, F_old, x_old, F_old)
    F = np.stack([ops.interpolate(name, bounded=sim.bounded) for name in sim.names], axis=1)
    sim.x, sim.D, sim.keys = x_new, D_new, keys_new
    sim.F = F = sim.eq.pin(F, x_new, sim.t)
    if needs_rhs:
        ops.fields = sim.eq.named(F)
        u_old = sim.eq.u(x_old, sim.t, F_old) if sim.eq.conservative else None
        # (no stability bound from this old -> new operator: it moves f once, it is not iterated)
        rhs = sim.eq.pin(sim.eq.rates(ops, F, u_old), x_new, sim.t, rates=True)
    else:
        rhs = np.zeros_like(F)
    for op in ops.built:
        sim._degenerate = max(sim._degenerate, sim.particles.total(op.failed.size))
    lists = float(sum(e["t_lists"] for e in log))
    sim._phase.update(t_monitor=t1 - t0, t_organize_lists=lists, t_organize_rest=t2 - t1 - lists,
                       t_interpolate=time.perf_counter() - t2)
    return dict(rhs=rhs, iterations=len(log), converged=converged, **moved)

def _adapted(sim: Any, field: Any, x_old: np.ndarray, keys_old: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict], bool]:
    """Step 4(d)-(e): the particles adapted to the field, (x, D, keys, log, converged), numbered
    0 .. N - 1 in key order over every rank; each rank keeps the particles of the adaptation's final
    boxes (which become the simulation's)."""
    ranks = sim.particles
    ps = self_organize(sim.domain.wrap(x_old), field, domain=sim.domain, potential=sim.potential,
                       order=sim.order, seed=seed64(sim.rng), max_iter=sim.max_iter,
                       max_particles=sim.max_particles, comm=ranks.comm, keys=keys_old, decomposition=ranks.decomposition)
    assert ps.keys is not None and ps.decomposition is not None
    # the steps' boxes: cut anew by count if the adaptation's (cut by its own cost) are uneven by count;
    # the steps' balance measures from here (on these boxes)
    ps.migrate(CostBalance(ranks.comm, measured=False))
    ranks.decomposition = ps.decomposition
    sim._balance.cut()
    return ps.x, ps.D, key_places(ranks.comm, ps.keys), ps.log, ps.converged
