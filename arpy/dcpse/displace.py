"""The paper's rule for stencils the moment conditions cannot use, and the choice between the rules.

Reboux et al. 2012, §2.2: where a particle's moment matrix is not invertible, randomly displace or
insert particles until it is (:func:`displace_until_valid`; on a particle set,
:func:`arpy.adapt.organize.displace_set`); the operators are then built without repair
(:func:`repair_for`).  The other rule, arpy's own, repairs the stencils instead
(:mod:`arpy.dcpse.domain`).
"""

from __future__ import annotations

from math import comb
from typing import TypedDict

import numpy as np

from .._validate import as_cutoffs, as_positions
from ..domain import Domain, as_domain
from .domain import NO_REPAIR, REPAIR, DomainDCPSE, Repair

__all__ = ["DISPLACE_ROUNDS", "Displaced", "STENCIL_RULES", "check_stencil_rule", "displace_until_valid", "repair_for"]

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
    faces.  The rounds end when no row the rule can fix fails, or after ``rounds``.

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
    xs = as_positions(x).copy()
    Ds = as_cutoffs(D, xs.shape[0]).copy()
    home = xs.copy()                                  # where the adaptation put each particle
    dom = as_domain(domain, xs.shape[1])
    gen = np.random.default_rng(rng)
    need = comb(int(order) - 1 + xs.shape[1], xs.shape[1])
    done: Displaced = {"failed": 0, "displaced": 0, "inserted": 0, "rounds": 0, "left": 0}
    for k in range(int(rounds) + 1):
        at = DomainDCPSE(xs, rstar * Ds, domain=dom, order=order, strict=False, operators=["laplacian"])
        bad = at.failed
        few = bad[at.n_neighbors[bad] < need]
        fixable = bad
        if old is not None:
            to = DomainDCPSE(old[0], old[1], xs, rstar * Ds, domain=dom, order=order, strict=False,
                             operators=["interpolation"])
            bad = np.union1d(bad, to.failed)
            # too few old sources within a particle's reach: no displacement within D_p / 2 helps
            fixable = np.union1d(fixable, to.failed[to.n_neighbors[to.failed] >= need])
        if k == 0:
            done["failed"] = int(bad.size)
        if fixable.size == 0 or k == rounds:
            done["left"] = int(bad.size)
            break
        done["rounds"] = k + 1
        moved = np.setdiff1d(fixable, few)
        xs[moved] = dom.reflect(home[moved] + 0.5 * Ds[moved, None] * _in_ball(gen, moved.size, xs.shape[1]))
        parent = np.repeat(few, need - at.n_neighbors[few])
        step = _in_ball(gen, parent.size, xs.shape[1])
        xs = np.concatenate([xs, dom.reflect(xs[parent] + 0.5 * rstar * Ds[parent, None] * step)])
        home = np.concatenate([home, xs[len(home):]])
        Ds = np.concatenate([Ds, Ds[parent]])
        done["displaced"] += int(moved.size)
        done["inserted"] += int(parent.size)
    return xs, Ds, done


def _in_ball(gen: np.random.Generator, n: int, d: int) -> np.ndarray:
    """n points uniform in the unit ball of R^d, (n, d)."""
    v = gen.normal(size=(n, d))
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)
    return v * gen.random((n, 1)) ** (1.0 / d)
