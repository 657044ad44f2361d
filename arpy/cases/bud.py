"""§4.6 of Reboux et al. (2012): particles self-organized in a narrow band around the surface of a
budding cell (:class:`arpy.surface.Bud`), their resolution from its curvature (Eq. 4.14), with the
Morse potential V1 and free-space edges (Figs. 4.10 and 4.11).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable

import numpy as np

from ..distributed import Comm
from ..distributed.reductions import key_places
from ..domain import Domain
from ..lists import neighbor_list
from ..particles import Particles
from ..adapt.organize import DEFAULT_SEED, EDGE_LAYER, seed64, self_organize, start_share
from ..plotting import plot_bud_surface, write_figure
from ..surface import Bud
from .registry import RESOLUTION, Case, domain, option, seed_option

__all__ = ["BUD_DMIN", "BUD_MAX_PARTICLES", "BUD_PAPER_N", "CASE", "ball_inside", "bud_surface"]

#: The particle number at which :func:`bud_surface`'s self-organization stops (its band is 3D).
BUD_MAX_PARTICLES = 20_000_000
#: Reboux et al. (2012), Fig. 4.10: the particle numbers N per centre distance L.
BUD_PAPER_N = {0.40: 2.75e4, 0.45: 2.8e4, 0.50: 3.0e4, 0.56: 4.8e4}
#: The finest resolution Dmin that ``arpy run bud-surface`` and benchmarks/surface.py use per L
#: (none otherwise).  At L = 0.56 the neck is 6e-4 wide (radii 0.3, 0.1 and neck arc 0.1 pinch
#: off at L = 0.5605): Eq. 4.14 alone asks for D~ ~ 6e-5 there, about 2.7e5 particles before
#: self-organization.  The paper reports 4.8e4 and names no floor; D~ is bounded below by
#: D0 / 100 = 1e-3 there.
BUD_DMIN = {0.56: 1e-3}


def ball_inside(x: np.ndarray, radius: np.ndarray, region: Callable[[np.ndarray], np.ndarray], n_dirs: int = 128,
                seed: int = 0) -> np.ndarray:
    """Which balls ``|y - x_p| <= radius_p`` lie inside ``region``.

    Probed at the full and the half radius along the 3^d - 1 axis and diagonal directions plus
    ``n_dirs`` random ones: a particle passes only if every probe is inside.  With radius
    r_c + EDGE_LAYER D_p this is a stricter test than the 3^d - 1 probes by which
    :func:`arpy.self_organize` exempts particles near a region's edge from the neighbour requirement.

    Parameters
    ----------
    x : (n, d) array
        Centres.
    radius : (n,) array
        Radii (length).
    region : callable
        (m, d) -> (m,) bool, whether points are inside.
    n_dirs : int
        Random probe directions.
    seed : int
        Seed of the random directions.

    Returns
    -------
    (n,) bool array
    """
    n, d = x.shape
    grid = np.array([v for v in np.ndindex(*([3] * d)) if any(c != 1 for c in v)], float) - 1.0
    rand = np.random.default_rng(seed).normal(size=(n_dirs, d))
    dirs = np.concatenate([grid, rand])
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    ok = np.ones(n, bool)
    for scale in (1.0, 0.5):
        probes = (x[:, None, :] + scale * radius[:, None, None] * dirs[None]).reshape(-1, d)
        ok &= np.asarray(region(probes), bool).reshape(n, -1).all(axis=1)
    return ok


def bud_surface(L: float = 0.40, *, D0: float = 0.1, R: float = 0.3, r: float = 0.1, r_neck: float = 0.1,
                half_width: float = 4.0, Dmin: float | None = None, max_iter: int = 150, seed: int = DEFAULT_SEED,
                progress: bool = False, comm: Comm | None = None) -> dict:
    """§4.6: particles resolving the surface of a budding cell (:class:`arpy.surface.Bud`).

    The particles fill the narrow band ``|phi| <= half_width * D~`` around the surface, D~ from the
    curvature and the thickness (Eq. 4.14, coarsest D0), optionally bounded below by ``Dmin``.
    They start as a random fill of the band (:meth:`~arpy.surface.Bud.sample_band`, about one
    particle per D~^3) and self-organize (fusion, insertion, descent) with the Morse potential V1
    in free space, confined to the band; N* = 20 (DC-PSE order 4 in 3D).

    The paper calls 4 D~ the band's width; read as a half-width it gives particle counts close to
    the paper's (a total width of 4 D~ gives about half of them), and particles deep enough in the
    band to have a full neighbourhood.

    Parameters
    ----------
    L : float
        Distance between the centres of the sphere and the bud (length).
    D0 : float
        Coarsest resolution (length).
    R, r, r_neck : float
        Radii of the sphere, the bud and the neck's arc (length).
    half_width : float
        Half-width of the band in units of D~.
    Dmin : float, optional
        Lower bound of D~ (length; :data:`BUD_DMIN`).
    max_iter : int
        Iterations of the self-organization at most.
    seed : int
        Seed of the random fill, insertions and probes.
    progress : bool
        Show a progress bar.
    comm : Comm, optional
        Self-organize over the ranks of a communicator (every rank calls this function with the same
        arguments; :func:`arpy.self_organize` with ``comm``): each rank adapts its share of the random fill
        (:func:`arpy.adapt.organize.start_share`) and keeps its share of the result, bitwise the one-process
        result's particles; N and the range of D_p are reductions, none gathered.

    Returns
    -------
    dict
        ``bud`` (the geometry), ``particles`` (the :class:`~arpy.particles.Particles`; with ``comm`` on
        several ranks this rank's share), ``N_initial``, ``N``, ``D_min``/``D_max``, ``iterations``,
        ``converged``, ``neck_radius``, ``wall_s``, ``half_width``, ``interior`` (n,) bool (of the
        particles of ``particles``: those whose neighbourhood ball,
        widened by the edge layer, lies in the band: :func:`ball_inside` with radius
        r_c + EDGE_LAYER D_p), ``band`` (a callable (m, 3) -> (m,) bool, the band) and ``target``
        (the callable (m, 3) -> (m,) D~ the particles followed).
    """
    if not (np.isfinite(half_width) and half_width > 0):
        raise ValueError("half_width must be a finite number > 0")
    bud = Bud(L, R, r, r_neck)
    target = bud.monitor_spacing(D0, Dmin)

    def band(y: np.ndarray) -> np.ndarray:
        return bud.in_band(y, target, half_width)

    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    x0 = bud.sample_band(target, half_width=half_width, seed=rng)
    ps = self_organize(**start_share(x0, comm), resolution=target, D0=D0, Dmin=Dmin, potential="V1", region=band,
                       max_iter=max_iter, seed=seed64(rng), progress=progress, max_particles=BUD_MAX_PARTICLES,
                       domain=Domain(), comm=comm)
    return dict(L=float(L), D0=D0, bud=bud, particles=ps,
                interior=ball_inside(ps.x, ps.rc + EDGE_LAYER * ps.D, band, seed=seed), N_initial=int(x0.shape[0]),
                N=ps.total(ps.n), D_min=ps.gmin(float(ps.D.min(initial=np.inf))),
                D_max=ps.gmax(float(ps.D.max(initial=-np.inf))), iterations=len(ps.log),
                converged=ps.converged, neck_radius=bud.neck_radius, wall_s=time.perf_counter() - t0, band=band,
                target=target, half_width=float(half_width))


# ---------------------------------------------------------------- arpy run bud-surface
def _neighbour_counts(ps: Particles) -> np.ndarray:
    """The neighbours (min rule) of each of this rank's particles among every rank's, int (n,): on several
    ranks over its own particles and its ghosts (each particle of another rank within its own cutoff
    of this rank's box)."""
    if not ps.parallel:
        return ps.neighbor_list().counts()
    layer = ps.ghosts(ps.rc)
    return neighbor_list(np.concatenate([ps.x, layer.x]), np.concatenate([ps.rc, layer.rc]), full=True,
                         domain=ps.domain).counts()[:ps.n]


def run(args: argparse.Namespace, out: Path) -> dict:
    """``arpy run bud-surface``: per L, prints N, D_p and the neighbour counts; then writes
    bud_L<L>.npz (with the summary of every L) and bud_L<L>_particles.vtu per L, and bud_surface.png
    (Figs. 4.10 and 4.11); returns the summary (one entry per L).  Under mpiexec nothing is gathered:
    each rank counts its particles' neighbours over its ghosts, the fractions are reductions, the
    particles go to one piece per rank as ``arpy run pulse``'s (:meth:`~arpy.cases.registry.Case.save`,
    :meth:`~arpy.cases.registry.Case.vtu`), and rank 0 draws the figure from the pieces read back."""
    print(f"arpy run bud-surface: curvature-driven surface refinement (Reboux et al. 2012, Sec. 4.6), "
          f"D0 = {args.D0:g}, V1, band |phi| <= 4 D~")
    comm = getattr(args, "comm", None)
    results, rows = [], []
    for L in args.L:
        Dmin = BUD_DMIN.get(round(L, 2))
        if Dmin is not None:
            print(f"  L = {L:g}: the neck is nearly pinched off; D~ is bounded below by Dmin = {Dmin:g}")
        r = bud_surface(L, D0=args.D0, Dmin=Dmin, seed=args.seed, progress=not args.quiet, comm=comm)
        ps = r["particles"]
        enough = _neighbour_counts(ps) >= ps.n_star
        inner = ps.total(int(np.count_nonzero(r["interior"])))
        # (the fractions as np.mean of every rank's flags takes them: exact counts, one division)
        interior = ps.total(int(np.count_nonzero(enough[r["interior"]]))) / inner if inner else float("nan")
        every = ps.total(int(np.count_nonzero(enough))) / r["N"]
        print(f"  L = {L:g} (neck radius {r['neck_radius']:.3g}): N = {r['N']} (from {r['N_initial']}), "
              f"D_p in [{r['D_min']:.3g}, {r['D_max']:.3g}], {r['iterations']} iterations "
              f"({'converged' if r['converged'] else 'NOT converged'}), {r['wall_s']:.1f} s; "
              f"neighbours >= {ps.n_star}: {interior:.1%} of the {inner} particles away from the band's edges, "
              f"{every:.1%} of all")
        results.append(r)
        rows.append({"N_star_interior": interior, "N_star_all": every,
                     **{k: r[k] for k in ("L", "neck_radius", "N_initial", "N", "D_min", "D_max", "iterations",
                                          "converged", "wall_s")}})
    summary = {"D0": args.D0, "runs": rows}
    archives, own = [], []
    for r in results:                               # (one process, or one piece per rank: collective)
        ps, phi = r["particles"], r["bud"].phi(r["particles"].x)
        rows = dict(keys=key_places(ps.comm, ps.keys), x=ps.x, D=ps.D, phi=phi)
        archives.append(CASE.save(args, out / f"bud_L{r['L']:g}.npz", summary, rows=rows))
        own.append(rows)
        CASE.vtu(args, out / f"bud_L{r['L']:g}_particles.vtu", ps.x, D=ps.D, phi=phi)
    whole = [CASE.drawn_rows(args, archive, rows) for archive, rows in zip(archives, own)]
    if whole and whole[0] is not None:              # (the rank that draws: each run's particles, or a sample)
        drawn = [{**r, "particles": SimpleNamespace(x=w["x"], D=w["D"])} for r, w in zip(results, whole)
                 if w is not None]                         # (every w on this rank; narrows the type)
        write_figure(out / "bud_surface.png", lambda path: plot_bud_surface(drawn, path, BUD_PAPER_N))
    return summary


def _closed_bud(L: float, _: dict[str, Any]) -> bool:
    """Whether the sphere and the bud at centre distance L join into a closed surface (else ValueError)."""
    Bud(L)
    return True


#: ``arpy run bud-surface``.
CASE = Case(
    "bud-surface", "Sec. 4.6: particles refining the surface of a budding cell (Figs. 4.10, 4.11)",
    (option(bud_surface, "L", "--L",
            "distances between the sphere's and the bud's centres, a length each (the paper shows 0.40 0.45 0.50 "
            "0.56)", (_closed_bud, "must join the sphere and the bud into a closed surface"), nargs="+"),
     option(bud_surface, "D0", "--D0", "coarsest resolution D0, a length (the sphere's radius is 0.3)",
            *RESOLUTION),
     seed_option(bud_surface)),
    lambda a: domain(1.0, 3, max_particles=BUD_MAX_PARTICLES), run, seconds=86.0)
