"""A pseudo-spectral reference solution of the 2D Burgers equation of §4.4 (Reboux et al. 2012).

    df/dt + u . grad f = nu lap f,   u = (f, f),   on the periodic unit square,

written in conservative form, df/dt = -(d/dx + d/dy)(f^2 / 2) + nu lap f,
and integrated in Fourier space with the integrating-factor RK4 scheme (the
diffusion exactly, the nonlinear term by RK4) and the 2/3 dealiasing rule.
Values at arbitrary points come from the spectrum zero-padded onto a finer
grid and a quintic spline on it.  Its own convergence is checked in the tests
(resolution halved and doubled).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

__all__ = ["SpectralBurgers"]


class SpectralBurgers:
    """The 2D Burgers solution on an n x n Fourier grid of [0, 1)^2.

    Parameters
    ----------
    f0 : callable
        (m, 2) points -> (m,) initial values (periodic, smooth).
    n : int
        Grid points per edge (even).
    nu : float
        Viscosity 1 / Re.
    cfl : float
        Step = ``cfl * (1 / n) / max|u|`` (u = (f, f)).
    """

    def __init__(self, f0: Callable[[np.ndarray], np.ndarray], n: int, nu: float, cfl: float = 0.4) -> None:
        if n < 8 or n % 2:
            raise ValueError("n must be an even number >= 8")
        if not (np.isfinite(nu) and nu >= 0):
            raise ValueError("nu must be finite and >= 0")
        self.n, self.nu, self.cfl = int(n), float(nu), float(cfl)
        g = np.arange(n) / n
        self.grid = np.stack(np.meshgrid(g, g, indexing="ij"), -1)
        k = 2 * np.pi * np.fft.fftfreq(n, 1.0 / n)
        self.kx, self.ky = np.meshgrid(k, k, indexing="ij")
        kmax = np.abs(k).max()
        self.dealias = (np.abs(self.kx) < 2 / 3 * kmax) & (np.abs(self.ky) < 2 / 3 * kmax)
        self.k2 = self.kx ** 2 + self.ky ** 2
        self.fh = np.fft.fft2(np.asarray(f0(self.grid.reshape(-1, 2)), dtype=np.float64).reshape(n, n))
        self.t, self.steps = 0.0, 0

    @property
    def f(self) -> np.ndarray:
        """The field on the grid, shape (n, n), index [i, j] at (i / n, j / n)."""
        return np.fft.ifft2(self.fh).real

    def _nonlinear(self, fh: np.ndarray) -> np.ndarray:
        f = np.fft.ifft2(fh * self.dealias).real
        return -0.5j * (self.kx + self.ky) * np.fft.fft2(f * f) * self.dealias

    def step(self, dt: float) -> None:
        """One integrating-factor RK4 step."""
        e = np.exp(-self.nu * self.k2 * dt / 2)
        e2 = e * e
        v = self.fh
        a = dt * self._nonlinear(v)
        b = dt * self._nonlinear(e * (v + a / 2))
        c = dt * self._nonlinear(e * v + b / 2)
        d = dt * self._nonlinear(e2 * v + e * c)
        self.fh = e2 * v + (e2 * a + 2 * e * (b + c) + d) / 6
        self.t += dt
        self.steps += 1

    def run(self, T: float) -> "SpectralBurgers":
        """Integrate to t = T (CFL-limited steps, the last one landing on T)."""
        while self.t < T * (1 - 1e-12):
            umax = max(np.abs(self.f).max() * np.sqrt(2), 1e-12)
            self.step(min(self.cfl / (self.n * umax), T - self.t))
        return self

    def __call__(self, x: np.ndarray, pad: int = 4) -> np.ndarray:
        """f at points x (m, 2) (any real coordinates; periodic), shape (m,).

        The spectrum is zero-padded onto a grid ``pad`` times finer and a
        periodic quintic spline interpolates on it.
        """
        from scipy.ndimage import map_coordinates, spline_filter

        n, m = self.n, self.n * int(pad)
        h = n // 2
        src = self.fh * self.dealias                       # the Nyquist modes are zero
        big = np.zeros((m, m), complex)
        for rows_big, rows in ((slice(0, h), slice(0, h)), (slice(m - h, m), slice(n - h, n))):
            for cols_big, cols in ((slice(0, h), slice(0, h)), (slice(m - h, m), slice(n - h, n))):
                big[rows_big, cols_big] = src[rows, cols]
        fine = np.fft.ifft2(big).real * (m / n) ** 2
        coeffs = spline_filter(fine, order=5, mode="grid-wrap")
        pts = np.mod(np.asarray(x, dtype=np.float64), 1.0) * m
        return map_coordinates(coeffs, pts.T, order=5, mode="grid-wrap", prefilter=False)
