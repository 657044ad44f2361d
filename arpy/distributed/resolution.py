"""The resolution of an old particle set spread over the ranks: :class:`RankResolution` (D_p at any
points, by Shepard interpolation over the old particles of every rank), :func:`graded_on_ranks`
(Eq. 2.9) and :func:`field_resolution` (from a field's :class:`arpy.distributed.dcpse.DistributedDCPSE`
derivatives), each bitwise the one-process result.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .._validate import as_cutoffs, as_positions
from ..adapt.resolution import SampledResolution
from ..dcpse.boundary import Conditions
from ..domain import Domain
from .comm import Comm
from .dcpse import DistributedDCPSE, nearest_values
from .decomposition import Decomposition, bounding_box
from .ghosts import fetch, halo

__all__ = ["RankResolution", "field_resolution", "graded_on_ranks"]


def graded_on_ranks(comm: Comm, x: np.ndarray, d_tilde: np.ndarray, keys: np.ndarray, rstar: float,
                    domain: Domain, reading: str = "implicit") -> np.ndarray:
    """:func:`arpy.adapt.resolution.graded_resolution` (Eq. 2.9) of the particles spread over the ranks: each
    rank asks the others for their particles (and periodic images) within r* times its largest D~ of
    its own particles' bounding box, then scans them as one process does
    (:func:`arpy.adapt.resolution.grade`).  Bitwise the one-process result.  Collective."""
    from ..adapt.resolution import check_reading, grade

    check_reading(reading)
    xs, target = as_positions(x), np.asarray(d_tilde, dtype=np.float64)
    n, d = xs.shape
    if reading == "pointwise":
        return target.copy()
    dom = domain.for_dim(d)
    width = rstar * float(target.max(initial=0.0))
    lo, hi = bounding_box(xs)
    sends = _box_sends(comm, xs, np.zeros(n), lo - width, hi + width, dom)
    xg, dg, _, _, _ = fetch(comm, xs, target, np.asarray(keys, np.int64), sends, dom)
    if n == 0:
        return target.copy()
    return grade(xs, target, np.concatenate([xs, xg]), np.concatenate([target, dg]), rstar, reading)


def _box_sends(comm: Comm, x: np.ndarray, reach: np.ndarray, lo: np.ndarray, hi: np.ndarray,
               domain: Domain) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per rank, this rank's particles (and periodic images) within ``reach`` of the box [lo, hi] that
    rank asks about (:func:`halo` with the asked boxes; not this rank's own particles to itself)."""
    asks = comm.allgather((lo, hi))
    boxes = Decomposition(np.array([a[0] for a in asks]), np.array([a[1] for a in asks]))
    return halo(x, reach, boxes, np.full(x.shape[0], comm.rank, np.int64), domain=domain)


class RankResolution:
    """:class:`arpy.adapt.resolution.SampledResolution` of an old particle set spread over the ranks: D_p
    at any points, by the same Shepard interpolation, each rank asking the others for the old
    particles (and periodic images) whose reach r* D_q meets its points' bounding box; the sums run
    in the order of one process holding the whole old set numbered by key (old particles by key, then
    images by shift and key), so the values are bitwise the one-process ones.  A point no old particle
    reaches takes the D of the nearest (a k-nearest request).  Calls are collective (every rank calls
    it the same number of times, as :func:`self_organize` does).

    Parameters
    ----------
    comm : Comm
    x, D, keys : arrays (n, d), (n,), (n,)
        This rank's old particles, their D_p (graded) and keys.
    rstar : float
        Cutoff factor: old particle q reaches r* D_q.
    domain : Domain
        The box.
    """

    #: Its values are D_p already graded by Eq. 2.9 (:func:`self_organize` takes them as they are).
    graded = True

    def __init__(self, comm: Comm, x: np.ndarray, D: np.ndarray, keys: np.ndarray, rstar: float,
                 domain: Domain) -> None:
        self.comm, self.x = comm, as_positions(x)
        self.d = self.x.shape[1]
        self.D, self.keys = as_cutoffs(D, self.x.shape[0]), np.asarray(keys, dtype=np.int64)
        self.rstar, self.domain = float(rstar), domain.for_dim(self.d)
        self.degenerate = 0

    def __call__(self, y: np.ndarray) -> np.ndarray:
        ys = as_positions(y)
        n, m, d = self.x.shape[0], ys.shape[0], ys.shape[1]
        if d != self.d:
            raise ValueError(f"points must have d = {self.d} columns, got {ys.shape}")
        lo, hi = bounding_box(ys)
        sends = _box_sends(self.comm, self.x, self.rstar * self.D, lo, hi, self.domain)
        own = sends[self.comm.rank]                             # own particles: to itself unshifted too
        sends[self.comm.rank] = (np.concatenate([np.arange(n), own[0]]), np.concatenate([np.zeros((n, d)), own[1]]))
        xl, Dl, _, _, _ = fetch(self.comm, self.x, self.D, self.keys, sends, self.domain)
        out, ok = np.empty(m), np.zeros(m, bool)
        if m and xl.shape[0]:                  # (in the one-process order: SampledResolution's sums)
            out, ok = SampledResolution(xl, Dl, self.rstar).shepard(ys)
        out[~ok] = nearest_values(self.comm, self.x, self.keys, self.D, self.domain, ys[~ok], 1)[:, 0]
        return out


def field_resolution(comm: Comm, dec: Decomposition, x: np.ndarray, f: np.ndarray, D: np.ndarray, keys: np.ndarray, *,
                     D0: float, Dmin: float | None = None, order: int = 4, domain: Domain, widen: int | None = None,
                     max_lebesgue: float | None = None, reach: float = 1.0, monitor: str = "gradient",
                     bc: Sequence[Conditions | None] | None = None, t: float = 0.0,
                     reading: str = "implicit") -> RankResolution:
    """:func:`arpy.field_resolution` of an old particle set spread over the ranks (each rank's own
    particles x (n, d) with their fields f (n,) or (n, k), D_p and keys): the monitor from
    :class:`DistributedDCPSE` derivatives, Eq. 2.9 by :func:`graded_on_ranks`, the result a
    :class:`RankResolution`, bitwise the one-process one.  ``degenerate``: the particles without a
    stencil, over all ranks.  Collective."""
    from ..adapt.resolution import check_monitor, check_reach, monitor_target, n_star_for, r_star

    xs = as_positions(x)
    n, d = xs.shape
    fields = np.asarray(f, dtype=np.float64).reshape(n, -1)
    bcs = [None] * fields.shape[1] if bc is None else list(bc)
    check_reach(reach)
    check_monitor(monitor, order)
    dom = domain.for_dim(d)

    def build(eps: np.ndarray, m: int, operators: list, wild: bool) -> DistributedDCPSE:
        return DistributedDCPSE(comm, dec, xs, eps, keys, domain=dom, order=m, strict=False, widen=widen,
                                max_lebesgue=max_lebesgue if wild else None, operators=operators, reorder=False)

    op, target = monitor_target(build, fields, D, d=d, D0=D0, Dmin=Dmin, order=order, domain=dom, monitor=monitor,
                                bcs=bcs, t=t)
    rs = r_star(d, n_star_for(order, d))
    field = RankResolution(comm, xs, graded_on_ranks(comm, xs, target, keys, reach * rs, dom, reading), keys, rs, dom)
    field.degenerate = comm.sum(int(op.failed.size))
    return field
