"""The paper's rule for stencils the moment conditions cannot use, and the choice between the rules.

Reboux et al. 2012, §2.2: where a particle's moment matrix is not invertible, randomly displace or
insert particles until it is (:func:`displace_until_valid`; on a particle set,
:func:`arpy.adapt.organize.displace_set`); the operators are then built without repair
(:func:`repair_for`).  The other rule, arpy's own, repairs the stencils instead
(:mod:`arpy.dcpse.domain`).
"""

from __future__ import annotations

from math import comb
from typing import TYPE_CHECKING, TypedDict

import numpy as np

from .._validate import as_cutoffs, as_positions
from ..domain import Domain, as_domain
from .domain import NO_REPAIR, REPAIR, Repair

if TYPE_CHECKING:
    from ..distributed import Comm, Decomposition

__all__ = ["DISPLACE_ROUNDS", "Displaced", "STENCIL_RULES", "check_stencil_rule", "displace_on_ranks",
           "displace_until_valid", "repair_for"]

#: The rules for stencils the moment conditions cannot use: "repair" (arpy's, :mod:`arpy.dcpse.domain`) and
#: "displace" (Reboux et al. 2012, §2.2: particles randomly displaced or inserted until every moment
#: matrix is invertible; :func:`displace_until_valid`).
STENCIL_RULES = ("repair", "displace")
#: Rounds of :func:`displace_until_valid` before it gives up on the rows still failing.
DISPLACE_ROUNDS = 20


def check_stencil_rule(rule: str) -> None:
    """A rule of :data:`STENCIL_RULES`."""
    if rule not in STENCIL_RULES:
        raise ValueError(f"stencil_rule must be one of {STENCIL_RULES}, got {rule!r}")


def repair_for(rule: str) -> Repair:
    """The keyword arguments of :class:`DomainDCPSE` under a stencil rule: :data:`REPAIR` for "repair",
    :data:`NO_REPAIR` for "displace" (whose particles were moved until every stencil is valid)."""
    check_stencil_rule(rule)
    return REPAIR if rule == "repair" else NO_REPAIR


class Displaced(TypedDict):
    """What :func:`displace_until_valid` did: ``failed``: rows without a valid stencil at the start
    (at the particles plus, with an old set, its interpolation to them); ``displaced`` and
    ``inserted``: particles moved and added over all rounds; ``rounds``; ``left``: rows still failing
    at the end."""

    failed: int
    displaced: int
    inserted: int
    rounds: int
    left: int


def displace_until_valid(x: np.ndarray, D: np.ndarray, rstar: float, *, domain: Domain | None = None, order: int = 4,
                         old: tuple[np.ndarray, np.ndarray] | None = None,
                         rng: np.random.Generator | int | None = None,
                         rounds: int = DISPLACE_ROUNDS) -> tuple[np.ndarray, np.ndarray, Displaced]:
    """The paper's stencil rule (Reboux et al. 2012, §2.2): where a particle's moment matrix is not
    invertible, randomly displace or insert particles until it is.

    Each round checks the DC-PSE stencils (order m, core sizes r* D, failures as :class:`arpy.DCPSE`
    counts them: too few neighbours, singular or ill-conditioned moments) at the particles and, given
    the old set, those of the interpolation from it to the particles.  A particle with a failed row
    and k < N* neighbours (N* the monomials a stencil fits) gets N* - k new particles (same D),
    uniform in the ball of radius r* D_p / 2 around it: within reach of it and of each other, so
    each of them has N* neighbours too.  Any other failed particle moves to a random point within
    D_p / 2 of where the adaptation put it (a fresh draw each round, so the set keeps its order).
    An interpolation row with fewer old sources within the particle's reach than N* is left failed:
    near where the old set is coarser than the new, no such move finds more (arpy's repair widens
    those rows instead).  Moved and new particles are reflected at walls and wrapped across periodic
    faces.  The rounds end when no row the rule can fix fails, or after ``rounds``.  On the ranks of
    a communicator: :func:`displace_on_ranks` (this function is it on one process).

    Parameters
    ----------
    x : array (n, d)
        Positions.
    D : array (n,)
        Resolutions D_p (length unit of x).
    rstar : float
        Core size factor: eps = r* D.
    domain : Domain or None
        The domain (ghost sources as :class:`DomainDCPSE` makes them).
    order : int
        DC-PSE order m.
    old : (x_old (k, d), eps_old (k,)) or None
        An old set whose values are interpolated to the particles (a re-organization).
    rng : Generator, int or None
        Random draws.
    rounds : int
        At most this many rounds.

    Returns
    -------
    (x (n', d), D (n',), Displaced)
        The particles (inserted ones at the end) and what was done.
    """
    from ..distributed import SerialComm, bisect

    xs = as_positions(x)
    dom = as_domain(domain, xs.shape[1])
    comm = SerialComm()
    dec = bisect(xs, 1, domain=domain, comm=comm)[0]
    olds = None if old is None else (as_positions(old[0]), old[1], np.arange(len(old[0]), dtype=np.int64))
    xs, Ds, _, done = displace_on_ranks(comm, dec, xs, D, np.arange(xs.shape[0], dtype=np.int64), rstar, domain=dom,
                                        order=order, old=olds, rng=rng, rounds=rounds)
    return xs, Ds, done


def displace_on_ranks(comm: "Comm", dec: "Decomposition", x: np.ndarray, D: np.ndarray, keys: np.ndarray,
                      rstar: float, *, domain: Domain, order: int = 4,
                      old: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                      rng: np.random.Generator | int | None = None, rounds: int = DISPLACE_ROUNDS
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, Displaced]:
    """:func:`displace_until_valid` over the ranks of ``comm``: x, D, keys are this rank's particles
    (in the boxes ``dec``; keys 0 .. N - 1 over the ranks) and ``old`` = (x, eps, keys) this rank's old
    particles in the same boxes.  Rows go by key (:class:`arpy.distributed.DistributedDCPSE`), the
    draws are those of one process taking the failed particles in key order (every rank draws them
    all from the same generator and uses its own), and particle N + i is the i-th inserted, in key
    order of their parents: the particles are bitwise one process's for every rank count.  Returns
    this rank's particles (x, D, keys, in key order, moved to the ranks whose boxes hold them) and
    the figures (global).  Collective."""
    from ..distributed import DistributedDCPSE, migrate

    xs = as_positions(x).copy()
    Ds = as_cutoffs(D, xs.shape[0]).copy()
    ks = np.array(keys, dtype=np.int64)
    home = xs.copy()                                  # where the adaptation put each particle
    dom, d = as_domain(domain, xs.shape[1]), xs.shape[1]
    gen = np.random.default_rng(rng)
    need = comb(int(order) - 1 + d, d)
    total = comm.sum(xs.shape[0])
    done: Displaced = {"failed": 0, "displaced": 0, "inserted": 0, "rounds": 0, "left": 0}
    def built(*args: np.ndarray, wanted: str) -> DistributedDCPSE:          # (without repair)
        return DistributedDCPSE(comm, dec, *args, domain=dom, order=order, strict=False, widen=0, max_lebesgue=None,
                                operators=[wanted], reorder=False)

    for k in range(int(rounds) + 1):
        at = built(xs, rstar * Ds, ks, wanted="laplacian")
        nnb = at.n_neighbors
        bad = at.failed
        few = bad[nnb[bad] < need]
        fixable = bad
        if old is not None:
            to = built(old[0], old[1], old[2], xs, rstar * Ds, wanted="interpolation")
            bad = np.union1d(bad, to.failed)
            # too few old sources within a particle's reach: no displacement within D_p / 2 helps
            fixable = np.union1d(fixable, to.failed[to.n_neighbors[to.failed] >= need])
        moved = np.setdiff1d(fixable, few)
        every = comm.allgather((bad.size, fixable.size, ks[moved], ks[few], need - nnb[few]))
        if k == 0:
            done["failed"] = sum(e[0] for e in every)
        if sum(e[1] for e in every) == 0 or k == rounds:
            done["left"] = sum(e[0] for e in every)
            break
        done["rounds"] = k + 1
        # the draws of one process: the moved particles, then the new ones, each in key order
        moved_keys = np.sort(np.concatenate([e[2] for e in every]))
        step = _in_ball(gen, moved_keys.size, d)[np.searchsorted(moved_keys, ks[moved])]
        xs[moved] = dom.reflect(home[moved] + 0.5 * Ds[moved, None] * step)
        parent_keys = np.concatenate([e[3] for e in every])
        by_key = np.argsort(parent_keys)
        counts = np.concatenate([e[4] for e in every])[by_key]
        first = np.concatenate([[0], np.cumsum(counts)])[np.searchsorted(parent_keys[by_key], ks[few])]
        draws = _in_ball(gen, int(counts.sum()), d)
        slot = np.concatenate([f + np.arange(c) for f, c in zip(first, need - nnb[few])]).astype(np.int64) \
            if few.size else np.zeros(0, np.int64)
        parent = np.repeat(few, need - nnb[few])
        new_x = dom.reflect(xs[parent] + 0.5 * rstar * Ds[parent, None] * draws[slot])
        xs, Ds, home = (np.concatenate(a) for a in ((xs, new_x), (Ds, Ds[parent]), (home, new_x)))
        ks = np.concatenate([ks, total + slot])
        total += int(counts.sum())
        done["displaced"] += moved_keys.size
        done["inserted"] += int(counts.sum())
        if comm.size > 1:                             # (to the ranks whose boxes hold them now)
            xs, ks, got = migrate(comm, dec, xs, ks, {"D": Ds, "home": home})
            Ds, home = got["D"], got["home"]
    return xs, Ds, ks, done


def _in_ball(gen: np.random.Generator, n: int, d: int) -> np.ndarray:
    """n points uniform in the unit ball of R^d, (n, d)."""
    v = gen.normal(size=(n, d))
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)
    return v * gen.random((n, 1)) ** (1.0 / d)
