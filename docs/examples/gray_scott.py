"""Gray-Scott patterns on self-organizing particles: the user guide's example of equations of your own.

    python docs/examples/gray_scott.py            # to T = 2000 (2 minutes), writes gray_scott.png beside it
    python docs/examples/gray_scott.py --quick    # to T = 40 (as the tests do), writes nothing

Pearson's system (Science 261, 1993) with his rates, his "mitosis" spots (F = 0.0367, k = 0.0649),
in a periodic box of edge 16 with diffusivities 0.0125 and 0.00625: his 2e-5 and 1e-5 with lengths
25 times his, so the box is a square of edge 0.64 of his [0, 2.5]^2.  16 random spots of v divide
and fill the box.  The particles adapt to u and v (Eq. 2.8 on both): D_p from 0.25 to 0.30 at T = 2000
(N = 5,660).  D0 = 0.3 resolves the spots' rims: at D0 = 0.4 (N = 3,221 at T = 400) a few particles
there carry values of v up to 0.6 max(v) above the mean of their six nearest neighbours (165 particles
above 0.2), specks that D0 = 0.3 does not show (7 particles above 0.2, largest 0.29).
With a right-hand side of your own the simulation does not know the stability bound of its terms:
the default step, h_min^2 / (4 nu) with nu the largest diffusivity, follows the finest particles;
a fixed ``dt`` is taken as given (``dt = 1.0`` with ``D0 = 0.02`` in Pearson's own units blew up
after the first re-organization refined the particles).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import arpy

# -- the example (docs/guide.md shows these lines) --
L = 16.0                                      # edge of the periodic box
DU, DV, F, K = 0.0125, 0.00625, 0.0367, 0.0649   # diffusivities, feed and kill rates


def gray_scott(t, x, f, ops):
    """The rates of u and v: diffusion by DC-PSE Laplacians, the reactions in plain NumPy."""
    uvv = f["u"] * f["v"] ** 2
    return {"u": DU * ops.laplacian("u") - uvv + F * (1 - f["u"]),
            "v": DV * ops.laplacian("v") + uvv - (F + K) * f["v"]}


def spots(x, centres, radius=0.75):
    """Gaussian spots of height 1 at the centres (periodic images by the minimum image): (n,)."""
    g = np.zeros(len(x))
    for c in centres:
        d = x - c
        d -= L * np.round(d / L)
        g += np.exp(-(d ** 2).sum(1) / (2 * radius ** 2))
    return g


def spots_gradient(x, centres, radius=0.75):
    """The gradient of :func:`spots`: (n, 2)."""
    grad = np.zeros_like(x)
    for c in centres:
        d = x - c
        d -= L * np.round(d / L)
        grad -= d / radius ** 2 * np.exp(-(d ** 2).sum(1) / (2 * radius ** 2))[:, None]
    return grad


def run(T, D0=0.3, seed=1, progress=False):
    """Gray-Scott to time T on particles adapted to the initial spots; returns the Simulation."""
    rng = np.random.default_rng(seed)
    box = arpy.Domain([L, L], periodic=True)
    centres = rng.uniform(0, L, (16, 2))
    ps = arpy.self_organize(rng.uniform(0, L, (600, 2)), grad_f=lambda p: 0.25 * spots_gradient(p, centres),
                            D0=D0, domain=box, seed=seed)
    sim = arpy.Simulation(ps, {"u": lambda p: 1 - 0.5 * spots(p, centres), "v": lambda p: 0.25 * spots(p, centres)},
                          rhs=gray_scott, nu=DU, D0=D0, seed=seed)    # nu: the largest diffusivity, for the step
    sim.run(T, progress=progress)
    return sim
# -- end of the example --


def plot(sim, path):
    """v on the particles (linear on their Delaunay triangles, periodic seams left out) and D_p."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10.5, 4.8))
    x, v = sim.x, sim.fields["v"]
    im = axes[0].tripcolor(x[:, 0], x[:, 1], v, shading="gouraud", cmap="magma")
    fig.colorbar(im, ax=axes[0], label="v", shrink=0.85)
    axes[0].set_title(f"v at t = {sim.t:g}")
    sim.particles.plot(ax=axes[1], circles=0, size=5, title=f"D_p of the N = {sim.n} particles")
    for ax in axes:
        ax.set_xlim(0, L)
        ax.set_ylim(0, L)
        ax.set_aspect("equal")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="to T = 40, no figure")
    args = parser.parse_args(argv)
    sim = run(40.0 if args.quick else 2000.0, progress=not args.quick)
    v = sim.fields["v"]
    print(f"t = {sim.t:g}: {sim.steps} steps, N = {sim.n}, v in [{v.min():.3f}, {v.max():.3f}], "
          f"variance of v {v.var():.3e}")
    if not args.quick:
        plot(sim, Path(__file__).with_suffix(".png"))
    return sim


if __name__ == "__main__":
    main()
