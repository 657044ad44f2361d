"""The results pages in benchmarks/results/*.md are what benchmarks/report.py makes from the
committed JSON beside them: regenerated here and compared, so the pages cannot drift."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_results_pages_regenerate_identically_from_their_json():
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "report.py"), "--check"], capture_output=True,
                         text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_every_results_json_has_a_page():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import report
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    stems = {p.stem for p in (ROOT / "benchmarks" / "results").glob("*.json")}
    assert stems == set(report.PAGES)
    assert {p.stem for p in (ROOT / "benchmarks" / "results").glob("*.md")} == stems
