"""The command line and the benchmark scripts run end to end (small sizes)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from arpy.cli import main

ROOT = Path(__file__).resolve().parents[1]


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
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "cell_lists.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    data = json.loads((tmp_path / "cell_lists_2d_quick.json").read_text())
    assert all(r["same_pairs"] for r in data["rows"])
    assert {r["method"] for r in data["rows"]} >= {"arpy cell (sym)", "kd query_pairs", "kd ball_point"}
    assert (tmp_path / "cell_lists_2d_quick.png").stat().st_size > 0


def test_ar_cell_list_benchmark_quick(tmp_path):
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "ar_cell_lists.py"), "--quick", "--out",
                          str(tmp_path)], check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "ar_cell_lists_quick.json").read_text())
    rows = data["fig6"] + data["fig7"]
    assert all(r["same_pairs"] for r in rows)
    assert {r["lam"] for r in data["fig7"]} >= {1.0, 10.0, 1000.0}
    assert "break-even lambda" in out
    for name in ("ar_cell_lists_quick_fig6.png", "ar_cell_lists_quick_fig7.png"):
        assert (tmp_path / name).stat().st_size > 0


def test_dcpse_benchmark_quick(tmp_path):
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "dcpse.py"), "--quick", "--out", str(tmp_path)],
                         check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "dcpse_quick.json").read_text())
    assert all(r["max_rel_diff_vs_reference"] < 1e-10 for r in data["timing"])
    assert abs(data["convergence"]["2"]["orders"]["interpolation"] - 4) < 0.5
    assert "convergence orders" in out
    assert (tmp_path / "dcpse_quick.png").stat().st_size > 0


def test_self_organization_benchmark_quick(tmp_path):
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "self_organization.py"), "--quick", "--out",
                          str(tmp_path)], check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "self_organization_quick.json").read_text())
    assert "paper" in out and data["pulse"][0]["converged"]
    assert data["pulse"][0]["n"] > 400                     # 800 random particles: fused, then refined at the pulse
    assert all(r["energy_end"] < r["energy_start"] for r in data["fig23"])
    assert data["timing"][0]["converged"]
    for name in ("fig31", "fig23", "timing"):
        assert (tmp_path / f"self_organization_quick_{name}.png").stat().st_size > 0


def test_run_pulse_and_advection_write_outputs(tmp_path, capsys):
    assert main(["run", "pulse", "--D0", "0.16", "--T", "0.05", "--remeshed", "32", "--quiet", "--out",
                 str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "L-infinity error" in out and "remeshed particle method" in out
    for name in ("pulse.png", "pulse.npz", "pulse_particles.vtk"):
        assert (tmp_path / "pulse" / name).stat().st_size > 0
    data = np.load(tmp_path / "pulse" / "pulse.npz")
    assert data["x"].shape[0] == data["f"].shape[0] == data["D"].shape[0]
    assert np.abs(data["f"] - data["f_exact"]).max() < 0.05
    assert main(["run", "pulse", "--monitor", "fourth", "--D0", "0.4", "--T", "0.05", "--remeshed", "0", "--quiet",
                 "--out", str(tmp_path)]) == 0
    assert "D0 = 0.4, T = 0.05, monitor fourth" in capsys.readouterr().out
    data = np.load(tmp_path / "pulse" / "pulse.npz")
    assert np.abs(data["f"] - data["f_exact"]).max() < 0.05
    assert main(["run", "advection", "--D0", "0.25", "--T", "0.05", "--quiet", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "advection" / "advection_particles.vtk").stat().st_size > 0
    assert main(["run", "advection", "--monitor", "fourth", "--T", "0.05", "--quiet", "--out", str(tmp_path)]) == 0
    assert "D0 = 0.25, monitor fourth" in capsys.readouterr().out
    assert main(["run", "burgers", "--D0", "0.25", "--T", "0.01", "--remeshed", "32", "--quiet", "--out", str(tmp_path)]) == 0
    assert "pseudo-spectral" in capsys.readouterr().out
    for name in ("burgers.png", "burgers.npz", "burgers_particles.vtk"):
        assert (tmp_path / "burgers" / name).stat().st_size > 0
    assert main(["run", "consistency", "--field", "blob", "--monitor", "fourth", "--D0", "0.22", "--quiet", "--out",
                 str(tmp_path)]) == 0
    assert "blob of Sec. 4.2 at rest" in capsys.readouterr().out
    data = np.load(tmp_path / "consistency" / "consistency.npz")
    assert data["N"].size == 2 and np.all(data["p99_interp"] <= data["err_interp"])   # D0 = 0.2375, 0.2256
    out = subprocess.run([sys.executable, "-m", "arpy", "run", "--help"], capture_output=True, text=True,
                         check=True).stdout
    assert "pulse" in out and "advection" in out and "consistency" in out and "burgers" in out


def test_simulation_benchmark_quick(tmp_path):
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "simulation.py"), "--quick", "--out",
                          str(tmp_path)], check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "simulation_quick.json").read_text())
    assert "fitted orders" in out and "equal error" in out
    for key, monitor in (("fig41", "gradient"), ("fig41b", "fourth")):          # §4.1 with both monitors
        rows = data[key]["rows"]
        assert data[key]["monitor"] == monitor and len(rows) == 2 and rows[1]["N"] > rows[0]["N"]
        assert all(r["median_interp"] <= r["p99_interp"] <= r["err_interp"] < 0.01 for r in rows)
    two, three = data["fig44"]["2d"], data["fig44"]["3d"]
    assert set(two["adaptive"]) == {"reach 1", "reach 2", "B.13, reach 1"}
    assert all(r["monitor"] == "fourth" for r in two["adaptive"]["B.13, reach 1"])
    # 3D: Eq. B.13 refines the peak to D0 (1 + 3 (Pe/2)^2)^(-1/4) = 0.108 D0, Eq. 2.8 to D0 / max|grad f| = 0.233 D0
    (b13,), (eq28,) = three["adaptive"]["B.13, reach 1"], three["adaptive"]["reach 1"]
    assert 0.1 * b13["D0"] < b13["D_min"] < 0.15 * b13["D0"] and eq28["D_min"] > 0.2 * eq28["D0"]
    pulse_rows = [r for rows in list(two["adaptive"].values()) + list(three["adaptive"].values()) for r in rows]
    assert data["fig42"]["monitor"] == "gradient" and data["fig42b"]["monitor"] == "fourth"
    for r in data["fig42"]["rows"] + data["fig42b"]["rows"] + pulse_rows:
        assert np.isfinite(r["error"]) and r["error"] < 0.1 and r["N"] > 0 and r["wall_s"] > 0
    assert two["remeshed"][0]["error"] > two["remeshed"][1]["error"]          # the baseline converges
    for key, rows in two["adaptive"].items():
        assert len(two["particle_ratio"][key]) == len(rows) and min(two["particle_ratio"][key]) > 1
        assert all(abs(m) < 0.05 for r in rows for m in r["mass_loss"])
    assert data["fig43"]["N_initial"] > 100
    for kind in ("gradient", "fourth"):                       # fig42i: the paper's monitor and Eq. B.13
        static = data["fig42i"][kind]["rows"]
        assert len(static) == 2 and static[1]["N"] > static[0]["N"]
        assert all(r["median_interp"] <= r["p99_interp"] <= r["err_interp"] < 0.01 and 0 < r["D_at_max"] <= r["D0"]
                   for r in static)
        assert sum(b["n"] for b in data["fig42i"][kind]["bands"]) == static[-1]["N"]
    for kind in ("gradient", "fourth"):                       # fig42h: the error after each re-organization
        hist = data["fig42h"][kind]
        assert len(hist["t"]) == 2 and abs(hist["max"][-1] - hist["error"]) < 1e-5    # RK4 paths: ~1e-6
        assert 0 < hist["t_90"] <= 0.2
    for name in ("fig41", "fig42", "fig42h", "fig42i", "fig43", "fig44", "fig45"):
        assert (tmp_path / f"simulation_quick_{name}.png").stat().st_size > 0


def test_burgers_benchmark_quick(tmp_path):
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "burgers.py"), "--quick", "--out", str(tmp_path)],
                         check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "burgers_quick.json").read_text())
    assert "fitted orders" in out and "cost split" in out
    assert data["fig46"]["N"] > 500 and data["fig46"]["scale_ratio"] >= 1
    rows = data["fig47"]["adaptive"]
    assert all(r["error"] < 1e-2 and r["particle_ratio"] > 1 for r in rows)
    for r in rows:
        c = r["cost"]
        assert abs(c["share_self_organization"] + c["share_dcpse_and_rest"] - 1) < 1e-12
        assert abs(sum(c["self_organization_split"].values()) - 1) < 1e-12
        assert all(v >= 0 for v in c["seconds"].values()) and c["steps"] == r["steps"]
    for name in ("fig46", "fig47", "fig412"):
        assert (tmp_path / f"burgers_quick_{name}.png").stat().st_size > 0


def test_five_spot_benchmark_and_cli_quick(tmp_path, capsys):
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "five_spot.py"), "--quick", "--out",
                          str(tmp_path)], check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "five_spot_quick.json").read_text())
    assert "the paper: 373 -> 7300" in out
    assert data["N_max"] > data["N_initial"] and -0.05 <= data["f_min"] and data["f_max"] <= 1.0
    assert len(data["snapshots"]) == 3 and (tmp_path / "five_spot_quick.png").stat().st_size > 0
    assert main(["run", "five-spot", "--T", "0.001", "--quiet", "--out", str(tmp_path)]) == 0
    assert "saturation range" in capsys.readouterr().out
    for name in ("five_spot.png", "five_spot.npz", "five_spot_particles.vtk"):
        assert (tmp_path / "five-spot" / name).stat().st_size > 0


def test_surface_benchmark_and_cli_quick(tmp_path, capsys):
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "surface.py"), "--quick", "--out",
                          str(tmp_path)], check=True, capture_output=True, text=True).stdout
    data = json.loads((tmp_path / "surface_quick.json").read_text())
    bud = data["bud"][0]
    assert bud["converged"] and bud["interior_min_neighbors"] >= bud["n_star"] == 20
    assert bud["paper_N"] == 2.75e4
    lists = data["lists"]
    assert all(r["same_pairs"] for r in lists) and len(lists) == 3
    assert lists[-1]["lam"] > 100 and lists[-1]["n"] > lists[0]["n"]
    assert "break-even lambda, h0 = 0.45" in out and "0.45" in data["break_even_lambda"]
    for name in ("surface_quick_fig410.png", "surface_quick_fig9.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert main(["run", "bud-surface", "--D0", "0.3", "--quiet", "--out", str(tmp_path)]) == 0
    assert "neighbours >= 20" in capsys.readouterr().out
    for name in ("bud_surface.png", "bud_L0.4.npz", "bud_L0.4_particles.vtk"):
        assert (tmp_path / "bud-surface" / name).stat().st_size > 0
