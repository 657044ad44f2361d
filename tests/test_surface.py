"""The budding-cell surface (arpy.surface.Bud), the §4.6 self-organization in its
narrow band, and the AR cell-list application distribution (Awile et al. §3.2)."""

from __future__ import annotations

import numpy as np
import pytest

from arpy.cases import bud_surface
from arpy.distributions import bud_benchmark
from arpy.surface import Bud, eq_4_14, pinch_off_distance
from conftest import kdtree_pairs

LS = (0.40, 0.45, 0.50, 0.56)


def profile_points(bud: Bud, margin: float, m: int = 25):
    """Points inside each arc (away from its ends by ``margin`` of its angle range), with their
    arc index, as (z, rho) and as 3D points at random azimuths."""
    rng = np.random.default_rng(3)
    out = []
    for k, a in enumerate(bud.arcs):
        span = a.a1 - a.a0
        ang = np.linspace(a.a0 + margin * span, a.a1 - margin * span, m)
        z, rho = a.point(ang)
        t = rng.uniform(0, 2 * np.pi, m)
        out.append((k, ang, np.stack([rho * np.cos(t), rho * np.sin(t), z], 1)))
    return out


def fd_hessian(f, x: np.ndarray, h: float) -> np.ndarray:
    """Central finite-difference Hessian of f: (m, 3) -> (m,) at the points x, (m, 3, 3)."""
    e = np.eye(3) * h
    H = np.empty((x.shape[0], 3, 3))
    for i in range(3):
        for j in range(3):
            H[:, i, j] = (f(x + e[i] + e[j]) - f(x + e[i] - e[j]) - f(x - e[i] + e[j]) + f(x - e[i] - e[j])) / (4 * h * h)
    return H


@pytest.mark.parametrize("L", LS)
def test_level_set_is_the_signed_distance(L):
    bud = Bud(L)
    pts = bud.surface_points(80, 36)
    assert np.abs(bud.phi(pts)).max() < 1e-12
    # off the surface along the outward normal: phi = offset, for offsets below the radii of curvature
    for k, ang, x in profile_points(bud, 0.02):
        a = bud.arcs[k]
        nz, nr = a.normal(ang)
        radial = x[:, :2] / np.linalg.norm(x[:, :2], axis=1)[:, None]
        n3 = np.column_stack([nr[:, None] * radial, nz])
        t = 0.3 * min(bud.neck_radius, bud.r_neck, bud.r)
        for s in (-t, t):
            assert np.allclose(bud.phi(x + s * n3), s, atol=1e-12)
    # a point inside each sphere, and far away
    assert bud.phi(np.array([[0, 0, -0.5 * bud.R]]))[0] == pytest.approx(-0.5 * bud.R)
    assert bud.phi(np.array([[0, 0, L + 0.5 * bud.r]]))[0] == pytest.approx(-0.5 * bud.r)
    assert bud.phi(np.array([[0, 0, -2 * bud.R]]))[0] == pytest.approx(bud.R)


@pytest.mark.parametrize("L", LS[:3])
def test_principal_curvatures_match_the_hessian_of_phi(L):
    """On the surface, the Hessian of a signed distance has the principal curvatures as
    its tangential eigenvalues (and 0 along the normal): finite differences of phi
    check the analytic curvatures on all three arcs."""
    bud = Bud(L)
    for k, ang, x in profile_points(bud, 0.1):
        keep = np.linalg.norm(x[:, :2], axis=1) > 0.2 * bud.r     # off the axis: phi is smooth there too,
        x = x[keep]                                               # but its FD stencil crosses rho = 0
        kap = np.sort(bud.principal_curvatures(x), axis=1)
        ev = np.linalg.eigvalsh(fd_hessian(bud.phi, x, 1e-4 * bud.r))
        ev = np.sort(np.delete(ev, np.argmin(np.abs(ev), axis=1)[:, None] + 3 * np.arange(len(x))[:, None]).reshape(-1, 2),
                     axis=1)
        assert np.allclose(ev, kap, rtol=1e-3, atol=1e-3 / bud.r), k


def test_curvatures_on_the_spheres_and_at_the_neck():
    for L in LS:
        bud = Bud(L)
        south = np.array([[0.1, -0.05, -np.sqrt(bud.R ** 2 - 0.0125)]])
        north = np.array([[0.02, 0.0, L + np.sqrt(bud.r ** 2 - 0.0004)]])
        assert np.allclose(bud.principal_curvatures(south), 1 / bud.R)
        assert np.allclose(bud.principal_curvatures(north), 1 / bud.r)
        neck = np.array([[bud.neck_radius, 0.0, bud.z_neck]])
        assert np.allclose(bud.principal_curvatures(neck), [[-1 / bud.r_neck, 1 / bud.neck_radius]])
        assert bud.curvature(neck)[0] == pytest.approx(max(1 / bud.r_neck, 1 / bud.neck_radius))
        # the neck radius from the tangency conditions, independently: the neck circle's
        # centre is R + r_n from the sphere's centre and r + r_n from the bud's
        zn, rn = bud.z_neck, bud.rho_neck
        assert np.hypot(zn, rn) == pytest.approx(bud.R + bud.r_neck)
        assert np.hypot(zn - L, rn) == pytest.approx(bud.r + bud.r_neck)
        assert bud.neck_radius == pytest.approx(rn - bud.r_neck)


def test_thickness_and_monitor():
    bud = Bud(0.40)
    # from the sphere's south pole the inward ray runs along the axis to the bud's top
    south = np.array([[0.0, 0.0, -bud.R]])
    assert bud.thickness(south)[0] == pytest.approx(bud.R + bud.L + bud.r, rel=1e-6)
    for L in LS:
        b = Bud(L)
        neck = np.array([[b.neck_radius, 0.0, b.z_neck]])
        assert b.thickness(neck)[0] == pytest.approx(2 * b.neck_radius, rel=1e-3)
        # Eq. 4.14: on the sphere kappa = 1/R dominates 1/d (d <= 2R)
        p = np.array([[0.0, bud.R, -0.01]])
        assert b.monitor(p, 0.1)[0] == pytest.approx(0.1 / np.sqrt(1 + 1 / b.R ** 2))
    k = np.array([[3.0, -1.0], [2.0, 2.0]])
    assert np.allclose(eq_4_14(k, np.array([10.0, 0.1]), 0.1), 0.1 / np.sqrt(1 + np.array([3.0, 10.0]) ** 2))


def test_bad_geometry_is_refused():
    with pytest.raises(ValueError, match="pinched off"):
        Bud(pinch_off_distance(0.3, 0.1, 0.1) + 1e-6)
    with pytest.raises(ValueError):
        Bud(0.4, R=-0.3)
    with pytest.raises(ValueError):
        Bud(0.1)                # the bud inside the sphere: no neck


def test_narrow_band_has_the_requested_width():
    bud = Bud(0.45)
    D0 = 0.1
    at_points = bud.monitor_spacing(D0)
    for hw in (2.0, 4.0):
        x = bud.sample_band(at_points, half_width=hw, seed=0)
        u = np.abs(bud.phi(x)) / at_points(x)
        assert u.max() <= hw * (1 + 1e-12)
        assert u.max() > 0.99 * hw                      # filled up to its edge
        assert abs(u.mean() - hw / 2) < 0.03 * hw       # uniformly across it
        assert np.all(bud.in_band(x, at_points, hw))
        assert np.array_equal(bud.in_band(x[:500] * 1.01, at_points, hw),
                              bud.in_band(x[:500] * 1.01, lambda y: bud.monitor(y, D0), hw))
        # about one particle per D~^3 of band volume: the volume from a Monte Carlo estimate
        rng = np.random.default_rng(1)
        lo, hi = bud.bounds
        lo, hi = lo - hw * D0, hi + hw * D0
        y = rng.uniform(lo, hi, (400_000, 3))
        inside = bud.in_band(y, at_points, hw)
        expected = np.prod(hi - lo) * np.mean(inside / at_points(y) ** 3)
        assert abs(len(x) / expected - 1) < 0.1, (len(x), expected)


def test_v1_self_organization_in_the_band_keeps_n_star_neighbours():
    r = bud_surface(0.40, D0=0.25, seed=2)
    ps, band = r["particles"], r["band"]
    assert r["converged"] and ps.n_star == 20
    assert np.all(band(ps.x))
    # neighbours under the min rule, counted with a kd-tree (not arpy's lists)
    i, j = kdtree_pairs(ps.x, ps.rc)
    counts = np.bincount(i, minlength=ps.n) + np.bincount(j, minlength=ps.n)
    interior = r["interior"]
    assert interior.mean() > 0.5                        # the check covers most particles
    assert counts[interior].min() >= 20
    # D_p follows the curvature monitor (Eq. 2.9 never asks for more than D~)
    D_target = r["target"](ps.x)
    assert np.all(ps.D <= D_target * (1 + 1e-12))
    on_bud = ps.x[:, 2] > r["bud"].L
    assert np.median(ps.D[on_bud]) < 0.5 * np.median(ps.D[ps.x[:, 2] < 0])


def test_bud_benchmark_spans_lambda():
    for lam in (3.0, 50.0):
        x, rc, bud = bud_benchmark(0.45, lam, seed=1)
        assert bud.r_neck == pytest.approx(3.0 / lam)
        assert rc.max() / rc.min() == pytest.approx(max(lam, 3.0 / bud.neck_radius), rel=1e-6)
        # spacing h = h0 / (R kappa): h0 on the large sphere
        south = x[:, 2] < -1.0
        assert np.allclose(rc[south] / np.sqrt(3.0), 0.45)
