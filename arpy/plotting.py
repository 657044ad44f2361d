"""Plots of particle sets (matplotlib, the ``plot`` extra: ``pip install 'arpy-particles[plot]'``):
positions coloured by D_p, with the resolution D_p (dashed) and cutoff r_c (solid) drawn as circles
for a sample of particles, as in Figs. 2.3 and 3.1 of Reboux et al. (2012), and the figures of the
cases."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Protocol

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = ["FieldLike", "ParticleLike", "available", "counted", "plot_bud_surface", "plot_burgers", "plot_five_spot",
           "plot_particles", "save_figure", "slope_lines", "write_figure"]


def counted(drawn: int, total: int | None = None) -> str:
    """A figure's count of particles: ``N = total``, and how many are drawn when only a sample of them is
    (``total`` None: all ``drawn``)."""
    total = drawn if total is None else int(total)
    return f"N = {total}" + (f", {drawn} drawn" if drawn < total else "")


def available() -> bool:
    """Whether matplotlib can be imported (figures can be drawn)."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def write_figure(path: Path, draw: Callable[[Path], None]) -> bool:
    """``draw(path)`` if matplotlib is installed; otherwise say which figure was left out and how to
    get it.  Returns whether the figure was written."""
    if not available():
        print(f"  {Path(path).name} not drawn: matplotlib is not installed (pip install 'arpy-particles[plot]')")
        return False
    draw(path)
    return True


class ParticleLike(Protocol):
    """What :func:`plot_particles` draws: positions ``x`` (n, 2) and resolutions ``D`` (n,), and
    for ``circles`` > 0 cutoffs ``rc`` (n,) too (a :class:`arpy.Particles`; an
    :class:`arpy.Simulation` with ``circles=0``)."""

    @property
    def x(self) -> np.ndarray: ...

    @property
    def D(self) -> np.ndarray: ...


class FieldLike(ParticleLike, Protocol):
    """Particles with values: ``x``, ``D`` and ``f`` (n,) (an :class:`arpy.Simulation`)."""

    @property
    def f(self) -> np.ndarray: ...


def plot_particles(ps: ParticleLike, ax: Axes | None = None, *, color: np.ndarray | str = "D", circles: int = 12,
                   seed: int = 0, size: float | None = None, cmap: str = "viridis", title: str | None = None,
                   colorbar: bool = True, label: str | None = None) -> Axes:
    """Draw a 2D particle set.

    Parameters
    ----------
    ps : Particles
        A :class:`arpy.Particles` (or any object with ``x`` (n, 2), ``D`` (n,) and ``rc`` (n,)).
    ax : matplotlib Axes, optional
        Where to draw; default: a new figure.
    color : "D" or array (n,)
        "D" (resolution D_p, log scale), or values (e.g. a field: name it with ``label``).
    circles : int
        How many particles (picked at random with ``seed``) get their D_p (dashed) and r_c
        (solid) circles drawn.
    seed : int
        Seed of that pick.
    size : float, optional
        Marker size in points^2; default from the particle number.
    cmap : str
        Colour map.
    title : str, optional
        Title of the axes.
    colorbar : bool
        Whether to add a colour bar.
    label : str, optional
        The colour bar's label; default "$D_p$" with ``color="D"``, none with values.

    Returns
    -------
    matplotlib Axes
    """
    import matplotlib.pyplot as plt
    from matplotlib.collections import PatchCollection
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Circle

    x = np.asarray(ps.x)
    if x.ndim != 2 or x.shape[1] != 2:
        raise ValueError("plot_particles draws 2D particle sets (x of shape (n, 2))")
    n = x.shape[0]
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 6))
    if isinstance(color, str):
        if color != "D":
            raise ValueError('color must be "D" or an array of values')
        values, norm = np.asarray(ps.D), None
        label = "$D_p$" if label is None else label
        if n and values.max() > values.min():
            norm = LogNorm(vmin=values.min(), vmax=values.max())
    else:
        values, norm = np.asarray(color, dtype=float), None
        if values.shape != (n,):
            raise ValueError(f"color values must have shape ({n},)")
    if size is None:
        size = float(np.clip(4e3 / max(n, 1), 0.3, 30.0))
    sc = ax.scatter(x[:, 0], x[:, 1], c=values, s=size, cmap=cmap, norm=norm, linewidths=0)
    if circles and n:
        pick = np.random.default_rng(seed).choice(n, size=min(int(circles), n), replace=False)
        D, rc = np.asarray(ps.D)[pick], np.asarray(getattr(ps, "rc"))[pick]     # (rc: only read here)
        ax.add_collection(PatchCollection([Circle(x[p], r) for p, r in zip(pick, D)], facecolor="none",
                                          edgecolor="k", linestyle="--", linewidth=0.7))
        ax.add_collection(PatchCollection([Circle(x[p], r) for p, r in zip(pick, rc)], facecolor="none",
                                          edgecolor="k", linewidth=0.7))
        ax.plot(x[pick, 0], x[pick, 1], "k+", ms=5)
    box = getattr(ps, "box", None)
    if box is not None:
        lo, hi = box
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    if colorbar:
        ax.figure.colorbar(sc, ax=ax, label=label or "", shrink=0.8)
    ax.set_title(title if title is not None else f"N = {n}")
    return ax


def slope_lines(ax: Axes, h: np.ndarray, err: np.ndarray, orders: Iterable[float]) -> None:
    """Dashed guide lines err ~ h^p (one per order p) through the finest point of a log-log plot."""
    h, err = np.asarray(h, dtype=np.float64), np.asarray(err, dtype=np.float64)
    hh = np.array([h.min(), h.max()])
    e0 = err[np.argmin(h)]
    for p in orders:
        ax.loglog(hh, e0 * (hh / h.min()) ** p, "k--", lw=0.8)
        ax.annotate(f"slope {p}", (hh[1], e0 * (hh[1] / h.min()) ** p), fontsize=8)


def plot_five_spot(result: dict, path: str | Path) -> None:
    """Figs. 4.8 and 4.9 from :func:`arpy.cases.five_spot`'s result: the velocity field
    ``result["velocity"]`` (x (m, 2) -> (m, 2)) as arrows on a 24 x 24 grid, the particles
    coloured by the saturation at each snapshot, and N over time; saved to path."""
    import matplotlib.pyplot as plt

    shots = sorted(result["snapshots"].items())
    fig, axes = plt.subplots(1, len(shots) + 2, figsize=(4.4 * (len(shots) + 2), 4.2))
    g = np.linspace(-0.48, 0.48, 24)                  # off the symmetry lines, where |u| can vanish
    grid = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    u = result["velocity"](grid)
    speed = np.maximum(np.sqrt((u ** 2).sum(1)), 1e-12)
    arrows = axes[0].quiver(grid[:, 0], grid[:, 1], u[:, 0] / speed, u[:, 1] / speed, np.log10(speed),
                            cmap="viridis")
    fig.colorbar(arrows, ax=axes[0], label="log10 |u|")
    axes[0].set_aspect("equal")
    axes[0].set_title("(Fig. 4.8a) u = -grad p (direction)")
    sc = None
    for ax, (t, snap) in zip(axes[1:], shots):
        sc = ax.scatter(snap["x"][:, 0], snap["x"][:, 1], c=snap["f"], s=2, cmap="viridis", vmin=0, vmax=1)
        ax.set_aspect("equal")
        ax.set_xlim(-0.5, 0.5)
        ax.set_ylim(-0.5, 0.5)
        ax.set_title(f"(Fig. 4.9) t = {t:g}, {counted(len(snap['f']), snap.get('N'))}")
    if sc is not None:
        fig.colorbar(sc, ax=axes[len(shots)], label="f (water saturation)")
    axes[-1].plot(result["t"], result["n"])
    axes[-1].set_xlabel("t")
    axes[-1].set_ylabel("N")
    axes[-1].set_title("(Fig. 4.8b) particles over time")
    save_figure(fig, path)


def plot_burgers(sim: FieldLike, path: str | Path, title: str, total: int | None = None) -> None:
    """Fig. 4.6 from a Burgers :class:`arpy.Simulation`: (a) the particle values f_p
    (linear on their Delaunay triangles), (b) the particles coloured by D_p; saved to path.  ``total``:
    the count of particles when ``sim`` holds a sample of them."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    im = axes[0].tripcolor(sim.x[:, 0], sim.x[:, 1], sim.f, shading="gouraud", cmap="RdBu_r")
    fig.colorbar(im, ax=axes[0], label="f")
    axes[0].set_aspect("equal")
    axes[0].set_title(f"(a) f_p, {title}")
    plot_particles(sim, ax=axes[1], circles=0,
                   title=f"(b) {counted(len(sim.x), total)}, D_p ratio {sim.D.max() / sim.D.min():.1f}")
    save_figure(fig, path)


def plot_bud_surface(results: list[dict], path: str | Path, paper_n: dict | None = None) -> None:
    """Figs. 4.10 and 4.11 from :func:`arpy.cases.bud_surface` results (one column each):
    top, the surface (the zero level set) coloured by the D_p of the nearest
    particle, log scale; bottom, a close-up of the neck: the particles in a thin
    slab ``|y| < 2 D_p`` around the meridian plane, coloured by D_p, with the
    surface's profile.  ``paper_n``: the paper's N per L for the titles."""
    import matplotlib.pyplot as plt
    from matplotlib import colors

    from .domain import nearest

    k = len(results)
    fig = plt.figure(figsize=(4.2 * k, 8.4))
    dmin = min(res["particles"].D.min() for res in results)
    dmax = max(res["particles"].D.max() for res in results)
    norm = colors.LogNorm(vmin=dmin, vmax=dmax)
    cmap = plt.get_cmap("viridis")
    for i, res in enumerate(results):
        bud, ps = res["bud"], res["particles"]
        X, Y, Z = bud.mesh(90, 72)
        near = nearest(ps.x, y=np.stack([X, Y, Z], -1).reshape(-1, 3))[1]
        face = cmap(norm(ps.D[near].reshape(X.shape)))
        ax = fig.add_subplot(2, k, i + 1, projection="3d")
        ax.plot_surface(X, Y, Z, facecolors=face, rstride=1, cstride=1, linewidth=0, antialiased=False, shade=False)
        lo, hi = bud.bounds
        half = 0.5 * (hi - lo).max()
        mid = 0.5 * (hi + lo)
        for set_lim, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), mid):
            set_lim(c - half, c + half)
        ax.set_box_aspect((1, 1, 1), zoom=1.5)
        ax.view_init(elev=10, azim=-60)
        ax.set_axis_off()
        ref = "" if not paper_n or res["L"] not in paper_n else f" (paper {paper_n[res['L']]:.3g})"
        ax.set_title(f"(Fig. 4.10) L = {res['L']:g}\nN = {res['N']}{ref}", fontsize=9)
        ax2 = fig.add_subplot(2, k, k + i + 1)
        slab = np.abs(ps.x[:, 1]) < 2 * ps.D
        zn, w = bud.z_neck, 1.5 * bud.r_neck
        sel = slab & (np.abs(ps.x[:, 2] - zn) < w) & (np.abs(ps.x[:, 0]) < w)
        ax2.scatter(ps.x[sel, 0], ps.x[sel, 2], c=ps.D[sel], s=3, cmap=cmap, norm=norm)
        z, rho = bud.profile(400)
        for sgn in (1, -1):
            ax2.plot(sgn * rho, z, "k-", lw=0.6)
        ax2.set_xlim(-w, w)
        ax2.set_ylim(zn - w, zn + w)
        ax2.set_aspect("equal")
        ax2.set_xlabel("x")
        ax2.set_ylabel("z")
        ax2.set_title(f"(Fig. 4.11) neck, radius {bud.neck_radius:.2g}", fontsize=9)
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), ax=fig.axes, shrink=0.6, label="D_p")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def plot_manufactured(runs: list[dict], path: str | Path, finest: dict[str, Any]) -> None:
    """:func:`arpy.cases.manufactured` at several resolutions: the errors of u and v against h with a
    slope-2 guide, and the finest run's particles ``finest`` (arrays ``x`` (n, 2), ``u``, ``D``; their
    count ``N`` when they are a sample) coloured by u (size: D_p); saved to path."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.4))
    h = np.array([r["h"] for r in runs])
    for kind, style in (("rms", "o-"), ("max", "s--")):
        for name in ("u", "v"):
            axes[0].loglog(h, [r[kind][name] for r in runs], style, label=f"{kind} error of {name}")
    if len(runs) > 1:
        ref = runs[0]["rms"]["u"] * (h / h[0]) ** 2
        axes[0].loglog(h, ref, "k:", label="slope 2")
    axes[0].set_xlabel("h = 1 / sqrt(N)")
    axes[0].set_ylabel("error at T")
    axes[0].legend(fontsize=8)
    axes[0].set_title(f"errors against the exact solution ({runs[0]['walls']} walls)")
    x, D = finest["x"], finest["D"]
    sc = axes[1].scatter(x[:, 0], x[:, 1], c=finest["u"], s=24 * (D / D.max()) ** 2, cmap="viridis")
    fig.colorbar(sc, ax=axes[1], label="u")
    axes[1].set_aspect("equal")
    axes[1].set_title(f"u at T, {counted(len(x), finest.get('N'))} particles (D0 = {runs[-1]['D0']:g})")
    save_figure(fig, path)


def save_figure(fig: Figure, path: str | Path, dpi: int = 110) -> None:
    """Lay out, write and close a matplotlib figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
