"""General right-hand sides on self-organizing particles: systems of fields, variable diffusivity, the
compressible term -f div u (Eq. 2.3b), Dirichlet values and Neumann fluxes on walls; checked against
manufactured solutions (the source computed from the exact field by finite differences, independent
of arpy)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest

import arpy
from arpy.dcpse.boundary import Dirichlet, Neumann, conditions, face_names
from arpy.dcpse.domain import REPAIR, DomainDCPSE
from arpy.adapt.resolution import field_resolution

TWO_PI = 2 * np.pi


def central(fun, x: np.ndarray, t: float, axis: int) -> np.ndarray:
    """d fun / dx_axis by the fourth-order central difference (h = 1e-3: error about 1e-10)."""
    h = 1e-3
    e = np.zeros(x.shape[1])
    e[axis] = h
    return (-fun(x + 2 * e, t) + 8 * fun(x + e, t) - 8 * fun(x - e, t) + fun(x - 2 * e, t)) / (12 * h)


def d_dt(fun, x: np.ndarray, t: float) -> np.ndarray:
    h = 1e-4
    return (-fun(x, t + 2 * h) + 8 * fun(x, t + h) - 8 * fun(x, t - h) + fun(x, t - 2 * h)) / (12 * h)


class Problem:
    """Exact fields and coefficients in the unit square: periodic (waves of period 1) or with walls
    (smooth fields with non-zero normal derivatives on every wall, a velocity tangential to them)."""

    def __init__(self, walls: str) -> None:
        self.walls = walls
        self.periodic = periodic = walls == "periodic"
        self.domain = arpy.Domain([1.0, 1.0], periodic=periodic)
        self.q = TWO_PI if periodic else np.pi

    def u_exact(self, x, t):
        if self.periodic:
            return 1 + 0.5 * np.sin(TWO_PI * (x[:, 0] + x[:, 1]) + t)
        return 1 + 0.5 * np.sin(2 * x[:, 0] + 3 * x[:, 1] + t)

    def v_exact(self, x, t):
        if self.periodic:
            return 0.5 + 0.3 * np.cos(TWO_PI * (x[:, 0] - 2 * x[:, 1])) * np.exp(-t)
        return 0.5 + 0.3 * np.cos(x[:, 0] - 2 * x[:, 1]) * np.exp(-t)

    def k(self, x, fields=None):
        s = TWO_PI if self.periodic else 1.0
        return 0.01 * (1 + 0.5 * np.sin(s * (x[:, 0] + x[:, 1])))

    def velocity(self, x, t=None, f=None):
        q = self.q
        return np.stack([0.1 * np.sin(q * x[:, 0]) * np.cos(q * x[:, 1]),
                         0.05 * np.sin(q * x[:, 1]) * (1 + np.cos(q * x[:, 0]))], axis=1)

    def div_flux(self, fun, coef, x, t):
        """div(coef grad fun) by central differences."""
        return sum(central(lambda y, s, a=a: coef(y) * central(fun, y, s, a), x, t, a) for a in range(2))

    def scalar_source(self, x, t):
        """S of u_t + div(vel u) = div(k grad u) + S."""
        f = self.u_exact
        flux = sum(central(lambda y, s, a=a: self.velocity(y)[:, a] * f(y, s), x, t, a) for a in range(2))
        return d_dt(f, x, t) + flux - self.div_flux(f, self.k, x, t)

    def system_sources(self, x, t):
        """S_u, S_v of u_t = div(k grad u) - u v + S_u, v_t = 0.004 lap v + u v - v + S_v."""
        u, v = self.u_exact(x, t), self.v_exact(x, t)
        su = d_dt(self.u_exact, x, t) - self.div_flux(self.u_exact, self.k, x, t) + u * v
        sv = d_dt(self.v_exact, x, t) - self.div_flux(self.v_exact, lambda y: np.full(len(y), 0.004), x, t) - u * v + v
        return su, sv

    def conditions(self, fun, walls: str | None = None):
        """fun's exact values (Dirichlet) or outward normal derivatives (Neumann) on the walls."""
        walls = walls or self.walls
        if walls == "periodic":
            return None
        if walls == "dirichlet":
            return Dirichlet(fun)
        return {name: Neumann(lambda w, t, a=k // 2, sign=(1 if k % 2 else -1): sign * central(fun, w, t, a))
                for k, name in enumerate(face_names(2))}


@lru_cache(maxsize=None)
def particles(periodic: bool, D0: float, seed: int) -> arpy.Particles:
    dom = arpy.Domain([1.0, 1.0], periodic=periodic)
    start = np.random.default_rng(seed).random((int(1.2 / D0 ** 2), 2))
    return arpy.self_organize(start, lambda p: np.full(len(p), D0), domain=dom, seed=seed)


RESOLUTIONS = (0.1, 0.07, 0.05)
SEEDS = (1, 2, 3)
#: the manufactured-solution runs, the suite's costliest here, over two seeds (their margins were
#: measured over seeds 1-5)
RUN_SEEDS = (1, 2)


def rms_order(errors: list[tuple[int, float]]) -> float:
    n, e = np.array(errors).T
    return float(np.polyfit(np.log(1 / np.sqrt(n)), np.log(e), 1)[0])


def scalar_run(problem: Problem, D0: float, seed: int) -> tuple[int, float, float]:
    ps = particles(problem.periodic, D0, seed)

    def rhs(t, x, f, ops):
        return ops.diffusion(problem.k, "f") + problem.scalar_source(x, t)

    sim = arpy.Simulation(ps, lambda p: problem.u_exact(p, 0.0), rhs=rhs, velocity=problem.velocity,
                          conservative=True, boundary=problem.conditions(problem.u_exact), D0=D0, reorganize_every=0,
                          integrator="rk4", dt=0.02).run(0.2)
    e = sim.f - problem.u_exact(sim.x, sim.t)
    assert max(entry["degenerate"] for entry in sim.log) == 0
    return ps.n, float(np.sqrt(np.mean(e ** 2))), float(np.abs(e).max())


def system_run(problem: Problem, D0: float, seed: int) -> tuple[int, float, float]:
    ps = particles(problem.periodic, D0, seed)

    def rhs(t, x, f, ops):
        su, sv = problem.system_sources(x, t)
        uv = f["u"] * f["v"]
        return {"u": ops.diffusion(lambda y, g: problem.k(y), "u") - uv + su,
                "v": 0.004 * ops.laplacian("v") + uv - f["v"] + sv}

    # with walls: u held at its values, v given its fluxes
    boundary = None if problem.periodic else {"u": problem.conditions(problem.u_exact, "dirichlet"),
                                              "v": problem.conditions(problem.v_exact, "neumann")}
    sim = arpy.Simulation(ps, {"u": lambda p: problem.u_exact(p, 0.0), "v": lambda p: problem.v_exact(p, 0.0)},
                          rhs=rhs, boundary=boundary, D0=D0, reorganize_every=0, integrator="rk4", dt=0.02).run(0.2)
    e = np.concatenate([sim.fields["u"] - problem.u_exact(sim.x, sim.t), sim.fields["v"] - problem.v_exact(sim.x, sim.t)])
    return ps.n, float(np.sqrt(np.mean(e ** 2))), float(np.abs(e).max())


@pytest.mark.parametrize("run, walls", [(scalar_run, "periodic"), (scalar_run, "dirichlet"), (scalar_run, "neumann"),
                                        (system_run, "periodic"), (system_run, "mixed")])
def test_manufactured_solutions_converge_at_order_two(run, walls):
    """The Laplacian's O(h^2) sets the order: the RMS error over three resolutions falls at order
    1.6-2.6 for every seed, the largest error falls with h too and stays within 8 times the RMS error
    (no particle left behind, e.g. one moved onto a Dirichlet wall without its values).  Measured,
    seeds 1-5: RMS orders 1.83-2.38, the maxima's 1.21-2.60 (least with Neumann walls, whose
    mirror images are exact to O(s^3) only); largest / RMS error at the finest set 2.0-6.4
    (snapped particles left with the values of where they were give 13)."""
    problem = Problem(walls)
    for seed in RUN_SEEDS:
        rows = [run(problem, D0, seed) for D0 in RESOLUTIONS]
        order = rms_order([(n, rms) for n, rms, _ in rows])
        assert 1.6 < order < 2.6, (seed, rows, order)
        assert rows[-1][2] < rows[0][2] and rows[-1][2] < 8 * rows[-1][1], (seed, rows)


def test_the_builtin_equation_and_the_same_rhs_give_the_same_bits():
    """nu lap f as a right-hand side gives bitwise the run of nu=: the same operators, assembled in
    the same pass from the second stage on, with a re-organization (variant (ii)) and RK4."""
    box = arpy.Domain([1.0, 1.0], periodic=(True, False))
    ps = particles(False, 0.1, 4)
    ps = arpy.self_organize(ps.x, lambda p: np.full(len(p), 0.1), domain=box, seed=4)

    def blob(p):
        return np.exp(-30 * ((p - 0.5) ** 2).sum(1))

    def u(x, t, f):
        return np.stack([np.ones(len(x)), np.zeros(len(x))], axis=1)

    for integrator in ("euler", "rk4"):
        common = dict(velocity=u, D0=0.1, Dmin=0.05, reorganize_every=2, integrator=integrator, dt=0.01)
        a = arpy.Simulation(ps, blob, nu=0.01, **common).run(0.04)
        b = arpy.Simulation(ps, blob, nu=0.01, rhs=lambda t, x, f, ops: {"f": 0.01 * ops.laplacian("f")},
                            **common).run(0.04)
        assert a.n == b.n and np.array_equal(a.x, b.x) and np.array_equal(a.f, b.f)


def test_neumann_images_are_exact_for_quadratics_at_faces_edges_and_corners():
    """f(image) = f_p + 2 s q with q the exact flux: exact when f_nnn = 0 (here a quadratic), for
    images across one wall and across two (corners, rules applied in axis order), in 3D."""
    dom = arpy.Domain([[0.0, 0.0, 0.0], [1.0, 2.0, 1.0]], periodic=(False, False, True))
    rng = np.random.default_rng(5)
    x = rng.random((400, 3)) * [1.0, 2.0, 1.0]

    def f(p, t=0.0):
        return 1 + p[:, 0] - 2 * p[:, 1] + 0.5 * p[:, 0] ** 2 + p[:, 0] * p[:, 1] - 0.3 * p[:, 1] ** 2 + p[:, 2] * 0

    def grad(p, a):
        return [1 + p[:, 0] + p[:, 1], -2 + p[:, 0] - 0.6 * p[:, 1], 0 * p[:, 2]][a]

    faces = {name: Neumann(lambda w, t, a=k // 2, sign=(1 if k % 2 else -1): sign * grad(w, a))
             for k, name in enumerate(face_names(3)) if k < 4}
    bc = conditions(faces, dom)
    xg, src = dom.ghosts(x, np.full(len(x), 0.3))
    walls = ((xg[:, :2] < 0) | (xg[:, :2] > [1.0, 2.0])).sum(axis=1)
    assert (walls == 2).sum() > 10                            # corner images are among them
    # periodic images along z: f does not depend on z, so every image's exact value is f there
    np.testing.assert_allclose(bc.ghost_values(f(x), x, src, xg, 0.0), f(xg), rtol=0, atol=1e-12)


def test_conditions_are_checked():
    box = arpy.Domain([1.0, 1.0], periodic=(True, False))
    assert conditions(None, box).homogeneous
    with pytest.raises(ValueError, match="periodic"):
        conditions({"x-": Neumann(1.0)}, box)
    with pytest.raises(ValueError, match="unknown faces"):
        conditions({"left": Neumann(1.0)}, box)
    with pytest.raises(ValueError, match="Neumann"):
        conditions({"y-": 1.0}, box)
    with pytest.raises(ValueError, match="free space"):
        conditions(Neumann(1.0), arpy.Domain())
    with pytest.raises(ValueError, match="finite"):
        Neumann(np.nan)
    assert not conditions({"y+": Neumann(0.5)}, box).homogeneous


def test_operators_against_exact_derivatives():
    """ops on a static set: gradient, divergence (array and callable), diffusion with a constant and
    a variable k, a second derivative, all close to the exact values (order-4 DC-PSE)."""
    ps = particles(True, 0.05, 1)
    x = ps.x

    def f(p, t=0.0):
        return np.sin(TWO_PI * p[:, 0]) * np.cos(TWO_PI * p[:, 1])

    seen = {}

    def rhs(t, xs, fields, ops):
        seen["grad"] = ops.gradient("f")
        seen["lap"] = ops.laplacian("f")
        seen["dxx"] = ops.derivative((2, 0), "f")
        seen["div"] = ops.divergence(np.stack([fields["f"], fields["f"]], axis=1))
        seen["div_callable"] = ops.divergence(lambda y, g: np.stack([g["f"], g["f"]], axis=1))
        seen["k_const"] = ops.diffusion(0.5, "f")
        seen["k_var"] = ops.diffusion(lambda y, g: 1 + 0.5 * np.cos(TWO_PI * y[:, 0]), "f")
        return np.zeros(len(xs))

    # (the rhs returns 0; the step is below the stability bound of the terms it applied)
    arpy.Simulation(ps, f, rhs=rhs, D0=0.05, dt=1e-4, reorganize_every=0).step()
    s, c = np.sin(TWO_PI * x), np.cos(TWO_PI * x)
    fx, fy = TWO_PI * c[:, 0] * c[:, 1], -TWO_PI * s[:, 0] * s[:, 1]
    lap = -2 * TWO_PI ** 2 * f(x)
    k, kx = 1 + 0.5 * c[:, 0], -0.5 * TWO_PI * s[:, 0]
    scale = TWO_PI ** 2
    np.testing.assert_allclose(seen["grad"], np.stack([fx, fy], axis=1), atol=0.02 * TWO_PI)
    np.testing.assert_allclose(seen["lap"], lap, atol=0.03 * 2 * scale)
    np.testing.assert_allclose(seen["dxx"], -TWO_PI ** 2 * f(x), atol=0.03 * scale)
    np.testing.assert_allclose(seen["div"], fx + fy, atol=0.02 * TWO_PI)
    np.testing.assert_array_equal(seen["div"], seen["div_callable"])
    np.testing.assert_array_equal(seen["k_const"], 0.5 * seen["lap"])
    np.testing.assert_allclose(seen["k_var"], k * lap + kx * fx, atol=0.05 * 2 * scale)


def test_the_monitor_of_several_fields_is_the_finest():
    ps = particles(True, 0.07, 2)
    f1 = np.exp(-20 * ((ps.x - 0.3) ** 2).sum(1))
    f2 = np.exp(-20 * ((ps.x - 0.7) ** 2).sum(1))
    kw = dict(D0=0.07, Dmin=0.03, domain=ps.domain)
    both = field_resolution(ps.x, np.stack([f1, f2], axis=1), ps.D, **kw)
    one, two = field_resolution(ps.x, f1, ps.D, **kw), field_resolution(ps.x, f2, ps.D, **kw)
    probe = np.random.default_rng(0).random((300, 2))
    assert np.all(both(probe) <= np.minimum(one(probe), two(probe)) + 1e-15)
    assert both(probe).min() < 0.9 * 0.07


def test_systems_are_checked_and_round_trip(tmp_path):
    ps = particles(False, 0.1, 1)
    fields = {"u": np.ones(ps.n), "v": np.zeros(ps.n)}

    def rhs(t, x, f, ops):
        return {"u": -f["u"], "v": f["u"]}

    sim = arpy.Simulation(ps, fields, rhs=rhs, D0=0.1, dt=0.01, reorganize_every=0)
    with pytest.raises(AttributeError, match="fields"):
        sim.f
    sim.run(0.05)
    np.testing.assert_allclose(sim.fields["u"], (1 - 0.01) ** 5)      # forward Euler on u' = -u
    path = sim.save_state(tmp_path / "s.npz")
    again = arpy.Simulation(ps, fields, rhs=rhs, D0=0.1, dt=0.01, reorganize_every=0).load_state(path)
    assert np.array_equal(again.F, sim.F) and again.t == sim.t
    single = arpy.Simulation(ps, np.ones(ps.n), nu=0.01, D0=0.1, reorganize_every=0)
    with pytest.raises(ValueError, match="fields"):
        single.load_state(path)
    with pytest.raises(ValueError, match="rhs must return"):
        arpy.Simulation(ps, fields, rhs=lambda t, x, f, ops: {"w": f["u"]}, D0=0.1, dt=0.01).step()
    with pytest.raises(ValueError, match="shape"):
        arpy.Simulation(ps, fields, rhs=lambda t, x, f, ops: {"u": f["u"][:3]}, D0=0.1, dt=0.01).step()
    with pytest.raises(ValueError, match="monitor_fields"):
        arpy.Simulation(ps, fields, rhs=rhs, D0=0.1, dt=0.01, monitor_fields=["w"])
    with pytest.raises(ValueError, match="boundary maps field names"):
        arpy.Simulation(ps, fields, rhs=rhs, D0=0.1, dt=0.01, boundary={"w": Neumann(1.0)})
    with pytest.raises(ValueError, match="velocity"):
        arpy.Simulation(ps, fields, rhs=rhs, D0=0.1, dt=0.01, conservative=True)


def dirichlet_operators(D0: float, seed: int, snap: bool = True):
    """A set in the unit square with Dirichlet walls (snapped as a simulation snaps them), the
    conditions of f, the Laplacian at the particles and the interpolation to a second set."""
    dom = arpy.Domain([1.0, 1.0])
    bc = conditions(Dirichlet(lambda w, t: wave(w)), dom)
    old, new = particles(False, D0, seed), particles(False, D0, seed + 100)
    x, x_new = old.x, new.x
    if snap:
        x, x_new = bc.snap(x, old.eps, arpy.equations.SNAP), bc.snap(x_new, new.eps, arpy.equations.SNAP)
    lap = DomainDCPSE(x, old.eps, domain=dom, order=4, strict=False, operators=["laplacian"], dirichlet=bc, **REPAIR)
    to_new = DomainDCPSE(x, old.eps, x_new, new.eps, domain=dom, order=4, strict=False, dirichlet=bc, **REPAIR)
    return x, bc, lap, to_new, x_new


def wave(x):
    return 1 + 0.5 * np.sin(2 * x[:, 0] + 3 * x[:, 1])


def test_dirichlet_walls_read_boundary_particles_at_the_orders_of_the_operators():
    """The Laplacian (order 2, largest error over the free particles) and the interpolation old -> new
    (order 4, RMS error; its largest error falls too), with the values of f on the walls carried by
    boundary particles.  Measured, seeds 1-8: Laplacian orders 1.81-2.07, interpolation 4.22-4.45.
    The largest interpolation errors sit at rows the repair rebuilt 1.5 times wider, whose larger
    constant puts the order of the maxima at 2.8-4.1 over these three sets (mirror images with Neumann
    fluxes, exact to O(s^3) only, give 0.4-1.1 for the Laplacian and 2.6-3.5 for the interpolation)."""
    for seed in SEEDS:
        lap_err, rms, worst, n = [], [], [], []
        for D0 in RESOLUTIONS:
            x, bc, lap, to_new, x_new = dirichlet_operators(D0, seed)
            free = np.setdiff1d(np.arange(len(x)), bc.on_walls(x, 0.0)[0])
            assert lap.n_boundary > 0 and lap.failed.size == 0 and to_new.failed.size == 0
            lap_err.append(np.abs((lap.laplacian() @ lap.extend(wave(x), bc))[free] + 13 * (wave(x[free]) - 1)).max())
            e = to_new.interpolate(wave(x), bc=bc) - wave(x_new)
            rms.append(np.sqrt(np.mean(e ** 2)))
            worst.append(np.abs(e).max())
            n.append(len(x))
        assert 1.5 < rms_order(list(zip(n, lap_err))) < 2.5, (seed, n, lap_err)
        assert 3.6 < rms_order(list(zip(n, rms))) < 5.0, (seed, n, rms)
        assert worst[0] > worst[1] > worst[2], (seed, worst)


def test_dirichlet_walls_give_a_stable_laplacian():
    """The Laplacian acting on the free particles (those not on a Dirichlet face) has eigenvalues with
    negative real parts only, so forward Euler and RK4 are stable for small steps.  Without the
    snapping of particles closer than SNAP core sizes to a wall, a particle almost on its boundary
    particle can make positive eigenvalues of order 1e4 (checked here too, on a set where it does)."""
    for seed in SEEDS:
        for D0 in RESOLUTIONS[1:]:
            x, bc, lap, _, _ = dirichlet_operators(D0, seed)
            free = np.setdiff1d(np.arange(len(x)), bc.on_walls(x, 0.0)[0])
            A = lap.laplacian()[free][:, free].toarray()
            assert np.linalg.eigvals(A).real.max() < 0, (seed, D0)
    x, bc, lap, _, _ = dirichlet_operators(0.05, 3, snap=False)
    free = np.setdiff1d(np.arange(len(x)), bc.on_walls(x, 0.0)[0])
    assert np.linalg.eigvals(lap.laplacian()[free][:, free].toarray()).real.max() > 100


def test_a_simulation_snaps_and_holds_the_dirichlet_values():
    walls = arpy.Domain([1.0, 1.0])
    ps = particles(False, 0.1, 2)
    g = Dirichlet(lambda w, t: 1 + t + w[:, 1])
    sim = arpy.Simulation(ps, np.zeros(ps.n), nu=0.01, boundary={"x-": g}, D0=0.1, Dmin=0.05, dt=0.01,
                          reorganize_every=3, seed=0)   # dt 0.01 is stable on seed 0's particles
    gap = sim.x[:, 0]
    assert np.all((gap == 0) | (gap >= arpy.equations.SNAP * sim.eps))
    moved = np.any(sim.x != ps.x, axis=1)
    assert moved.any() and np.all(sim.x[moved, 0] == 0)
    sim.run(0.05)                                   # with re-organizations
    on = sim.x[:, 0] == 0
    assert on.sum() > 3
    np.testing.assert_array_equal(sim.f[on], 1 + sim.t + sim.x[on, 1])
    assert np.all(sim.x[:, 0] >= 0)
    with pytest.raises(ValueError, match="verlet_skin"):
        arpy.Simulation(ps, np.zeros(ps.n), nu=0.01, boundary=g, D0=0.1, verlet_skin=0.3)
    with pytest.raises(ValueError, match="stencil_rule"):
        arpy.Simulation(ps, np.zeros(ps.n), nu=0.01, boundary=g, D0=0.1, stencil_rule="displace")
    with pytest.raises(ValueError, match="finite"):
        Dirichlet(np.inf)
    assert walls.d == 2


def test_neumann_fluxes_with_reused_lists():
    """Verlet lists kept across stages (verlet_skin) move the ghosts with their particles: the fluxes'
    image values follow, and the run equals the one with fresh lists up to rounding."""
    problem = Problem("neumann")
    ps = particles(False, 0.07, 1)

    def run(skin):
        def rhs(t, x, f, ops):
            return ops.diffusion(problem.k, "f") + problem.scalar_source(x, t)

        return arpy.Simulation(ps, lambda p: problem.u_exact(p, 0.0), rhs=rhs, velocity=problem.velocity,
                               conservative=True, boundary=problem.conditions(problem.u_exact), D0=0.07,
                               reorganize_every=0, integrator="rk4", dt=0.02, verlet_skin=skin).run(0.1)

    fresh, kept = run(0.0), run(0.3)
    assert kept._lists is not None and kept._lists.builds < 4 * kept.steps
    np.testing.assert_allclose(kept.f, fresh.f, rtol=0, atol=1e-11)
