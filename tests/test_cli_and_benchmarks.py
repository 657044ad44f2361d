"""The command line and the benchmark scripts run end to end (small sizes)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from arpy.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_demo_runs_and_all_methods_agree(capsys):
    assert main(["demo", "--n", "3000", "--lam", "20", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "cell (uniform cell list)" in out and "brute (all pairs)" in out
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
