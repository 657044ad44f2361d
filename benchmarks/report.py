"""The results pages, written from the committed JSON so that they cannot drift.

Each benchmark script ``benchmarks/<script>.py`` has a function ``report(res: dict) -> str``
that turns its JSON result into a Markdown page.  This script calls them::

    python benchmarks/report.py            # (re)write every results/<stem>.md from results/<stem>.json
    python benchmarks/report.py --check    # exit 1 if a committed page differs from its JSON (tests)

A benchmark run writes its own page the same way (``arpy._bench.write_page``), right after its JSON.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

from arpy._bench import write_page

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"

#: page stem (``results/<stem>.json`` -> ``results/<stem>.md``) -> the script whose ``report`` renders it
PAGES = {
    "cell_lists_2d": "cell_lists",
    "ar_cell_lists": "ar_cell_lists",
    "verlet_options": "verlet_options",
    "dcpse": "dcpse",
    "self_organization": "self_organization",
    "simulation": "simulation",
    "burgers": "burgers",
    "five_spot": "five_spot",
    "surface": "surface",
    "threads": "threads",
    "cache_order": "cache_order",
    "distributed": "distributed",
    "manufactured": "manufactured",
    "monitor_study": "monitor_study",
    "stencil_rule": "stencil_rule",
    "rules": "rules",
    "auto_calibration": "auto_calibration",
    "auto_rules": "auto_rules",
    "peers": "peers",
    "stability": "stability",
}


def script(name: str) -> ModuleType:
    """The benchmark script ``benchmarks/<name>.py`` as a module (not run)."""
    spec = importlib.util.spec_from_file_location(f"arpy_benchmark_{name}", HERE / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def render(stem: str) -> str:
    """The Markdown page of ``results/<stem>.json``."""
    return script(PAGES[stem]).report(json.loads((RESULTS / f"{stem}.json").read_text()))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="compare instead of writing; exit 1 on a difference")
    parser.add_argument("stems", nargs="*", help=f"pages (default: all of {', '.join(PAGES)})")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.stems) - set(PAGES))
    if unknown:
        parser.error(f"no results page {', '.join(unknown)}")
    stale = []
    for stem in args.stems or PAGES:
        if args.check:
            page = RESULTS / f"{stem}.md"
            if not page.exists() or page.read_text() != render(stem):
                stale.append(stem)
        else:
            print(f"wrote {write_page(RESULTS, stem, script(PAGES[stem]).report)}")
    if stale:
        print("results pages differ from their JSON (run python benchmarks/report.py): " + ", ".join(stale))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
