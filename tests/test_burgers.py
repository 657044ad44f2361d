"""§4.4: the 2D Burgers equation on adaptive particles and with the remeshed baseline, against
a pseudo-spectral reference whose own accuracy is checked first."""

from __future__ import annotations

import numpy as np
import pytest

from arpy import cases
from arpy.reference.burgers import SpectralBurgers

PTS = np.random.default_rng(0).random((500, 2))


@pytest.fixture(scope="module")
def reference() -> SpectralBurgers:
    """The pseudo-spectral solution at Re = 100, T = 0.1 on 256^2 (``cases.burgers_reference``):
    checked by the first test, the reference of the second (computed once: 1.1 to 1.8 s of CPU)."""
    return cases.burgers_reference(100.0, 0.1)


def test_spectral_reference_converges_and_keeps_the_invariants(reference):
    # self-convergence at Re = 100, T = 0.1 (the steepest front is about 0.05 wide)
    assert (reference.n, reference.nu, reference.t) == (256, 0.01, pytest.approx(0.1))
    sols = {n: SpectralBurgers(cases.burgers_initial, n, 0.01).run(0.1)(PTS) for n in (64, 128)}
    sols[256] = reference(PTS)
    e64, e128 = np.abs(sols[64] - sols[256]).max(), np.abs(sols[128] - sols[256]).max()
    assert e128 < 1e-6 and e128 < e64 / 100
    # the interpolation onto points is exact for the initial condition
    s = SpectralBurgers(cases.burgers_initial, 32, 0.01)
    np.testing.assert_allclose(s(PTS), cases.burgers_initial(PTS), atol=1e-12)
    # inviscid and smooth (before the shock at t ~ 0.11): the mean and the mean of f^2 are invariants
    inv = SpectralBurgers(cases.burgers_initial, 128, 0.0)
    m0, q0 = inv.f.mean(), (inv.f ** 2).mean()
    inv.run(0.05)
    assert abs(inv.f.mean() - m0) < 1e-12 and abs((inv.f ** 2).mean() - q0) < 1e-6 * q0
    # viscous: d/dt mean(f^2 / 2) = -nu mean(|grad f|^2) = -nu 4 pi^2 mean(f^2) at t = 0 (one Fourier mode pair)
    vis = SpectralBurgers(cases.burgers_initial, 64, 0.01)
    dt = 1e-5
    vis.run(dt)
    rate = ((vis.f ** 2).mean() / 2 - q0 / 2) / dt
    assert rate == pytest.approx(-0.01 * 4 * np.pi ** 2 * 2 * q0, rel=1e-3)


def test_burgers_converges_at_second_order(reference):
    """Re = 100 to T = 0.1: the adaptive method (D0 = 0.14 and 0.1, N ~ 2800 and 5000) and the
    remeshed baseline in conservative form (32^2 to 128^2, no randomness) converge at order
    2 +- 0.5 in h = 1 / sqrt(N).  Adaptive, seeds 1-5: 2.09, 2.34, 2.11, 2.15, 2.04 (with
    D0 = 0.12 as a third size: the same to 0.01)."""
    ref = reference
    runs = [cases.burgers(D0=d0, T=0.1, reference=ref) for d0 in (0.14, 0.1)]
    h, e = np.array([r["h"] for r in runs]), np.array([r["error"] for r in runs])
    assert np.all(np.diff(h) < 0) and np.all(np.diff(e) < 0)
    assert abs(cases.slope(h, e) - 2) < 0.5
    assert e[-1] < 1e-3
    for r in runs:
        assert r["sim"].t == pytest.approx(0.1) and r["scale_ratio"] > 2          # refined at the fronts
    base = [cases.remeshed_burgers(n_cells=m, T=0.1, reference=ref) for m in (32, 64, 128)]
    hb, eb = np.array([b["h"] for b in base]), np.array([b["error"] for b in base])
    assert np.all(np.diff(eb) < 0) and abs(cases.slope(hb, eb) - 2) < 0.5
