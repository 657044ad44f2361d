"""The adaptation loop of the self-organizing particles (Reboux et al. 2012, §2.3.4, §3.1): one
iteration fuses and inserts particles, rebuilds the lists, takes D_p from the target, and descends
the energy W with a line search, until the stopping rule holds.  :class:`Adaptation` runs it on a
rank's particles through its :class:`~arpy.adapt.view.View` (one process: P = 1), :class:`Target`
gives D~ (a callable, or the monitor of a gradient) and Eq. 2.9; the draws of insertion come from
:func:`counter_uniforms`, the fusion pairs from :func:`~arpy.adapt.view.greedy_matching` over every rank
(:meth:`~arpy.adapt.view.View.fusion`).  The public entry point is
:func:`arpy.self_organize` (:mod:`arpy.adapt.organize`).
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable

import numpy as np

from .. import _bridge
from ..domain import Domain, nearest
from .forces import energy_terms
from .view import Confinement, Near, View, places
from .resolution import graded_among, monitor_gradient

__all__ = ["Adaptation", "Target", "counter_uniforms"]

#: Displacement cap of one descent step, in units of the particle's D_p.
MAX_STEP = 0.25
#: Armijo sufficient-decrease constant and the most step halvings per line search.
ARMIJO_C, MAX_HALVINGS = 0.1, 40
#: Random candidate sites tried per insertion (the one farthest from other particles wins).
INSERT_CANDIDATES = 16

#: Insertion counts neighbours within this fraction of the cutoff (the stopping rule
#: counts up to the cutoff): a margin that keeps neighbours from flickering out.
INSERT_MARGIN = 0.97
#: Nearest existing particles checked for the clearance of a candidate site.
INSERT_NEAREST = 8
#: The particles a rank holds for its insertion candidates reach this many D_p beyond a parent at
#: first (its candidates lie within D_p of it; where their nearest lie farther, a wider search follows).
INSERT_REACH = 4.0



#: The mixing constants of SplitMix64 (Steele, Lea and Flood 2014), the hash of :func:`counter_uniforms`.
_MIX = (np.uint64(0x9E3779B97F4A7C15), np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB))


def _mix(z: np.ndarray) -> np.ndarray:
    """SplitMix64's finalizer of z + the golden-ratio increment (a bijection of uint64; wraps)."""
    z = z + _MIX[0]
    z = (z ^ (z >> np.uint64(30))) * _MIX[1]
    z = (z ^ (z >> np.uint64(27))) * _MIX[2]
    return z ^ (z >> np.uint64(31))


def counter_uniforms(seed: int, stream: int, keys: np.ndarray, count: int) -> np.ndarray:
    """Uniform numbers in [0, 1) from a counter-based generator: value (i, j) is a hash of
    (seed, stream, keys[i], j), so it does not depend on which other keys are drawn for, in which
    order, or on which process.  Returns an array (len(keys), count)."""
    with np.errstate(over="ignore"):
        base = _mix(_mix(np.full(1, seed & 0xFFFFFFFFFFFFFFFF, np.uint64)) ^ np.uint64(stream & 0xFFFFFFFFFFFFFFFF))
        per_key = _mix(base ^ np.asarray(keys, np.int64).astype(np.uint64))
        h = _mix(per_key[:, None] ^ np.arange(count, dtype=np.uint64)[None, :])
    return (h >> np.uint64(11)).astype(np.float64) * 2.0 ** -53


def _candidates(xp: np.ndarray, Dp: np.ndarray, dom: Confinement, draws: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """INSERT_CANDIDATES random sites near each parent (positions xp (n, d), D_p (n,)): at distance
    U(0.5, 1) D_p in random directions, reflected into the domain.  ``draws``: (n, INSERT_CANDIDATES
    (2 d + 1)) uniforms.  Returns (sites (n, INSERT_CANDIDATES, d), inside the walls and the region
    (n, INSERT_CANDIDATES) bool, the distances over D_p (n, INSERT_CANDIDATES))."""
    (n, d), k = xp.shape, INSERT_CANDIDATES
    u = draws.reshape(n, k, 2 * d + 1)
    # d normal deviates per candidate (Box-Muller), a uniformly random direction once normalized
    g = np.sqrt(-2.0 * np.log1p(-u[:, :, 0:2 * d:2])) * np.cos(2.0 * np.pi * u[:, :, 1:2 * d:2])
    g /= np.maximum(np.linalg.norm(g, axis=2), 1e-300)[:, :, None]
    rho = 0.5 + 0.5 * u[:, :, 2 * d]
    cand = dom.domain.reflect((xp[:, None, :] + (rho * Dp[:, None])[:, :, None] * g).reshape(-1, d))
    return cand.reshape(n, k, d), dom.inside(cand).reshape(n, k), rho


def _sites(xp: np.ndarray, Dp: np.ndarray, kp: np.ndarray, slack: np.ndarray, xa: np.ndarray, Da: np.ndarray,
           m: int, dom: Confinement, seed: int, iteration: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One site near each parent (positions xp (n, d), D_p, keys): of its INSERT_CANDIDATES candidates
    (:func:`_candidates`, drawn by key), the one with the largest clearance min_q |x - x_q| / D_pq to
    its m nearest particles among (xa, Da), among those that would count as the parent's neighbour (D of
    the new particle estimated from the grading of Eq. 2.9).  The m nearest are those of every particle
    where the m-th lies within ``slack`` (n,) of each candidate inside the domain (the caller's bound of
    what xa holds); else the parent's result is not to be used, and ``far`` gives the distance within
    which each of its candidates has m particles (an upper bound of the m-th nearest's; inf where xa
    holds fewer than m).  Returns (sites (n, d), whether a parent has one (n,) bool, far (n,): 0 where
    the result holds)."""
    n, d = xp.shape
    k = INSERT_CANDIDATES
    if n == 0 or xa.shape[0] < m:
        return np.zeros((n, d)), np.zeros(n, bool), np.full(n, 0.0 if n == 0 else np.inf)
    cand, ok, rho = _candidates(xp, Dp, dom, counter_uniforms(seed, iteration, kp, k * (2 * d + 1)))
    flat = cand.reshape(-1, d)
    dist, near = nearest(xa, m, y=flat, domain=dom.domain)
    dist, near = dist.reshape(flat.shape[0], m), near.reshape(flat.shape[0], m)
    reach = np.where(ok, dist[:, m - 1].reshape(n, k), 0.0).max(axis=1)
    far = np.where(reach <= slack, 0.0, reach)
    # the new particle's D, estimated with the grading of Eq. 2.9 (D rises by at most
    # 1/r* per unit distance) from its nearest particles and the parent
    rs = dom.rstar
    Dpar = np.repeat(Dp, k)
    Dnew = np.minimum((Da[near] + dist / rs).min(axis=1), Dpar * (1.0 + rho.ravel() / rs))
    # clearance: the smallest distance to an existing particle in units of D_pq
    clearance = (dist / np.minimum(Dnew[:, None], Da[near])).min(axis=1)
    # a site counts only if it would be the parent's neighbour: |x - x_p| <= r* min(D_p, D_new)
    counts = rho.ravel() * Dpar <= rs * np.minimum(Dpar, Dnew)
    score = np.where(ok.ravel(), clearance + np.where(counts, 1e3, 0.0), -np.inf).reshape(n, k)
    best = np.argmax(score, axis=1)
    return cand[np.arange(n), best], np.isfinite(score[np.arange(n), best]), far


def _displacement(domain: Domain, p: np.ndarray, pt: np.ndarray, step: np.ndarray) -> np.ndarray:
    """The move from p to pt (the descent's actual displacement): along periodic axes the step taken
    (pt is wrapped), else p - pt (walls may have shortened it)."""
    if domain.all_periodic:
        return step
    if domain.any_periodic:
        return np.where(np.asarray(domain.periodic), step, p - pt)
    return p - pt


#: What :func:`_scan` returns: own positions after fusion (n, d), alive (n,) bool, neighbour counts (n,),
#: counts of alive neighbours (n,), the ratio max D_pq / r_pq, the number of fused pairs.
Scan = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, int]


def _scan(near: Near, period: np.ndarray, rcount: float, ctx: View) -> Scan:
    """The adaptation's pass over the own rows (§3.1): (own positions after fusion, alive, neighbour
    counts, neighbour counts among the survivors within rcount D_pq, max D_pq / r_pq, fusions over
    every process).  Fusion is :func:`~arpy.adapt.view.greedy_matching` of the pairs closer than D_pq / 2 over every
    process (:meth:`View.fusion`; each particle fuses at most once per pass, the first of the pair in
    key order moves to the midpoint): it does not depend on the list's layout or on how the particles
    are spread over processes."""
    n, keys, nl = near.n, near.keys, near.nl
    rho = _bridge.so_ratios(near.x, near.D, period, nl.offsets, nl.indices, context="self_organize")
    cols = nl.indices
    lowest = ctx.gmin(float(rho.min()) if rho.size else np.inf)
    ratio = 1.0 / lowest if lowest > 0 else float(np.finfo(np.float64).max)
    # the entries closer than half their D_pq (few), each pair once: between own particles from the
    # row of its smaller key, with a particle of another process from the own particle's row
    close = np.flatnonzero(rho < 0.5)
    crow = np.searchsorted(nl.offsets, close, side="right") - 1        # their rows
    ccol = cols[close]
    once = (keys[ccol] > keys[crow]) | (ccol >= n)
    ka, kb = ctx.fusion(near, rho[close[once]], crow[once], ccol[once])
    alive_all = ~np.isin(keys, kb)
    xo = near.x[:n]
    mine = np.isin(ka, keys[:n])
    if mine.any():
        a, b = places(keys, np.stack([ka[mine], kb[mine]])).astype(np.int32)   # (both in near's keys)
        xo = np.ascontiguousarray(_bridge.so_fuse(near.x, period, a, b, context="self_organize")[:n])
    # per row, the entries within rcount D_pq whose two particles both survive
    within = rho <= rcount
    if kb.size:
        within &= alive_all[cols]
    cnt_alive = nl.stored_counts_where(within)[:n]
    if kb.size:
        cnt_alive[~alive_all[:n]] = 0
    return xo, alive_all[:n], nl.stored_counts()[:n], cnt_alive, ratio, ctx.total(int(np.count_nonzero(mine)))



#: A target resolution must be at least 2**-RESOLUTION_BITS of the coordinates' scale (the largest
#: |coordinate| of the particles or the box): positions carry 52 bits, so offsets of finer stencils
#: would be rounded by more than 2**-22 of their size and DC-PSE moments would lose their digits.
RESOLUTION_BITS = 30



class Target:
    """Steps iii-iv: D_p at given positions, from the monitor of a gradient (Eq. 2.8) or a target
    field D~, bounded by D0 and Dmin, graded by Eq. 2.9 (a :class:`SampledResolution` is taken as D_p
    directly)."""

    def __init__(self, resolution: Callable[[np.ndarray], np.ndarray] | None,
                 grad_f: Callable[[np.ndarray], np.ndarray] | None, D0: float | None, Dmin: float | None,
                 ball: float, domain: Domain, scale: float, reading: str = "implicit") -> None:
        self.resolution, self.grad_f, self.D0, self.Dmin = resolution, grad_f, D0, Dmin
        self.ball, self.domain, self.scale, self.reading = ball, domain, scale, reading
        self.floor = math.ldexp(scale, -RESOLUTION_BITS)     # the finest D~ positions can resolve
        self.sampled = bool(getattr(resolution, "graded", False))     # (a SampledResolution, on one or many ranks)

    def d_tilde(self, p: np.ndarray) -> np.ndarray:
        """The target D~ at the points p (m, d), bounded by D0 and Dmin, before the grading of Eq. 2.9."""
        D0, Dmin = self.D0, self.Dmin
        if self.grad_f is not None:
            g = np.asarray(self.grad_f(p), dtype=np.float64)
            if g.shape != p.shape:
                raise ValueError(f"grad_f must return shape {p.shape}, got {g.shape}")
            assert D0 is not None                       # (checked with grad_f: D0 is required)
            d_tilde = monitor_gradient(g, D0, Dmin)
        else:
            assert self.resolution is not None          # (checked: one of the two is given)
            d_tilde = np.asarray(self.resolution(p), dtype=np.float64)
            if d_tilde.shape != (p.shape[0],):
                raise ValueError(f"resolution must return shape ({p.shape[0]},), got {d_tilde.shape}")
            if D0 is not None:
                d_tilde = np.minimum(d_tilde, D0)
            if Dmin is not None:
                d_tilde = np.maximum(d_tilde, Dmin)
        if not np.all(np.isfinite(d_tilde)) or np.any(d_tilde <= 0):
            raise ValueError("the target resolution must be finite and > 0 everywhere")
        if d_tilde.min(initial=np.inf) < self.floor:              # (a rank may hold no particle)
            raise ValueError(f"the target resolution reaches {d_tilde.min():.3g}, below 2**-{RESOLUTION_BITS} of the "
                             f"coordinates' scale {self.scale:.3g}: positions cannot resolve it; bound it with Dmin")
        return d_tilde


class Adaptation:
    """The iteration of :func:`self_organize`, one method per step of the module docstring, over the own
    particles of a rank (one process: P = 1) as its :class:`~arpy.adapt.view.View` shows them."""

    def __init__(self, conf: Confinement, target: Target, potential: str, n_star: int, d_c: float,
                 seed: int, max_particles: int, ctx: View) -> None:
        self.conf, self.domain, self.target = conf, conf.domain, target
        self.potential, self.ns, self.rs, self.d_c = potential, n_star, conf.rstar, d_c
        self.seed, self.max_particles, self.ctx = seed, max_particles, ctx
        self.next_key = 0

    def resolution(self, x: np.ndarray, keys: np.ndarray) -> np.ndarray:
        """iii-iv. D_p at the own particles: from the target at them and at the particles within the
        ball of Eq. 2.9 (r* times the largest target value here) around them."""
        n, target = x.shape[0], self.target
        own = target.d_tilde(x)
        if target.sampled:
            return own
        xa, = self.ctx.around(x, keys, target.ball * float(own.max(initial=0.0)))
        ext = np.concatenate([own, target.d_tilde(xa[n:])]) if xa.shape[0] > n else own
        # D_p depends on the particles within r* D~_p alone (D_p <= D~_p): it may be computed elsewhere
        D, = self.ctx.sharing.map(
            "grade", lambda xi, ti, xq, tq: (graded_among(xi, ti, xq, tq, target.ball, target.domain, target.reading),),
            (x, own), x, lambda: target.ball * own, (xa, ext))
        return D

    def near(self, x: np.ndarray, D: np.ndarray, keys: np.ndarray, skin: float = 0.0) -> Near:
        return self.ctx.near(x, D, keys, self.rs * D, skin)

    def forces(self, near: Near) -> tuple[float, np.ndarray]:
        """W (an exact sum over every process) and the own particles' gradient."""
        e, g = energy_terms(near.x, near.D, near.nl, self.potential, domain=self.domain, cutoff=self.rs)
        assert g is not None
        return self.ctx.fsum(e[: near.n]), g[: near.n]

    def energy(self, near: Near) -> float:
        """W alone (as :meth:`forces` gives it): a trial of the line search needs no gradient."""
        e, _ = energy_terms(near.x, near.D, near.nl, self.potential, domain=self.domain, cutoff=self.rs,
                            gradient=False)
        return self.ctx.fsum(e[: near.n])

    def mirror_counts(self, x: np.ndarray, keys: np.ndarray, rc: np.ndarray) -> np.ndarray:
        """The own particles' neighbours among the mirror images across the walls (cutoffs rc)."""
        if not self.domain.has_walls:
            return np.zeros(x.shape[0], np.int64)
        xa, ra = self.ctx.around(x, keys, self.ctx.gmax(float(rc.max(initial=0.0))), rc)
        return self.conf.mirror_counts(xa, ra)[: x.shape[0]]

    def fuse_and_insert(self, scan: Scan, D: np.ndarray, keys: np.ndarray,
                        iteration: int) -> tuple[np.ndarray, np.ndarray, int, int, int]:
        """i. fusion (the scan's survivors); ii. one new particle near every particle with fewer
        than N* neighbours (keys after every existing one, in the order of their parents' keys);
        particles that left the region are removed.  The particles stay in key order.  Returns
        (x, keys, fused, inserted, removed)."""
        conf, rs, ctx = self.conf, self.rs, self.ctx
        xo, alive, _, cnt_alive, _, fused = scan
        xs, D, keys = self.domain.confine(xo[alive]), D[alive], keys[alive]   # a midpoint may cross a periodic face
        cnt = cnt_alive[alive] + self.mirror_counts(xs, keys, INSERT_MARGIN * rs * D)
        need = cnt < self.ns
        if conf.region is not None:
            need &= ~conf.near_edge(xs, rs * D)
        parents = np.flatnonzero(need)
        count = ctx.total(parents.size)
        inserted = removed = 0
        if count:
            several = ctx.comm.size > 1
            xp, Dp, kp = xs[parents], D[parents], keys[parents]
            m = min(INSERT_NEAREST, ctx.total(xs.shape[0]))
            # xa: every particle within `width` of this rank's box.  A candidate lies within D_p of its
            # parent p, so the particles within slack_p = width - gap(p) - D_p of it lie within `width` of
            # the box and of p: where its m nearest in xa lie that close, they are its m nearest of all
            # (on any rank p is shipped to, with the sources within `width` of it).  The parents where
            # they do not are searched again, with every particle as near as the m found.
            gp = ctx.gap(xp) if several else np.zeros(parents.size)
            width = float((INSERT_REACH * Dp + gp).max(initial=0.0))
            slack = (width - gp - Dp) - 1e-9 * width if several else np.full(parents.size, np.inf)
            xa, Da = ctx.around(xs, keys, width, D)
            site, found, far = ctx.sharing.map(
                "insertion", lambda q, Dq, kq, sq, xr, Dr: _sites(q, Dq, kq, sq, xr, Dr, m, conf, self.seed, iteration),
                (xp, Dp, kp, slack), xp, np.full(parents.size, width), (xa, Da))
            redo = np.flatnonzero(far > 0)
            wider = float((far[redo] + gp[redo] + Dp[redo]).max(initial=0.0)) * (1.0 + 1e-9)
            if ctx.gmax(wider) > 0:
                xb, Db = ctx.around(xs, keys, wider, D)
                site[redo], found[redo], _ = _sites(xp[redo], Dp[redo], kp[redo], np.full(redo.size, np.inf), xb, Db,
                                                    m, conf, self.seed, iteration)
            which = np.flatnonzero(found)
            new = site[which]
            kept = ctx.sites(new, D[parents[which]], keys[parents[which]])
            new_keys, self.next_key = ctx.new_keys(keys[parents[which[kept]]], self.next_key)
            inserted = ctx.total(int(kept.sum()))
            xs = np.concatenate([xs, new[kept]])
            keys = np.concatenate([keys, new_keys])
        if conf.region is not None:
            ok = conf.inside(xs)
            removed = ctx.total(int((~ok).sum()))
            xs, keys = xs[ok], keys[ok]
        total = ctx.total(xs.shape[0])
        if total > self.max_particles:
            raise RuntimeError(f"self_organize: {total} particles exceed max_particles = {self.max_particles} "
                               f"(smallest D_p {ctx.gmin(D.min(initial=np.inf)):.3g}); bound the resolution with Dmin")
        return xs, keys, fused, inserted, removed

    def descend(self, near: Near, gamma: float | None
                ) -> tuple[np.ndarray, Near, float, float, float | None, int, bool]:
        """vi-vii. Armijo backtracking along -grad W with a per-particle displacement cap.  Returns
        (positions, their Near, W before, W after, the next step size, trials, moved)."""
        domain, conf, ctx = self.domain, self.conf, self.ctx
        p, Dp, keys = near.x[: near.n], near.D[: near.n], near.keys[: near.n]
        W0, g = self.forces(near)
        gnorm = np.sqrt((g * g).sum(axis=1))
        if not ctx.total(int(np.count_nonzero(gnorm > 0))):
            return p, near, W0, W0, gamma, 0, False
        if gamma is None:                   # the median particle moves 0.1 D_p
            gamma = 0.1 * ctx.gmedian(Dp[gnorm > 0] / gnorm[gnorm > 0])
        cap = MAX_STEP * Dp                 # and none more than MAX_STEP D_p
        for trial in range(1, MAX_HALVINGS + 1):
            step = gamma * g * np.minimum(1.0, cap / np.maximum(gamma * gnorm, 1e-300))[:, None]
            pt = domain.confine(p - step)
            keep = conf.inside(pt)
            if conf.region is not None and not np.all(keep):
                pt = np.where(keep[:, None], pt, p)   # a particle never steps out of the region
            disp = _displacement(domain, p, pt, step * keep[:, None])
            skin = ctx.gmax(float(np.sqrt((disp * disp).sum(axis=1)).max(initial=0.0)))
            near_t = self.near(pt, Dp, keys, skin)
            Wt = self.energy(near_t)
            predicted = ctx.fsum(g * disp)      # first-order decrease (an exact sum)
            if Wt <= W0 - ARMIJO_C * predicted:
                grow = 2.0 if W0 - Wt >= 0.5 * predicted else 1.0
                return pt, near_t, W0, Wt, gamma * grow, trial, True
            gamma *= 0.5
        return p, near, W0, W0, gamma, MAX_HALVINGS, False

    def check(self, near: Near) -> tuple[Scan, int, float]:
        """viii. The scan, and the stopping figures: fewest neighbours (mirror images across walls
        included, particles at a region's edge exempt) and max D_pq / r_pq."""
        conf, rs, n = self.conf, self.rs, near.n
        sc = _scan(near, self.domain.period, INSERT_MARGIN * rs, self.ctx)
        cnt = sc[2] + self.mirror_counts(near.x[:n], near.keys[:n], rs * near.D[:n])
        counted = ~conf.near_edge(near.x[:n], rs * near.D[:n])
        fewest = self.ctx.gmin(float(cnt[counted].min()) if np.any(counted) else np.inf)
        return sc, (int(fewest) if np.isfinite(fewest) else self.ns), sc[4]

    def settle(self, near: Near, migrate: bool) -> Near:
        """The own particles of ``near`` after a move and their Near: with ``migrate``, migrated to their
        owners (in key order; the boxes cut anew if the work is uneven, once an iteration) and their Near
        built anew (``near`` itself when nothing migrated); else held where they are until the next
        migration (:meth:`View.hold`), ``near`` itself."""
        n = near.n
        if not migrate:
            self.ctx.hold(near.x[:n])
            return near
        changed, (x, keys, D) = self.ctx.migrate(near.x[:n], near.keys[:n], near.D[:n], balance=True)
        return self.near(x, D, keys) if changed else near

    def home(self, x: np.ndarray, D: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The own particles (x, D, keys) migrated to their owners if some were held outside their boxes
        (:meth:`settle`), in key order."""
        if self.ctx.slack > 0:
            _, (x, keys, D) = self.ctx.migrate(x, keys, D)
        return x, D, keys

    def end_state(self, near: Near, scan: Scan, ratio: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The candidate end state once every particle has N* neighbours: these positions, or, if only
        pairs closer than D_pq / d_c fail the rule, the set after fusing them (step i of the next
        iteration); with D_p at those positions the rule must hold once more.  Returns (x, D, keys)
        or None."""
        n = near.n
        if ratio <= self.d_c:
            x_end, k_end = near.x[:n], near.keys[:n]
        else:
            x_end, k_end = self.domain.confine(scan[0][scan[1]]), near.keys[:n][scan[1]]
            _, (x_end, k_end) = self.ctx.migrate(x_end, k_end)
        D_end = self.resolution(x_end, k_end)
        _, nb_end, ratio_end = self.check(self.near(x_end, D_end, k_end))
        return (x_end, D_end, k_end) if nb_end >= self.ns and ratio_end <= self.d_c else None

    def run(self, xs: np.ndarray, keys: np.ndarray, max_iter: int, adapt_number: bool, tol: float,
            bar: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict], bool]:
        """Iterate until the stopping rule holds (or the descent stalls, or max_iter runs out).
        ``keys``: the own particles' keys, ascending.  Returns (x, D, keys, the log, converged)."""
        ctx = self.ctx
        log: list[dict] = []
        self.next_key = int(ctx.gmax(float(keys.max(initial=-1)))) + 1
        D = self.resolution(xs, keys)
        near = self.near(xs, D, keys)
        scan = self.check(near)[0]
        gamma = None
        for it in range(1, max_iter + 1):
            t_start = time.perf_counter()
            fused = inserted = removed = 0
            if adapt_number:
                xs, keys, fused, inserted, removed = self.fuse_and_insert(scan, near.D[: near.n], keys, it)
                _, (xs, keys) = ctx.migrate(xs, keys, balance=True)
            t_fi = time.perf_counter()
            D = self.resolution(xs, keys)            # iii-v. D_p at the current positions, r_c = r* D_p
            t_res = time.perf_counter()
            near = self.near(xs, D, keys)
            t_lst = time.perf_counter()
            _, near, W_before, W, gamma, trials, moved = self.descend(near, gamma)
            # (adapting the number: held until the migration after the next insertion)
            near = self.settle(near, migrate=not adapt_number)
            xs, keys = near.x[: near.n], near.keys[: near.n]
            t_desc = time.perf_counter()
            scan, min_nb, ratio = self.check(near)     # (its fusion part serves the next iteration)
            t_end = time.perf_counter()
            n_all = ctx.total(near.n)
            log.append(dict(iteration=it, n=n_all, fused=int(fused), inserted=int(inserted),
                            removed=int(removed), energy_before=W_before, energy=W,
                            gamma=np.nan if gamma is None else float(gamma),   # None: no gradient yet
                            trials=int(trials), moved=bool(moved), min_neighbors=min_nb, max_ratio=ratio,
                            t_fuse_insert=t_fi - t_start, t_resolution=t_res - t_fi, t_lists=t_lst - t_res,
                            t_forces=(t_desc - t_lst) + (t_end - t_desc), t_total=t_end - t_start))
            if bar is not None:
                bar.update(1)
                bar.set_postfix(n=n_all, W=f"{W:.4g}", nb=min_nb, ratio=f"{ratio:.2f}")
            if adapt_number:
                end = self.end_state(near, scan, ratio) if min_nb >= self.ns else None
                if end is not None:
                    n_end = ctx.total(end[0].shape[0])
                    log[-1]["fused"] += n_all - n_end
                    log[-1]["n"] = n_end
                    return (*self.home(*end), log, True)
                if fused == inserted == removed == 0 and not moved:
                    break                         # stalled: nothing changes any more
            elif W_before - W <= tol * abs(W_before):
                return xs, near.D[: near.n], keys, log, True
        return (*self.home(xs, near.D[: near.n], keys), log, False)


