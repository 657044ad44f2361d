"""The remeshed Lagrangian particle method: the uniform-resolution baseline of §4.3-4.4.

Particles start on the nodes of a uniform Cartesian mesh of spacing h; each
step they are advected (exact flow map, or forward Euler with a velocity
field), their values are interpolated back onto the mesh with the M'4 kernel
(Monaghan 1985), and diffusion is applied on the mesh by second-order centred
finite differences with forward Euler.  Pure NumPy: it exists to be compared
against.
"""

from __future__ import annotations

import itertools
from typing import Callable

import numpy as np
import numpy.typing as npt

from .domain import Domain

__all__ = ["RemeshedLPM", "m4prime"]


def m4prime(s: np.ndarray) -> np.ndarray:
    """The M'4 interpolation kernel W(s), s in units of h (support ``|s| < 2``; W(0) = 1,
    W(integer != 0) = 0; it reproduces polynomials up to degree 2)."""
    a = np.abs(s)
    return np.where(a < 1, 1 - 2.5 * a ** 2 + 1.5 * a ** 3, np.where(a < 2, 0.5 * (2 - a) ** 2 * (1 - a), 0.0))


class RemeshedLPM:
    """A remeshed particle simulation of df/dt + u . grad f = nu lap f on a uniform mesh.

    Parameters
    ----------
    f0 : callable
        (m, d) points -> (m,) values, the initial condition.
    box : array (2, d) or array (d,)
        The domain: (lo, hi) or edge lengths.
    h : float
        Mesh spacing (the edges must be multiples of it, to 1e-9 relative).
    nu : float
        Diffusivity.
    flow : callable, optional
        Exact flow map (x, t, dt) -> x(t + dt).
    velocity : callable, optional
        (x, t, f) -> u, used with forward Euler when no flow is given.
    periodic : bool
        Periodic mesh; otherwise nodes cover [lo, hi] including both faces and values beyond
        them are zero.
    """

    def __init__(self, f0: Callable[[np.ndarray], np.ndarray], box: npt.ArrayLike, h: float, *, nu: float = 0.0,
                 flow: Callable | None = None, velocity: Callable | None = None, periodic: bool = False) -> None:
        mesh = Domain(box)
        assert mesh.d is not None and mesh.lo is not None and mesh.hi is not None    # a box
        d, self.lo, self.hi = mesh.d, mesh.lo, mesh.hi
        if not (np.isfinite(h) and h > 0):
            raise ValueError("h must be a finite number > 0")
        cells = (self.hi - self.lo) / h
        if np.any(np.abs(cells - np.round(cells)) > 1e-9 * cells):
            raise ValueError("the box edges must be multiples of h")
        self.d, self.h, self.nu, self.flow, self.velocity = d, float(h), float(nu), flow, velocity
        self.periodic = bool(periodic)
        self.shape = tuple(int(round(c)) + (0 if periodic else 1) for c in cells)
        axes = [self.lo[a] + h * np.arange(self.shape[a]) for a in range(d)]
        self.nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, d)
        self.f = np.asarray(f0(self.nodes), dtype=np.float64).reshape(self.shape)
        self.t, self.steps = 0.0, 0

    @property
    def n(self) -> int:
        """Number of particles (= mesh nodes)."""
        return int(np.prod(self.shape))

    def remesh(self, x: np.ndarray, values: np.ndarray) -> np.ndarray:
        """M'4 interpolation of particle values at x (m, d) onto the mesh (shape ``self.shape``)."""
        s = (x - self.lo) / self.h
        base = np.floor(s).astype(np.int64) - 1
        out = np.zeros(self.n)
        for offs in itertools.product(range(4), repeat=self.d):
            idx = base + np.asarray(offs)
            w = np.prod(m4prime(s - idx), axis=1) * values
            if self.periodic:
                idx = np.mod(idx, self.shape)
                ok = np.ones(len(w), bool)
            else:
                ok = np.all((idx >= 0) & (idx < self.shape), axis=1)
            flat = np.ravel_multi_index(tuple(idx[ok].T), self.shape)
            out += np.bincount(flat, w[ok], minlength=self.n)
        return out.reshape(self.shape)

    def laplacian(self, f: np.ndarray) -> np.ndarray:
        """Second-order centred finite-difference Laplacian (zero beyond non-periodic faces)."""
        out = -2.0 * self.d * f
        for a in range(self.d):
            if self.periodic:
                out = out + np.roll(f, 1, axis=a) + np.roll(f, -1, axis=a)
            else:
                pad = np.pad(f, [(1, 1) if b == a else (0, 0) for b in range(self.d)])
                out = out + np.take(pad, range(0, self.shape[a]), axis=a) + np.take(pad, range(2, self.shape[a] + 2), axis=a)
        return out / self.h ** 2

    def time_step(self) -> float:
        """Forward-Euler diffusion limit h^2 / (4 nu) (as in the paper); inf without diffusion."""
        return self.h ** 2 / (4 * self.nu) if self.nu > 0 else np.inf

    def step(self, dt: float) -> None:
        """Advect, remesh, diffuse."""
        f = self.f.ravel()
        if self.flow is not None:
            x = self.flow(self.nodes, self.t, dt)
        elif self.velocity is not None:
            x = self.nodes + dt * self.velocity(self.nodes, self.t, f)
        else:
            x = self.nodes
        g = self.remesh(x, f) if x is not self.nodes else self.f
        if self.nu > 0:
            g = g + dt * self.nu * self.laplacian(g)
        self.f = g
        self.t += dt
        self.steps += 1

    def run(self, T: float, dt: float | None = None) -> "RemeshedLPM":
        """Step to time T (default dt: :meth:`time_step`; the last step lands on T)."""
        while self.t < T * (1 - 1e-12):
            step = self.time_step() if dt is None else float(dt)
            if not np.isfinite(step):
                raise ValueError("give dt (no diffusion limits the step)")
            self.step(min(step, T - self.t))
        return self
