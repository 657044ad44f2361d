"""§4.5: the five-spot problem (viscous Buckley-Leverett in a stationary well field)."""

from __future__ import annotations

import numpy as np

from arpy import cases


def test_velocity_is_minus_grad_p_and_divergence_free_between_wells():
    rng = np.random.default_rng(0)
    x = rng.uniform(-0.4, 0.4, (200, 2))
    x = x[np.sqrt((x ** 2).sum(1)) > 0.1]
    rw = 0.02

    def p(y):                                  # the regularized potential of §4.5
        out = -0.5 * np.log((y ** 2).sum(1) + rw ** 2)
        for c in cases.FIVE_SPOT_WELLS:
            out += 0.5 * np.log(((y - c) ** 2).sum(1) + rw ** 2)
        return out

    h = 1e-6
    grad = np.stack([(p(x + h * e) - p(x - h * e)) / (2 * h) for e in np.eye(2)], axis=1)
    u = cases.five_spot_velocity(x, rw)
    np.testing.assert_allclose(u, -grad, rtol=1e-6, atol=1e-6)
    div = sum((cases.five_spot_velocity(x + h * e, 0.0)[:, k] - cases.five_spot_velocity(x - h * e, 0.0)[:, k])
              / (2 * h) for k, e in enumerate(np.eye(2)))
    assert np.abs(div).max() < 1e-4                          # harmonic p away from the wells
    # outward at the injection well, inward at the corner sinks
    assert np.all((cases.five_spot_velocity(x, rw) * x).sum(1)[np.sqrt((x ** 2).sum(1)) < 0.2] > 0)


def test_buckley_leverett_speed_is_the_flux_derivative():
    f = np.linspace(0.001, 0.999, 500)
    for mu in (0.5, 2.0):
        g = cases.buckley_leverett_flux
        num = (g(f + 1e-7, mu) - g(f - 1e-7, mu)) / 2e-7
        np.testing.assert_allclose(cases.buckley_leverett_speed(f, mu), num, rtol=1e-5)
    assert cases.buckley_leverett_speed(np.array([-0.1, 0.0, 1.0, 1.2]), 0.5).tolist() == [0, 0, 0, 0]


def test_five_spot_front_spreads_and_saturation_stays_bounded():
    r = cases.five_spot(D0=0.12, T=0.006, snapshots=(0.0, 0.006))
    sim = r["sim"]
    assert r["n"][-1] > 1.3 * r["n"][0]                       # the front lengthens: more particles
    assert -0.05 <= r["f_min"] and r["f_max"] <= 1.0 + 1e-12  # undershoot of the front up to 5 %
    assert np.all(sim.f[(sim.x ** 2).sum(1) < 0.02 ** 2] == 1.0)
    assert set(r["snapshots"]) == {0.0, 0.006}
    wet = lambda s: np.sqrt((s["x"][s["f"] > 0.5] ** 2).sum(1)).max()  # noqa: E731
    assert wet(r["snapshots"][0.006]) > wet(r["snapshots"][0.0])         # the water front moves out
