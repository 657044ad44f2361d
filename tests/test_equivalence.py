"""benchmarks/equivalence.py compares two records value by value: it finds a changed bit in a JSON
number, an npz array or a printed line, and skips only wall times and values that differ between two
records of the same build."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import equivalence  # noqa: E402

sys.path.pop(0)


def write_record(root: Path, error: float, wall: float, f: np.ndarray, line: str, jitter: float = 0.0) -> Path:
    (root / "bench").mkdir(parents=True)
    (root / "bench" / "case.json").write_text(json.dumps({"rows": [{"error": error, "n": 12, "wall_s": wall,
                                                                   "other": 1.0 + jitter}]}))
    np.savez(root / "bench" / "case.npz", f=f)
    (root / "run_case.log").write_text(f"{line}\n  done in {wall:.1f} s\n")
    return root


def test_compare_finds_every_changed_bit_and_skips_noise(tmp_path, capsys):
    f = np.linspace(0.0, 1.0, 7)
    before = write_record(tmp_path / "a", 1e-3, 0.5, f, "N = 12")
    noise = write_record(tmp_path / "b", 1e-3, 0.7, f, "N = 12", jitter=1e-9)      # same build, other run
    same = write_record(tmp_path / "c", 1e-3, 3.0, f, "N = 12")
    assert equivalence.compare(before, same, noise) == 0
    g = f.copy()
    g[3] = np.nextafter(g[3], 2.0)                                                  # one bit
    for name, record in (("error", (np.nextafter(1e-3, 1.0), 0.5, f, "N = 12")), ("array", (1e-3, 0.5, g, "N = 12")),
                         ("line", (1e-3, 0.5, f, "N = 13"))):
        changed = write_record(tmp_path / name, *record)
        assert equivalence.compare(before, changed, noise) == 1, name
    out = capsys.readouterr().out
    assert "bench/case.json:/rows[0]/error" in out and "bench/case.npz:f" in out and "run_case.log:0" in out
    # without a noise record, only the named timings are skipped: "other" counts
    assert equivalence.compare(before, noise, None) == 1
