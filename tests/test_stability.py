"""A simulation stops where its numbers go wrong, and its steps stay below the stability bound.

Non-finite fields, rates and positions raise :class:`arpy.NonFiniteError` at the step they appear,
naming what, where and the first particle; a fixed step above the stability bound of the diffusion
term is refused before it changes anything; a default step is never above it.
"""

from __future__ import annotations

import re

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
    # the row sums each operator hands on (those its weighing made, unless rows were rebuilt since): the
    # rows of its Laplacian as it is, by dense NumPy
    for op, L in ((plain, Lp), (fixed, Lf)):
        np.testing.assert_allclose(op.laplacian_row_sums(), np.abs(L).sum(axis=1), rtol=1e-13, atol=0)
    if domain is None:
        quad = x[:, 0] ** 2 - 3 * x[:, 0] * x[:, 1] + 2 * x[:, 1] ** 2          # its Laplacian: 6
        np.testing.assert_allclose(Lf[wild] @ quad, 6.0, atol=1e-7)
        lam_plain, lam_fixed = (np.abs(np.linalg.eigvals(L)).max() for L in (Lp, Lf))
        assert lam_fixed < 0.3 * lam_plain and lam_fixed <= np.abs(Lf).sum(axis=1).max()
    else:
        err = np.abs(Lf @ fixed.extend(wave(x)) + 4 * np.pi ** 2 * wave(x))
        assert err[wild].max() < 2 * err[keep].max()


@pytest.fixture(scope="module")
def user_system():
    """Issue 54's user system, a reaction-diffusion-advection system with a manufactured moving solution
    (``benchmarks/stability.py``: not one of arpy's cases), as a module."""
    import sys
    from pathlib import Path

    here = str(Path(__file__).resolve().parents[1] / "benchmarks")
    sys.path.insert(0, here)
    try:
        import report
    finally:
        sys.path.remove(here)
    return report.script("stability")


def rms_error(system, sim: arpy.Simulation) -> float:
    """The RMS error of u against the system's exact solution."""
    return float(np.sqrt(np.mean((sim.fields["u"] - system.exact(sim.x, sim.t)["u"]) ** 2)))


#: Issue 54's system at its smallest size: D0 = 0.12 (Dmin = 0.06), RK4, a re-organization every 4 steps,
#: T shortened to 0.1.  The exact fields vary by 0.5 and 0.25: an RMS error of u below 0.01 is a run that
#: stayed stable (the benchmark's default-step runs reach 3e-3 at T = 0.5; unstable ones 0.13 and more).
D0_TEST, T_TEST, RMS_OK = 0.12, 0.1, 0.01


#: Seeds of the tests, as the issue asks (the benchmark runs them at three sizes).
SEEDS = (1, 2, 3, 4, 5)


@pytest.mark.parametrize("seed", SEEDS)
def test_a_users_system_runs_to_T_with_the_default_step(user_system, seed):
    sim = user_system.simulation(D0_TEST, seed, None).run(T_TEST)
    h = sim.history()
    assert sim.t == pytest.approx(T_TEST) and np.all(h["dt"] <= h["dt_stable"]) and np.isfinite(h["dt_stable"]).all()
    assert rms_error(user_system, sim) < RMS_OK


@pytest.mark.parametrize("diffusivity", [0.02, 0.3])
@pytest.mark.parametrize("seed", SEEDS)
def test_a_users_system_with_a_fixed_step_runs_stably_or_stops_before_any_nan(user_system, monkeypatch, seed,
                                                                              diffusivity):
    """The fixed step 0.2 D0, with the system's Du = 0.02 and with Du = 0.3, for which that step lies
    far above the stability limit (at 9fedc08 every seed stopped with NonFiniteError at t = 0.096): it
    runs to T with a small error, or is refused (StabilityError) with its fields finite."""
    monkeypatch.setattr(user_system, "DU", diffusivity)
    sim = None
    try:
        sim = user_system.simulation(D0_TEST, seed, 0.2 * D0_TEST)
        sim.run(T_TEST)
    except arpy.StabilityError as e:
        assert re.search(r"dt is above the stability bound [\d.e-]+ of rk4 .* give dt <= ", str(e))
        assert sim is None or np.isfinite(sim.F).all()
        return
    assert rms_error(user_system, sim) < RMS_OK


def test_the_bound_of_a_user_rhs_covers_its_laplacians_and_diffusion_terms(ps):
    """A user rhs of two fields, ``0.01 lap u`` (declared nu = 0.01) and ``div(k grad v)`` with k(x): the
    radius the operators record (Gershgorin) bounds the spectrum of the terms it covers (``0.01 L`` and
    ``k L``; not ``grad k . grad v``), assembled densely from the matrices and given to NumPy's eigvals;
    a fixed step above STABILITY / radius is refused at construction, with the bound in the message."""
    from arpy.equations import STABILITY

    def k(p, f):
        return 0.02 * (1.2 + np.sin(2 * np.pi * p[:, 0]))

    def rhs(t, x, f, ops):
        return {"u": 0.01 * ops.laplacian("u"), "v": ops.diffusion(k, "v")}

    sim = arpy.Simulation(ps, {"u": wave, "v": wave}, rhs=rhs, nu=0.01, D0=0.07, dt=1e-4, reorganize_every=0)
    op = arpy.DomainDCPSE(ps.x, ps.eps, domain=BOX, operators=["laplacian", (1, 0), (0, 1)])
    n = ps.n
    E = np.zeros((op.n_src, n))
    E[np.arange(n), np.arange(n)] = 1.0
    E[n + np.arange(op.ghost_source.size), op.ghost_source] = 1.0          # ghosts carry their particle's value
    L = op.laplacian().toarray() @ E
    K = k(ps.x, None)[:, None] * L                                        # the k lap part of div(k grad .)
    lam = max(np.abs(np.linalg.eigvals(0.01 * L)).max(), np.abs(np.linalg.eigvals(K)).max())
    bound = sim._initial_bound()
    assert np.isfinite(bound) and STABILITY["euler"] / bound >= lam
    assert STABILITY["euler"] / bound <= 3 * lam                               # (and not far above it)
    # (a step 10 times the bound: the rows that alone make it unstable are rebuilt, and the bound of the
    # rebuilt operator still lies below it)
    with pytest.raises(arpy.StabilityError, match=rf"dt = {10 * bound:.3g} at the initial particles: dt is above the "
                                                  rf"stability bound [\d.e-]+ of euler"):
        arpy.Simulation(ps, {"u": wave, "v": wave}, rhs=rhs, nu=0.01, D0=0.07, dt=10 * bound, reorganize_every=0)


def test_max_dt_caps_the_default_step_and_yields_to_the_stability_bound(ps):
    """max_dt: the default step is at most max_dt, bitwise the run given that dt while it is below the
    bound; where the bound of an rhs's diffusion (which the default step does not see) is lower, each
    step is taken again at it (dt <= dt_stable in the log), where a fixed dt = max_dt is refused; dt and
    max_dt together, or a max_dt that is not a positive number, are refused."""
    def system(k):
        return dict(rhs=lambda t, x, f, ops: {"f": ops.diffusion(k, "f")}, velocity=lambda x, t, f: np.full_like(x, 0.3),
                    D0=0.07, integrator="rk4", reorganize_every=0)

    capped = arpy.Simulation(ps, wave, max_dt=0.004, **system(0.01)).run(0.012)
    fixed = arpy.Simulation(ps, wave, dt=0.004, **system(0.01)).run(0.012)
    assert capped.steps == 3 and np.all(capped.history()["dt"] == 0.004)
    assert capped.x.tobytes() == fixed.x.tobytes() and capped.f.tobytes() == fixed.f.tobytes()
    stiff = arpy.Simulation(ps, wave, max_dt=0.05, **system(0.5)).run(0.05)
    h = stiff.history()
    assert np.all(h["dt"] <= h["dt_stable"]) and h["dt"].max() < 0.05
    with pytest.raises(arpy.StabilityError):
        arpy.Simulation(ps, wave, dt=0.05, **system(0.5)).run(0.05)
    with pytest.raises(ValueError, match="not both"):
        arpy.Simulation(ps, wave, dt=0.01, max_dt=0.01, **system(0.01))
    with pytest.raises(ValueError, match="max_dt must be"):
        arpy.Simulation(ps, wave, max_dt=-1.0, **system(0.01))
