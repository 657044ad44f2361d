"""A simulation stops where its numbers go wrong, and its steps stay below the stability bound.

Non-finite fields, rates and positions raise :class:`arpy.NonFiniteError` at the step they appear,
naming what, where and the first particle; a fixed step above the stability bound of the diffusion
term is refused before it changes anything; a default step is never above it.
"""

from __future__ import annotations

import numpy as np
import pytest

import arpy

BOX = arpy.Domain([1.0, 1.0], periodic=True)


@pytest.fixture(scope="module")
def ps() -> arpy.Particles:
    return arpy.self_organize(np.random.default_rng(3).random((250, 2)), lambda p: np.full(len(p), 0.07),
                              domain=BOX, seed=3)


def wave(p: np.ndarray) -> np.ndarray:
    return np.sin(2 * np.pi * p[:, 0])


def test_a_rhs_that_turns_nan_stops_at_that_step_naming_the_field(ps):
    def rhs(t, x, fields, ops):
        rate = ops.laplacian("v")
        if t > 0.015:
            rate[7] = np.nan
        return {"v": 0.01 * rate}

    sim = arpy.Simulation(ps, {"u": wave, "v": wave}, rhs=rhs, D0=0.07, dt=0.01, reorganize_every=0)
    with pytest.raises(arpy.NonFiniteError, match=r"t = 0\.02: the rates \(rhs\) of 'v' not finite .* 1 particle"):
        sim.run(0.05)
    assert sim.steps == 2                                       # (steps 1 and 2 were fine)


def test_a_velocity_that_turns_inf_stops_naming_the_step_and_the_positions(ps):
    def u(x, t, f):
        out = np.ones_like(x)
        out[3] = np.inf if t > 0 else 1.0
        return out

    sim = arpy.Simulation(ps, wave, velocity=u, D0=0.07, dt=0.01, reorganize_every=0)
    sim.step()
    with pytest.raises(arpy.NonFiniteError, match=r"step 2 \(t = 0\.01 -> 0\.02.*the positions are not finite"):
        sim.step()


def test_a_flow_map_of_the_wrong_shape_is_named(ps):
    sim = arpy.Simulation(ps, wave, flow=lambda x, t, dt: x[1:], D0=0.07, dt=0.01)
    with pytest.raises(ValueError, match=r"flow\(x, t, dt\) must return the new positions"):
        sim.step()


def test_initial_values_that_are_not_finite_name_the_particle(ps):
    f = wave(ps.x)
    f[11] = np.nan
    with pytest.raises(arpy.NonFiniteError, match=r"f's initial values are not finite .* 1 particle\(s\), the first "
                                                  r"\(index 11\)"):
        arpy.Simulation(ps, f, nu=0.01, D0=0.07)


@pytest.mark.parametrize("integrator", ["euler", "rk4"])
def test_a_fixed_step_above_the_bound_is_refused_before_any_step(ps, integrator):
    """At construction, from the operators at the initial particles (the first Euler step
    re-organizes, with no bound of its own)."""
    with pytest.raises(ValueError, match=rf"dt = 1 at the initial particles: dt is above the stability bound .* of "
                                         rf"{integrator}"):
        arpy.Simulation(ps, wave, nu=0.01, D0=0.07, dt=1.0, integrator=integrator)
    taken = arpy.Simulation(ps, wave, nu=0.01, D0=0.07, dt=1.0, integrator=integrator, reorganize_every=0,
                            allow_unstable_dt=True)
    with pytest.warns(RuntimeWarning, match="taken anyway"):
        taken.step()
    assert taken.t == 1.0


def test_a_fixed_step_above_the_bound_of_a_later_step_is_refused_and_changes_nothing(ps):
    """A step the initial particles allow, refused where the particles' bound falls below it (here
    a stretching flow squeezes them): the step is undone."""
    def squeeze(x, t, dt):
        return x * np.array([1.0, 1.0 - 0.3 * dt / 0.02])

    box = arpy.Domain([1.0, 1.0])
    walls = arpy.Particles(ps.x, ps.D, ps.rstar, domain=box)
    probe = arpy.Simulation(walls, wave, nu=0.01, D0=0.07, flow=squeeze, reorganize_every=0)
    dt = 0.95 * probe.step()["dt_stable"]
    sim = arpy.Simulation(walls, wave, nu=0.01, D0=0.07, flow=squeeze, dt=dt, reorganize_every=0)
    with pytest.raises(ValueError, match=r"step \d+ .*dt is above the stability bound"):
        for _ in range(40):
            x, f, t, steps = sim.x.copy(), sim.f.copy(), sim.t, sim.steps
            sim.step()
    assert (sim.t, sim.steps, len(sim.log)) == (t, steps, steps)
    np.testing.assert_array_equal(sim.x, x)
    np.testing.assert_array_equal(sim.f, f)


@pytest.mark.parametrize("integrator", ["euler", "rk4"])
def test_the_default_step_stays_below_the_bound(ps, integrator):
    """With re-organizations (the set changes, and with it the operator's spectrum)."""
    sim = arpy.Simulation(ps, lambda p: 0.1 * wave(p), nu=0.01, velocity=lambda x, t, f: np.full_like(x, 0.3),
                          D0=0.07, integrator=integrator, reorganize_every=2).run(0.15)
    h = sim.history()
    assert np.isfinite(h["dt_stable"]).sum() >= 3
    assert np.all(h["dt"] <= h["dt_stable"])


def test_a_default_step_above_the_bound_is_taken_again_at_the_bound(ps, monkeypatch):
    """The step is undone (particles, generator, log) and taken at the bound: bitwise the step a
    simulation given that dt takes."""
    def sim(**kw):
        return arpy.Simulation(ps, lambda p: 0.1 * wave(p), nu=0.01, D0=0.07, integrator="rk4", reorganize_every=1,
                               **kw)

    probe = sim(dt=1.0, allow_unstable_dt=True)
    with pytest.warns(RuntimeWarning):
        bound = probe.step()["dt_stable"]
    long = sim()
    monkeypatch.setattr(long, "time_step", lambda: 10 * bound)
    entry = long.step()
    assert entry["dt"] == bound * (1 - 1e-9) and len(long.log) == 1 and long.steps == 1
    exact = sim(dt=bound * (1 - 1e-9))
    exact.step()
    np.testing.assert_array_equal(long.x, exact.x)
    np.testing.assert_array_equal(long.f, exact.f)


def test_nu_without_rhs_diffuses_every_field(ps):
    """Several fields and nu > 0 without rhs: each field diffuses (it raised KeyError: no field 'f')."""
    fields = {"u": wave, "v": lambda p: np.cos(2 * np.pi * p[:, 1])}
    sim = arpy.Simulation(ps, fields, nu=0.01, D0=0.07, dt=0.002, reorganize_every=0)
    F0 = sim.F.copy()
    sim.step()
    op = arpy.DomainDCPSE(ps.x, ps.eps, domain=BOX)
    for j in range(2):
        want = F0[:, j] + 0.002 * 0.01 * (op.laplacian() @ op.extend(F0[:, j]))
        np.testing.assert_allclose(sim.F[:, j], want, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("seed", range(5))
def test_row_norm_is_the_largest_absolute_row_sum(seed):
    """Operators.row_norm against dense NumPy, with empty rows first, inside and last."""
    import scipy.sparse as sp

    from arpy.dcpse.operators import Operators

    rng = np.random.default_rng(seed)
    dense = rng.normal(size=(9, 12)) * (rng.random((9, 12)) < 0.4)
    dense[[0, 4, 8]] = 0.0
    ops = Operators.__new__(Operators)
    ops._matrix = lambda key, name: sp.csr_matrix(dense)
    assert ops.row_norm("laplacian") == pytest.approx(np.abs(dense).sum(axis=1).max(), rel=1e-15)


@pytest.mark.parametrize("domain", [None, BOX])
def test_rows_with_wild_laplacian_weights_are_rebuilt_at_the_particles(domain):
    """Uniformly random points (not self-organized; the paper never takes such sets), in free space
    (one-sided rows at the edge of the data) and in a periodic box, with a limit of 100 / eps^2 on the
    rows' sums (only the Laplacian is assembled here): the rows whose sum_q |L_pq| (dense NumPy) exceeds
    it are the ones rebuilt; the other rows are bitwise those without the limit; the rebuilt ones are
    below it and still exact Laplacians of quadratics (free space) and of a periodic wave to the order
    of the others, and the operator's largest eigenvalue (NumPy) falls with its Gershgorin bound."""
    x = np.random.default_rng(5).random((400, 2))
    eps = np.full(len(x), 0.12)
    limit = 100 / 0.12 ** 2
    plain = arpy.DomainDCPSE(x, eps, domain=domain, strict=False, widen=3, operators=["laplacian"])
    fixed = arpy.DomainDCPSE(x, eps, domain=domain, strict=False, widen=3, max_row_sum=limit, operators=["laplacian"])
    Lp, Lf = plain.laplacian().toarray(), fixed.laplacian().toarray()
    wild = np.setdiff1d(np.flatnonzero(np.abs(Lp).sum(axis=1) > limit), plain.failed)
    assert wild.size >= 10 and fixed.failed.size == 0
    np.testing.assert_array_equal(fixed.heavy, wild)
    keep = np.setdiff1d(np.arange(len(x)), wild)
    np.testing.assert_array_equal(Lf[keep], Lp[keep])
    assert np.all(np.abs(Lf[wild]).sum(axis=1) <= limit)
    if domain is None:
        quad = x[:, 0] ** 2 - 3 * x[:, 0] * x[:, 1] + 2 * x[:, 1] ** 2          # its Laplacian: 6
        np.testing.assert_allclose(Lf[wild] @ quad, 6.0, atol=1e-7)
        lam_plain, lam_fixed = (np.abs(np.linalg.eigvals(L)).max() for L in (Lp, Lf))
        assert lam_fixed < 0.3 * lam_plain and lam_fixed <= np.abs(Lf).sum(axis=1).max()
    else:
        err = np.abs(Lf @ fixed.extend(wave(x)) + 4 * np.pi ** 2 * wave(x))
        assert err[wild].max() < 2 * err[keep].max()
