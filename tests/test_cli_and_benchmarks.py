"""The command line and the benchmark scripts run end to end (small sizes)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import meshio
import numpy as np
import pytest

from arpy.cases import equal_error_ratio, slope
from arpy.cli import main
from conftest import kdtree_pairs
from test_outputs import check_case_outputs

ROOT = Path(__file__).resolve().parents[1]


def benchmark(name: str):
    """The script benchmarks/<name>.py as a module, not run (benchmarks/report.py's loader)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import report
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    return report.script(name)


def test_demo_runs_and_all_methods_agree(capsys):
    assert main(["demo", "--n", "3000", "--lam", "20", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "ar (adaptive-resolution cells)" in out and "cell (uniform cell list)" in out
    assert "brute (all pairs)" in out
    assert "NO" not in out


def test_module_entry_point_help():
    out = subprocess.run([sys.executable, "-m", "arpy", "--help"], capture_output=True, text=True, check=True)
    assert "demo" in out.stdout


def test_cell_list_benchmark_quick(tmp_path):
    """Every row's pair count equals the one scipy's cKDTree finds on the same set (rebuilt
    here from the benchmark's generator), and every method found the same pairs."""
    cell_lists = benchmark("cell_lists")
    make_case, report = cell_lists.make_case, cell_lists.report
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "cell_lists.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    data = json.loads((tmp_path / "cell_lists_2d_quick.json").read_text())
    assert all(r["same_pairs"] for r in data["rows"])
    assert {r["method"] for r in data["rows"]} >= {"arpy cell (sym)", "kd query_pairs", "kd ball_point"}
    counts = {}
    for r in data["rows"]:
        key = (r["cutoffs"], r["n"])
        if key not in counts:
            x, rc = make_case(r["n"], 2, key[0])
            counts[key] = kdtree_pairs(x, rc)[0].size
        assert r["pairs"] == counts[key], (key, r["method"])
    assert len(counts) == 4
    assert (tmp_path / "cell_lists_2d_quick.png").stat().st_size > 0
    page = (tmp_path / "cell_lists_2d_quick.md").read_text()
    assert page == report(data) and "](cell_lists_2d_quick.png)" in page


def test_rules_benchmark_quick(tmp_path):
    """benchmarks/rules.py at its quick size: each rule's pair count within 2 % of the min rule's (its
    cutoffs scaled to match), both methods the same pairs as brute force on the benchmark's set, and
    the page made from the JSON."""
    from arpy.reference import brute_force_pairs

    rules = benchmark("rules")
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "rules.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    data = json.loads((tmp_path / "rules_quick.json").read_text())
    rows = data["rows"]
    assert {(r["d"], r["rule"], r["method"]) for r in rows} == {
        (d, rule, m) for d in (2, 3) for rule in ("min", "max", "sum") for m in ("cell", "ar")}
    counts = {}
    for r in rows:
        if (r["d"], r["rule"]) not in counts:
            x, rc = rules.make_case(r["n"], r["d"])
            counts[r["d"], r["rule"]] = brute_force_pairs(x, r["scale"] * rc, rule=r["rule"])[0].size
        assert r["pairs"] == counts[r["d"], r["rule"]] and r["same_pairs"]
        assert abs(r["pairs"] / counts[r["d"], "min"] - 1) < 0.02
    assert (tmp_path / "rules_quick.png").stat().st_size > 0
    assert (tmp_path / "rules_quick.md").read_text() == rules.report(data)


def test_ar_cell_list_benchmark_quick(tmp_path):
    """The pair counts of the benchmark rows against scipy's cKDTree on the same
    distributions (arpy.ar_benchmark is deterministic), whose span is the row's lambda."""
    import arpy

    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "ar_cell_lists.py"), "--quick", "--out",
                          str(tmp_path)], check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "ar_cell_lists_quick.json").read_text())
    rows = data["fig6"] + data["fig7"]
    assert all(r["same_pairs"] for r in rows)
    assert data["lam1"] and all(r["cells_same_pairs"] for r in data["lam1"])
    for r in rows:
        x, rc = arpy.ar_benchmark(r["n_small"], r["lam"])
        assert len(x) == r["n"] and rc.max() / rc.min() == pytest.approx(r["lam"], rel=1e-12)
        assert r["pairs"] == kdtree_pairs(x, rc)[0].size, (r["lam"], r["n"])
    assert "break-even lambda" in out
    for name in ("ar_cell_lists_quick_fig6.png", "ar_cell_lists_quick_fig7.png"):
        assert (tmp_path / name).stat().st_size > 0
    report = benchmark("ar_cell_lists").report
    page, be = (tmp_path / "ar_cell_lists_quick.md").read_text(), data["summary"]["break_even_lambda"]
    assert page == report(data) and f"| {'never' if be is None else f'{be:.2f}'} |" in page


def test_cache_order_benchmark_quick(tmp_path):
    """benchmarks/cache_order.py at its quick sizes: DC-PSE in both orders, every step case with and
    without cache order on about as many particles, and the page is its report() of the JSON."""
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "cache_order.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    data = json.loads((tmp_path / "cache_order_quick.json").read_text())
    assert [r["d"] for r in data["dcpse"]] == [2, 3]
    assert all(r["random"] > 0 and r["cache"] > 0 and r["cache_order"] > 0 for r in data["dcpse"])
    assert [r["case"] for r in data["steps"]] == ["advection"]
    for r in data["steps"]:
        assert r["plain"]["steps"] >= 1 and r["cache"]["steps"] >= 1
        assert abs(r["cache"]["n_mean"] / r["plain"]["n_mean"] - 1) < 0.05
    assert (tmp_path / "cache_order_quick.md").read_text() == benchmark("cache_order").report(data)


def test_threads_benchmark_quick(tmp_path):
    """benchmarks/threads.py at its quick sizes: every section measured at 1 and 2 threads, and the
    Markdown page is the one its report() makes from the JSON."""
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "threads.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    data = json.loads((tmp_path / "threads_quick.json").read_text())
    assert [r["d"] for r in data["dcpse"]] == [2, 3] and all(r["t1"] > 0 and r["t2"] > 0 for r in data["dcpse"])
    assert [r["lam"] for r in data["lists"]] == [1.0, 10.0]
    assert {r["method"] for r in data["periodic"]} == {"cell", "ar"}
    assert set(data["steps"]) == {f"{c}@{t}" for c in ("advection", "advection+skin", "pulse") for t in (1, 2)}
    for r in data["steps"].values():
        assert r["steps"] >= 1 and r["us"] > 0 and abs(r["glue"] + sum(r[k] for k in (
            "t_monitor", "t_organize_lists", "t_organize_rest", "t_interpolate", "t_rhs")) - r["us"]) < 1e-6 * r["us"]
    threads = benchmark("threads")
    assert (tmp_path / "threads_quick.md").read_text() == threads.report(data)
    # the targets: every list and DC-PSE figure, and with an old build the steps against 1/3 of its figures
    assert len(threads.targets(data)) == 2 + 4 * 2 + 2 * 2
    two = {c: [data["steps"][f"{v}@2"]["us"] for v in (c, c + "+skin") if f"{v}@2" in data["steps"]]
           for c in ("advection", "pulse")}
    fast = {f"{c}@1": {"us": 3.03 * max(us)} for c, us in two.items()}
    slow = {f"{c}@1": {"us": 2.97 * min(us)} for c, us in two.items()}
    met = [t for t in threads.targets(dict(data, baseline=fast)) if "the old build" in t]
    missed = [t for t in threads.targets(dict(data, baseline=slow)) if "the old build" in t]
    assert len(met) == len(missed) == 3                # (a), (a) with reused lists, (b)
    assert all(t.endswith(": met)") for t in met) and all(t.endswith("not met)") for t in missed)


def test_dcpse_benchmark_quick(tmp_path):
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "dcpse.py"), "--quick", "--out", str(tmp_path)],
                         check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "dcpse_quick.json").read_text())
    assert all(r["max_rel_diff_vs_reference"] < 1e-10 for r in data["timing"])
    assert abs(data["convergence"]["2"]["orders"]["interpolation"] - 4) < 0.5
    assert "convergence orders" in out
    assert (tmp_path / "dcpse_quick.png").stat().st_size > 0
    report = benchmark("dcpse").report
    page = (tmp_path / "dcpse_quick.md").read_text()
    assert page == report(data) and f"| {data['convergence']['2']['orders']['interpolation']:.2f} |" in page


def test_self_organization_benchmark_quick(tmp_path):
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "self_organization.py"), "--quick", "--out",
                          str(tmp_path)], check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "self_organization_quick.json").read_text())
    assert "paper" in out and data["pulse"][0]["converged"]
    assert data["pulse"][0]["n"] > 400                     # 800 random particles: fused, then refined at the pulse
    fig23 = {r["case"]: r for r in data["fig23"]}
    assert all(fig23[case]["energy_end"] < fig23[case]["energy_start"] for case in ("V1", "V2 jump", "V2 ramp"))
    # the explicit ball gives every particle near the square its D~ = 0.01; with no ball, neighbours
    # across the square's edge keep D~'s full jump of 10
    assert fig23["V2 jump, explicit"]["neighbour_ratio"] == 1.0
    assert fig23["V2 jump, pointwise"]["neighbour_ratio"] == pytest.approx(10.0)
    assert data["timing"][0]["converged"]
    for name in ("fig31", "fig23", "timing"):
        assert (tmp_path / f"self_organization_quick_{name}.png").stat().st_size > 0
    report = benchmark("self_organization").report
    page = (tmp_path / "self_organization_quick.md").read_text()
    assert page == report(data) and f"| {data['pulse'][0]['n']:,} |" in page


def test_run_pulse_and_advection_write_outputs(tmp_path, capsys):
    assert main(["run", "pulse", "--D0", "0.2", "--T", "0.02", "--remeshed", "32", "--quiet", "--out",
                 str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "L-infinity error" in out and "remeshed particle method" in out
    for name in ("pulse.png", "pulse.npz", "pulse_particles.vtu"):
        assert (tmp_path / "pulse" / name).stat().st_size > 0
    data = np.load(tmp_path / "pulse" / "pulse.npz")
    assert data["x"].shape[0] == data["f"].shape[0] == data["D"].shape[0]
    assert np.abs(data["f"] - data["f_exact"]).max() < 0.05
    assert main(["run", "pulse", "--monitor", "fourth", "--D0", "0.5", "--T", "0.02", "--remeshed", "0", "--quiet",
                 "--out", str(tmp_path)]) == 0
    assert "D0 = 0.5, T = 0.02, monitor fourth" in capsys.readouterr().out
    data = np.load(tmp_path / "pulse" / "pulse.npz")
    assert np.abs(data["f"] - data["f_exact"]).max() < 0.05
    assert main(["run", "advection", "--monitor", "fourth", "--T", "0.025", "--output-every", "1", "--quiet", "--out",
                 str(tmp_path)]) == 0
    assert "D0 = 0.25, monitor fourth" in capsys.readouterr().out
    assert (tmp_path / "advection" / "advection_particles.vtu").stat().st_size > 0
    check_case_outputs(tmp_path / "advection", {"monitor": "fourth", "T": 0.025, "D0": 0.25}, steps=1)
    assert main(["run", "burgers", "--D0", "0.25", "--T", "0.01", "--remeshed", "32", "--quiet", "--out", str(tmp_path)]) == 0
    assert "pseudo-spectral" in capsys.readouterr().out
    for name in ("burgers.png", "burgers.npz", "burgers_particles.vtu"):
        assert (tmp_path / "burgers" / name).stat().st_size > 0
    assert main(["run", "consistency", "--field", "blob", "--monitor", "fourth", "--D0-end", "0.22", "--quiet", "--out",
                 str(tmp_path)]) == 0
    assert "blob of Sec. 4.2 at rest" in capsys.readouterr().out
    data = np.load(tmp_path / "consistency" / "consistency.npz")
    assert json.loads((tmp_path / "consistency" / "consistency.json").read_text())["columns"] == {"x_at_max": ["x", "y"]}
    last = meshio.read(tmp_path / "consistency" / "consistency_particles.vtu")      # (the finest set)
    assert len(last.points) == data["N"][-1] and last.point_data["err_interp"].max() == data["err_interp"][-1]
    np.testing.assert_allclose(data["D0"], 0.25 * 0.95 ** np.arange(1, 3), rtol=1e-12)     # D0 = 0.2375, 0.2256
    np.testing.assert_allclose(data["h"], np.sqrt(1.0 / data["N"]), rtol=1e-12)            # the unit square
    assert np.all(data["err_interp"] < 1e-3) and np.all(data["failed"] == 0)
    out = subprocess.run([sys.executable, "-m", "arpy", "run", "--help"], capture_output=True, text=True,
                         check=True).stdout
    assert "pulse" in out and "advection" in out and "consistency" in out and "burgers" in out


def test_simulation_benchmark_quick(tmp_path):
    """The §4.1-4.3 benchmark end to end at its quick sizes.  The orders and accuracy of the
    cases are tested in test_simulation.py; here: every figure is written, the rows follow
    the definitions (h from N, D0 sequences, slopes and particle ratios recomputed from the
    rows), and the resolution of the initial pulse particles matches the monitors'
    analytic minima (Eq. 2.8: D0 / sqrt(1 + (Pe / 2) e^-1) at the ring of max |grad f|;
    Eq. B.13: D0 (1 + 3 (Pe / 2)^2)^(-1/4) at the peak)."""
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "simulation.py"), "--quick", "--out",
                          str(tmp_path)], check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "simulation_quick.json").read_text())
    par = data["parameters"]
    assert "fitted orders" in out and "equal error" in out
    for key, p in (("fig41", par["consistency"]), ("fig41b", par["consistency_b13"])):   # §4.1, both monitors
        rows = data[key]["rows"]
        d0 = p["d0_start"] * p["factor"] ** np.arange(1, len(rows) + 1)
        np.testing.assert_allclose([r["D0"] for r in rows], d0, rtol=1e-12)
        assert len(rows) == int(np.floor(np.log(p["d0_end"] / p["d0_start"]) / np.log(p["factor"])))
        n, h = np.array([r["N"] for r in rows]), np.array([r["h"] for r in rows])
        np.testing.assert_allclose(h, np.sqrt(4.0 / n), rtol=1e-12)                  # |Omega| = 4
        assert np.all(np.diff(n) > 0)
        for name, col in (("max_interp", "err_interp"), ("max_laplacian", "err_laplacian")):
            assert data[key]["slopes"][name] == pytest.approx(slope(h, [r[col] for r in rows]), rel=1e-9)
        assert all(r["err_interp"] < 0.01 and r["D_at_max"] <= r["D0"] * (1 + 1e-12) for r in rows)
    for key, p in (("fig42", par["advection"]), ("fig42b", par["advection_b13"])):          # §4.2
        rows = data[key]["rows"]
        assert [r["D0"] for r in rows] == p["D0"]
        np.testing.assert_allclose([r["h"] for r in rows], 1 / np.sqrt([r["N_max"] for r in rows]), rtol=1e-12)
        assert all(r["error"] < 0.01 and r["degenerate_max"] == 0 and r["N"] <= r["N_max"] for r in rows)
    for kind in ("gradient", "fourth"):        # fig42h: the error after each re-organization (every 4 steps)
        hist = data["fig42h"][kind]
        T, dt = par["advection_history"]["T"], 0.025
        np.testing.assert_allclose(hist["t"], dt * (1 + np.arange(0, int(round(T / dt)), 4)), rtol=1e-12)
        assert abs(hist["max"][-1] - hist["error"]) < 1e-5                          # RK4 paths: ~1e-6
        assert hist["t_90"] in hist["t"] and np.all(np.array(hist["median"]) <= np.array(hist["max"]))
    for kind in ("gradient", "fourth"):        # fig42i: the blob interpolated old -> new, no flow
        static = data["fig42i"][kind]["rows"]
        assert len(static) >= 2 and static[1]["N"] > static[0]["N"]
        assert all(r["err_interp"] < 0.01 and r["failed"] == 0 and 0 < r["D_at_max"] <= r["D0"] for r in static)
        # Eq. 2.9 takes the smallest D~ within reach: D_p <= D~ (medians per band)
        assert all(0 < b["D_over_Dtilde"] <= 1 + 1e-12 and b["D_over_D0"] <= 1 + 1e-12
                   for b in data["fig42i"][kind]["bands"])
    assert data["fig43"]["N_initial"] > 100 and data["fig43"]["error"] < 0.1
    two, three = data["fig44"]["2d"], data["fig44"]["3d"]
    assert set(two["adaptive"]) == {"reach 1", "reach 2", "B.13, reach 1"}
    # the initial particles resolve the pulse down to the monitors' analytic minima (the ball of
    # Eq. 2.9 only takes minima of D~, so D_min cannot fall below them)
    for d, res, pe in ((2, two, 1000.0), (3, three, 100.0)):
        for key, rows in res["adaptive"].items():
            for r in rows:
                if r["monitor"] == "gradient":
                    lowest = r["D0"] / np.sqrt(1 + pe / 2 * np.exp(-1))
                else:
                    lowest = r["D0"] * (1 + 3 * (pe / 2) ** 2) ** -0.25
                assert lowest * (1 - 1e-9) <= r["D_min"] < 1.05 * lowest, (d, key, r["D0"], r["D_min"] / lowest)
            edge = 2.0 if d == 2 else 3.0
            n = np.array([r["N"] for r in rows], float)
            np.testing.assert_allclose([r["h"] for r in rows], edge / n ** (1 / d), rtol=1e-12)
            # the particle ratio at equal error, recomputed from the remeshed rows
            rem = res["remeshed"]
            ratio = equal_error_ratio([r["N"] for r in rem], [r["error"] for r in rem], n,
                                      [r["error"] for r in rows])
            np.testing.assert_allclose(res["particle_ratio"][key], ratio, rtol=1e-9)
            assert np.all(ratio > 1)
            assert all(r["error"] < (0.01 if d == 2 else 0.1) for r in rows)
    for res in (two, three):                    # the baseline's meshes: (cells + 1)^d nodes, h = edge / cells
        rem = res["remeshed"]
        d = 2 if res is two else 3
        assert [r["N"] for r in rem] == [(r["n_cells"] + 1) ** d for r in rem]
        assert rem[0]["error"] > rem[1]["error"]                                    # the baseline converges
    for rows in two["adaptive"].values():
        assert all(abs(m) < 0.05 for r in rows for m in r["mass_loss"])
    for name in ("fig41", "fig42", "fig42h", "fig42i", "fig43", "fig44", "fig45"):
        assert (tmp_path / f"simulation_quick_{name}.png").stat().st_size > 0
    # the results page: what report() makes of the JSON, with the JSON's numbers next to the paper's,
    # and a link to every figure written
    page = (tmp_path / "simulation_quick.md").read_text()
    assert page == benchmark("simulation").report(data)
    assert "`--quick` sizes" in page and data["machine"] in page
    assert (f"| 4.2 | order of the maximum error (Eq. 4.5) | 4 | {data['fig42']['order']:.2f} | "
            f"{data['fig42b']['order']:.2f} |") in page
    assert f"| 4.3 | N after self-organization, Pe = 10⁴ | 1300 | {data['fig43']['N_initial']} | – |" in page
    links = re.findall(r"\]\((simulation_quick_\w+\.png)\)", page)
    assert sorted(links) == sorted(p.name for p in tmp_path.glob("simulation_quick_*.png"))


def test_burgers_benchmark_quick(tmp_path):
    """The §4.4/4.7 benchmark at its quick sizes (the convergence is tested in
    test_burgers.py): |f| stays within max |f0| = 1 (maximum principle of viscous
    Burgers), Eq. 2.8 never asks for D_p > D0, the adaptive errors against the
    pseudo-spectral reference are small and the particle ratios at equal error follow from
    the rows; the cost section's bookkeeping: one self-organization per re-organization
    (every 10 steps, the first at t = 0), each with at least one iteration.  The Markdown page is
    the one report() makes from the JSON, and shows these figures."""
    import re

    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "burgers.py"), "--quick", "--out", str(tmp_path)],
                         check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "burgers_quick.json").read_text())
    assert "fitted orders" in out and "cost split" in out
    f46 = data["fig46"]
    assert f46["N"] > 500 and f46["D_max"] <= f46["D0"] * (1 + 1e-12)
    assert f46["scale_ratio"] == pytest.approx(f46["D_max"] / f46["D_min"], rel=1e-12)
    assert -1 - 1e-3 <= f46["f_min"] < -0.9 and 0.9 < f46["f_max"] <= 1 + 1e-3
    rows, rem = data["fig47"]["adaptive"], data["fig47"]["remeshed"]
    assert all(r["error"] < 1e-2 for r in rows)
    ratio = equal_error_ratio([b["N"] for b in rem], [b["error"] for b in rem], [r["N"] for r in rows],
                              [r["error"] for r in rows])
    np.testing.assert_allclose([r["particle_ratio"] for r in rows], ratio, rtol=1e-9)
    assert np.all(ratio > 1)
    for r in rows:
        c = r["cost"]
        assert c["steps"] == r["steps"] == len(c["N"]) and len(c["so_iterations"]) == -(-r["steps"] // 10)
        assert c["t_reorganized"][0] == 0.0 and all(k >= 1 for k in c["so_iterations"])
        assert r["N"] == max(r["N_initial"], max(c["N"]))                      # N_max
    for name in ("fig46", "fig47", "fig412"):
        assert (tmp_path / f"burgers_quick_{name}.png").stat().st_size > 0
    burgers = benchmark("burgers")
    page = (tmp_path / "burgers_quick.md").read_text()
    assert page == burgers.report(data)
    assert f"| fitted order, adaptive | {data['fig47']['orders']['adaptive']:.2f} | 2 |" in page
    figures = re.findall(r"!\[[^]]*\]\(([^)]+)\)", page)
    assert figures == [f"burgers_quick_{name}.png" for name in ("fig47", "fig412", "fig46")]


def test_five_spot_benchmark_and_cli_quick(tmp_path, capsys):
    """The five-spot benchmark and `arpy run five-spot` at quick sizes (the physics is tested in
    test_five_spot.py): the injection well holds f = 1 (the largest value at every snapshot),
    f stays in [-0.05, 1], the snapshots' particle numbers are those of the N(t) series.  The
    Markdown page is the one report() makes from the JSON, and shows the figure."""
    import re

    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "five_spot.py"), "--quick", "--out",
                          str(tmp_path)], check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "five_spot_quick.json").read_text())
    assert "saturation range" in out
    assert data["N_max"] > data["N_initial"] and -0.05 <= data["f_min"] and data["f_max"] <= 1.0
    assert data["degenerate_max"] == 0
    t_n, n = np.array(data["t"]), np.array(data["n"])
    assert len(data["snapshots"]) == 3 and data["snapshots"]["0"]["N"] == data["N_initial"] == n[0]
    for t, shot in data["snapshots"].items():            # taken at the first step ending at or after t
        assert shot["N"] == n[np.argmax(t_n >= float(t) - 1e-12)]
        assert shot["f_max"] == 1.0 and shot["f_min"] >= -0.05
    assert data["n"][-1] == data["N"]
    assert (tmp_path / "five_spot_quick.png").stat().st_size > 0
    five_spot = benchmark("five_spot")
    page = (tmp_path / "five_spot_quick.md").read_text()
    assert page == five_spot.report(data)
    assert f"| particles at t = 0 | {data['N_initial']} | 373 |" in page
    assert re.findall(r"!\[[^]]*\]\(([^)]+)\)", page) == ["five_spot_quick.png"]
    assert main(["run", "five-spot", "--T", "0.001", "--quiet", "--out", str(tmp_path)]) == 0
    assert "saturation range" in capsys.readouterr().out
    for name in ("five_spot.png", "five_spot.npz", "five_spot_particles.vtu"):
        assert (tmp_path / "five-spot" / name).stat().st_size > 0


def test_surface_benchmark_and_cli_quick(tmp_path, capsys):
    """The surface benchmark and `arpy run bud-surface` at quick sizes (the self-organization
    in the band is tested in test_surface.py): the bud converges with N* neighbours inside
    (counted by cKDTree in the benchmark), D_p <= D0; the lists' pair counts equal
    cKDTree's on the same distributions, rebuilt here, whose span is the row's lambda.  The
    Markdown page is the one report() makes from the JSON, and shows the figures."""
    import re

    from arpy.distributions import bud_benchmark

    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "surface.py"), "--quick", "--out",
                          str(tmp_path)], check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "surface_quick.json").read_text())
    bud = data["bud"][0]
    assert bud["converged"] and bud["interior_min_neighbors"] >= bud["n_star"] == 20
    assert bud["interior_fraction"] > 0.5 and bud["D_max"] <= bud["D0"] * (1 + 1e-12) and bud["N"] > 1000
    lists = data["lists"]
    assert all(r["same_pairs"] for r in lists) and len(lists) >= 2
    for r in lists:
        x, rc, b = bud_benchmark(r["h0"], r["lam_target"], seed=0)
        assert len(x) == r["n"] and r["lam"] == pytest.approx(rc.max() / rc.min(), rel=1e-12)
        assert r["lam"] == pytest.approx(max(r["lam_target"], 3.0 / b.neck_radius), rel=1e-6)
        assert r["pairs"] == kdtree_pairs(x, rc)[0].size
    assert lists[-1]["n"] > lists[0]["n"]
    assert "break-even lambda, h0 = 0.45" in out and set(data["break_even_lambda"]) == {"0.45"}
    for name in ("surface_quick_fig410.png", "surface_quick_fig9.png"):
        assert (tmp_path / name).stat().st_size > 0
    surface = benchmark("surface")
    page = (tmp_path / "surface_quick.md").read_text()
    assert page == surface.report(data)
    assert f"| {bud['N_initial']} | {bud['N']} | 27500 |" in page
    assert re.findall(r"!\[[^]]*\]\(([^)]+)\)", page) == ["surface_quick_fig410.png", "surface_quick_fig9.png"]
    assert main(["run", "bud-surface", "--D0", "0.5", "--quiet", "--out", str(tmp_path)]) == 0
    assert "neighbours >= 20" in capsys.readouterr().out
    for name in ("bud_surface.png", "bud_L0.4.npz", "bud_L0.4_particles.vtu"):
        assert (tmp_path / "bud-surface" / name).stat().st_size > 0


def test_manufactured_benchmark_and_cli_quick(tmp_path, capsys):
    """The manufactured-solution benchmark and `arpy run manufactured` at quick sizes (the orders are
    tested over seeds in test_pde.py): errors far below the fields' variation (0.4) that fall from the
    coarser run to the finer, every stencil valid, the page the one report() makes from the JSON."""
    import re

    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "manufactured.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    data = json.loads((tmp_path / "manufactured_quick.json").read_text())
    runs = data["runs"]["mixed"]["1"]
    assert [r["D0"] for r in runs] == [0.1, 0.07] and runs[1]["N"] > runs[0]["N"]
    for name in ("u", "v"):
        assert runs[0]["rms"][name] < 1e-3 and runs[1]["rms"][name] < runs[0]["rms"][name]
    assert all(r["degenerate"] == 0 for r in runs)
    page = (tmp_path / "manufactured_quick.md").read_text()
    assert page == benchmark("manufactured").report(data)
    assert re.findall(r"!\[[^]]*\]\(([^)]+)\)", page) == ["manufactured_quick.png"]
    assert main(["run", "manufactured", "--D0", "0.12", "--T", "0.05", "--walls", "dirichlet", "--quiet",
                 "--out", str(tmp_path)]) == 0
    assert "u rms" in capsys.readouterr().out
    for name in ("manufactured.png", "manufactured.npz", "manufactured_particles.vtu"):
        assert (tmp_path / "manufactured" / name).stat().st_size > 0


def test_monitor_study_quick(tmp_path):
    """The Eq. 2.8 study at quick sizes: arpy's grading (Eq. 2.9, implicit reading) puts D_p at the
    pulse's peak within 10 % of the implicit reading computed independently on the continuous
    monitor (a polar grid around the peak); the explicit reading there is the smallest D~ of the
    pulse, proportional to D0 (slope 1 to 1e-3); the page is the one report() makes from the JSON."""
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "monitor_study.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    data = json.loads((tmp_path / "monitor_study_quick.json").read_text())
    for r in data["pulse"]:
        assert r["converged"] and abs(r["D_peak"] / r["implicit"] - 1) < 0.1, r
        assert r["explicit"] <= r["implicit"] * (1 + 1e-12)
    assert abs(data["slopes"]["pulse_explicit"] - 1) < 1e-3
    assert data["slopes"]["pulse_implicit"] < 0.8
    blob = {r["reading"]: r for r in data["blob"]}         # Fig. 4.2's set: the explicit ball floods it
    assert blob["explicit"]["N"] > 2 * blob["implicit"]["N"]
    assert blob["explicit"]["D_median"] < 1.001 * blob["explicit"]["D_min"]   # nearly uniform at the finest D
    assert blob["explicit"]["D_median"] < blob["implicit"]["D_median"]
    assert [r["reading"] for r in data["simulations"]] == ["implicit"] and data["simulations"][0]["error"] < 0.01
    assert (tmp_path / "monitor_study_quick.md").read_text() == benchmark("monitor_study").report(data)


def test_stencil_rule_quick(tmp_path):
    """The stencil-rule comparison at quick sizes: both rules run Figs. 4.1-4.3 on the same sets; on
    Fig. 4.1 arpy's repair leaves no row failing, the paper's rule no more than it found; the page is
    the one report() makes from the JSON."""
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "stencil_rule.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    data = json.loads((tmp_path / "stencil_rule_quick.json").read_text())
    rep, dis = data["fig41"]["repair"], data["fig41"]["displace"]
    assert sum(rep["failed_before"]) > 0 and sum(rep["failed"]) == 0 and sum(rep["displaced"]) == 0
    # the paper's rule leaves the rows with too few old sources (no displacement fixes them)
    assert all(a <= b for a, b in zip(dis["failed"], dis["failed_before"])) and sum(dis["failed_before"]) > 0
    # the same first sets; the paper's rule also checks the new set's own stencils
    assert rep["failed_before"][0] <= dis["failed_before"][0]
    for rule in ("repair", "displace"):
        assert all(r["error"] < 0.05 for r in data["fig42"][rule]["rows"] + data["fig43"][rule])
    page = (tmp_path / "stencil_rule_quick.md").read_text()
    assert page == benchmark("stencil_rule").report(data)


def test_verlet_options_quick(tmp_path):
    """The Verlet-list options at quick sizes: the direct full list has the expansion's rows, the
    ghost-ghost filter drops exactly the ghost pairs within one halo (kept = all - dropped, at most the
    ghost-ghost pairs); the page is the one report() makes from the JSON."""
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "verlet_options.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    data = json.loads((tmp_path / "verlet_options_quick.json").read_text())
    assert all(r["same_rows"] for r in data["full"]) and len(data["full"]) == 4
    for r in data["ghosts"]:
        assert r["pairs"] - r["ghost_ghost_pairs"] <= r["kept_pairs"] < r["pairs"]
    assert (tmp_path / "verlet_options_quick.md").read_text() == benchmark("verlet_options").report(data)


def test_plot_particles_names_the_colour_bar_it_is_given():
    """plot_particles labels the colour bar of values with ``label`` (none without it, never a guessed "f")
    and that of D_p with D_p."""
    from types import SimpleNamespace

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from arpy.plotting import plot_particles

    x = np.random.default_rng(0).random((50, 2))
    ps = SimpleNamespace(x=x, D=np.linspace(0.01, 0.02, 50))
    for kwargs, label in ((dict(color=x[:, 0], label="v (m/s)"), "v (m/s)"), (dict(color=x[:, 0]), ""),
                          ({}, "$D_p$")):
        ax = plot_particles(ps, circles=0, **kwargs)
        assert ax.figure.axes[-1].get_ylabel() == label
        plt.close(ax.figure)


def test_consistency_laplacian_scale_is_the_largest_laplacian_of_the_front():
    """The scale of consistency's Laplacian errors is max |lap f| of the tanh front: against the exact
    Laplacian on a radius finer by 1000 (the front is radial), to 0.1 %."""
    from arpy import fields
    from arpy.cases.convergence import _field, _laplacian_scale

    r = np.linspace(0.0, np.sqrt(2.0), 1_000_001)
    exact = np.abs(fields.tanh_front_laplacian(np.stack([r, 0 * r], 1), 0.01)).max()
    assert _laplacian_scale(_field("tanh", 0.01)) == pytest.approx(exact, rel=1e-3)


def test_auto_calibration_benchmark_quick(tmp_path):
    """benchmarks/auto_calibration.py at its quick size: every set's statistics are auto_terms' of the set
    (rebuilt here from the benchmark's generator) and its model times auto_work's, auto's recorded choice
    is the documented comparison of them, the three methods found the same rows, and the page is report()
    of the JSON."""
    import arpy
    from arpy.lists.auto import auto_terms, auto_work

    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "auto_calibration.py"), "--quick", "--out",
                    str(tmp_path)], check=True, capture_output=True, text=True)
    data = json.loads((tmp_path / "auto_calibration_quick.json").read_text())
    bench = benchmark("auto_calibration")
    assert {r["kind"] for r in data["rows"]} == set(bench.KINDS) and {r["d"] for r in data["rows"]} == {2, 3}
    for r in data["rows"]:
        x, rc = bench.make_set(r["kind"], r["d"], r["n"], r["span"])
        assert r["terms"] == list(auto_terms(x, rc)), r
        assert [r["model_cell"], r["model_ar"]] == list(auto_work(x, rc)), r
        assert r["choice"] == ("ar" if r["model_cell"] > arpy.AUTO_AR_WORK * r["model_ar"] else "cell")
        assert r["pairs"] == kdtree_pairs(x, rc)[0].size
        for t in data["meta"]["threads"]:
            assert r[f"t{t}"]["same_rows"] and r[f"t{t}"]["auto"] > 0
    assert (tmp_path / "auto_calibration_quick.md").read_text() == bench.report(data)


def test_auto_rules_benchmark_quick(tmp_path):
    """benchmarks/auto_rules.py at its quick size: every set has its rule's mean number of neighbours (within
    boundary effects), its statistics are auto_terms' of the set under its rule, auto's recorded choice is
    the documented comparison of auto_work's times, the three methods found the same rows and their pairs
    are brute force's, and the page is report() of the JSON."""
    import arpy
    from arpy.lists.auto import auto_terms, auto_work
    from arpy.reference import brute_force_pairs

    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "auto_rules.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    data = json.loads((tmp_path / "auto_rules_quick.json").read_text())
    bench = benchmark("auto_rules")
    assert {(r["rule"], r["kind"], r["d"]) for r in data["rows"]} == {
        (rule, kind, d) for rule in ("sum", "max") for kind in bench.KINDS for d in (2, 3)}
    for r in data["rows"]:
        x, rc = bench.rule_set(r["rule"], r["kind"], r["d"], r["n"], r["span"])
        assert r["terms"] == list(auto_terms(x, rc, rule=r["rule"])), r
        assert [r["model_cell"], r["model_ar"]] == list(auto_work(x, rc, rule=r["rule"])), r
        assert r["choice"] == ("ar" if r["model_cell"] > arpy.AUTO_AR_WORK * r["model_ar"] else "cell")
        assert r["pairs"] == brute_force_pairs(x, rc, rule=r["rule"])[0].size
        assert 0.6 * bench.NEIGHBOURS[r["rule"]] < 2 * r["pairs"] / r["n"] <= 1.05 * bench.NEIGHBOURS[r["rule"]], r
        for t in data["meta"]["threads"]:
            assert r[f"t{t}"]["same_rows"] and r[f"t{t}"]["auto"] > 0
    assert (tmp_path / "auto_rules_quick.md").read_text() == bench.report(data)


def test_peers_benchmark_quick(tmp_path):
    """benchmarks/peers.py at its quick size with cKDTree's query_pairs as the one peer: each measurement
    in its own process, the pairs of both equal to an independent count, arpy's sum rule used only when
    neighbor_list takes rule=, and the page is report() of the JSON."""
    import inspect

    import arpy

    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "peers.py"), "--quick", "--peers", "kdtree_pairs",
                    "--out", str(tmp_path)], check=True, capture_output=True, text=True)
    data = json.loads((tmp_path / "peers_quick.json").read_text())
    peers = benchmark("peers")
    sum_rule = "rule" in inspect.signature(arpy.neighbor_list).parameters
    assert data["meta"]["arpy_sum_rule"] == sum_rule
    assert [(r["rule"], r["domain"]) for r in data["rows"]] == [("min", "periodic"), ("sum", "periodic")]
    for r in data["rows"]:
        x, rad = peers.make_case(r["n"], r["d"], r["rule"])
        d = x[:, None, :] - x[None, :, :]
        d -= np.round(d)                                            # (minimum image in the unit box)
        reach = rad[:, None] if r["rule"] == "min" else rad[:, None] + rad[None, :]
        expected = int(np.count_nonzero(np.triu((d ** 2).sum(-1) <= reach ** 2, 1)))
        want = {"kdtree_pairs"} | ({"arpy"} if r["rule"] == "min" or sum_rule else set())
        assert set(r["results"]) == want
        for m in r["results"].values():
            assert m["pairs"] == expected and m["digest"] == r["reference"] and m["seconds"] > 0
    page = (tmp_path / "peers_quick.md").read_text()
    assert page == peers.report(data)
    assert sum_rule or "arpy sum rule: not available in this build" in page
