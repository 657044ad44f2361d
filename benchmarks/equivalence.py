"""Before/after equality of arpy's outputs: every benchmark's ``--quick`` mode and ``arpy run`` for
each case at a small size, run by two builds (e.g. the current tree and an older commit built with
``install-rev``), compared value by value.

    python benchmarks/equivalence.py record OUT [--python PY] [--tree DIR]
    python benchmarks/equivalence.py compare BEFORE AFTER [--noise BEFORE2]

``record`` runs the outputs of the tree DIR (default: this one) with the interpreter PY (default: this
one) into OUT: the JSON of each benchmark, the ``.npz`` and ``.vtu`` files of each case and the printed
summaries. ``compare`` reads two records and reports every value that differs. Wall times, dates and
versions differ from run to run: a value counts as noise only if it differs between two records of the
same build (``--noise``, a second record of BEFORE), and keys named like timings or memory (``NOISE_KEYS``)
are skipped. Everything else must be equal to the last bit. Exit status 1 on any
difference.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np

HERE = Path(__file__).resolve().parent

#: The benchmarks, each run with ``--quick``.
BENCHMARKS = ("cell_lists", "ar_cell_lists", "dcpse", "self_organization", "simulation", "burgers",
              "five_spot", "surface", "manufactured", "monitor_study")

#: ``arpy run`` at small sizes: every case (and both monitors where a case takes them), each option given
#: explicitly so that a change of a default does not change the run.
RUNS = {
    "pulse2d": ["pulse", "--d", "2", "--pe", "1000", "--D0", "0.2", "--T", "0.05", "--k", "10", "--remeshed", "8",
                "--mass-every", "10", "--monitor", "gradient", "--reach", "1", "--seed", "1"],
    "pulse2d_fourth": ["pulse", "--d", "2", "--pe", "1000", "--D0", "0.3", "--T", "0.02", "--k", "10",
                       "--remeshed", "0", "--mass-every", "10", "--monitor", "fourth", "--reach", "1", "--seed", "2"],
    "pulse3d": ["pulse", "--d", "3", "--pe", "100", "--D0", "1.0", "--T", "0.02", "--k", "10", "--remeshed", "6",
                "--mass-every", "10", "--monitor", "gradient", "--reach", "1", "--seed", "1"],
    "advection": ["advection", "--D0", "0.25", "--T", "0.1", "--k", "4", "--monitor", "gradient", "--reach", "1",
                  "--seed", "1"],
    "advection_fourth": ["advection", "--D0", "0.2", "--T", "0.05", "--k", "2", "--monitor", "fourth", "--reach",
                         "1.2", "--seed", "3"],
    "burgers": ["burgers", "--re", "100", "--D0", "0.2", "--T", "0.01", "--k", "10", "--remeshed", "8",
                "--reach", "1", "--seed", "1"],
    "five-spot": ["five-spot", "--mu", "0.5", "--nu", "0.01", "--D0", "0.2", "--T", "0.002", "--k", "10",
                  "--reach", "1", "--seed", "1"],
    "consistency": ["consistency", "--field", "tanh", "--D0-end", "0.3", "--monitor", "gradient", "--reach", "1",
                    "--seed", "1"],
    "consistency_blob": ["consistency", "--field", "blob", "--D0-end", "0.15", "--monitor", "fourth", "--reach", "1",
                         "--seed", "1"],
    "bud-surface": ["bud-surface", "--L", "0.45", "--D0", "0.35", "--seed", "1"],
    "manufactured": ["manufactured", "--D0", "0.12", "0.1", "--walls", "mixed", "--T", "0.1", "--k", "2", "--seed", "1"],
}

#: Keys (any component of a value's path) whose values are wall times, speeds, memory, dates or versions.
NOISE_KEYS = re.compile(r"wall_s|seconds|date|python|numpy|machine|t_\w+|history_t_\w+|\w*ns_per_\w+|us_\w+|ns_\w+"
                        r"|apply_GBps|kd_(ball|best|pairs)|(uniform|ar)_(build|total|list)|\w*speedup\w*|peak_\w+"
                        r"|\w*memory\w*|break_even_lambda|uniform_over_ar|kd_over_ar|share_\w+|cost")
#: In printed summaries: durations ("in 1.2 s", "(3 s)"), paths, whether a speed target is "met",
#: and the one-decimal numbers of the benchmarks' printed tables (their wall-time columns; every value
#: of those tables is also in the JSON, compared exactly).
NOISE_TEXT = re.compile(r"\d+(\.\d+)?(e[-+]?\d+)? ?(s|ms)\b|wrote \S+|\b(NOT )?met\b|(?<![\d.e-])\d+\.\d(?![\d.e])")


def record(out: Path, python: str, tree: Path, only: list[str] | None = None) -> None:
    """Runs the benchmarks and cases of ``tree`` with ``python`` into ``out`` (``only``: these names)."""
    out.mkdir(parents=True, exist_ok=True)
    for name in BENCHMARKS:
        if only and name not in only:
            continue
        t0 = time.perf_counter()
        run = subprocess.run([python, str(tree / "benchmarks" / f"{name}.py"), "--quick", "--out",
                              str(out / "bench")], capture_output=True, text=True, cwd=tree)
        (out / f"bench_{name}.log").write_text(run.stdout + run.stderr)
        print(f"  benchmark {name:18s} exit {run.returncode}  {time.perf_counter() - t0:6.1f} s", flush=True)
    for name, argv in RUNS.items():
        if only and name not in only:
            continue
        t0 = time.perf_counter()
        run = subprocess.run([python, "-m", "arpy", "run", *argv, "--quiet", "--out", str(out / "run" / name)],
                             capture_output=True, text=True, cwd=tree)
        (out / f"run_{name}.log").write_text(run.stdout + run.stderr)
        print(f"  arpy run {name:19s} exit {run.returncode}  {time.perf_counter() - t0:6.1f} s", flush=True)


def _leaves(value: Any, path: str = "") -> Iterator[tuple[str, Any]]:
    """(path, value) of every leaf of a JSON document."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _leaves(v, f"{path}/{k}")
    elif isinstance(value, list):
        for k, v in enumerate(value):
            yield from _leaves(v, f"{path}[{k}]")
    else:
        yield path, value


def _contents(root: Path) -> dict[str, Any]:
    """Every comparable value of a record: JSON leaves, npz arrays, the points and arrays of vtu files,
    vtk and log text lines."""
    values: dict[str, Any] = {}
    for path in sorted(root.rglob("*")):
        rel = str(path.relative_to(root))
        if path.suffix == ".json":
            values.update({f"{rel}:{k}": v for k, v in _leaves(json.loads(path.read_text()))})
        elif path.suffix == ".npz":
            with np.load(path) as data:
                values.update({f"{rel}:{k}": data[k] for k in data.files})
        elif path.suffix == ".vtu":
            import meshio

            mesh = meshio.read(path)
            values.update({f"{rel}:points": mesh.points, **{f"{rel}:{k}": v for k, v in mesh.point_data.items()}})
        elif path.suffix in (".vtk", ".log"):
            lines = path.read_text().splitlines()
            if path.suffix == ".log":
                lines = [NOISE_TEXT.sub("<t>", line) for line in lines if "%|" not in line]
            values.update({f"{rel}:{k}": line for k, line in enumerate(lines)})
    return values


def _equal(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()
    return type(a) is type(b) and (a == b or (a != a and b != b))


def compare(before: Path, after: Path, noise: Path | None) -> int:
    """Prints every difference between two records; returns the number of differences."""
    a, b = _contents(before), _contents(after)
    skip = {k for k in a if ".log:" not in k and any(NOISE_KEYS.fullmatch(c) for c in re.split(r"[/:\[\]]+", k))}
    if noise is not None:
        n = _contents(noise)
        skip |= {k for k in a if k not in n or not _equal(a[k], n[k])}
    missing = sorted(set(a) ^ set(b))
    differ = sorted(k for k in set(a) & set(b) if k not in skip and not _equal(a[k], b[k]))
    for k in missing:
        print(f"only in {'before' if k in a else 'after'}: {k}")
    for k in differ:
        print(f"differs: {k}: {str(a[k])[:120]!r} -> {str(b[k])[:120]!r}")
    compared = len(set(a) & set(b)) - len(skip & set(b))
    print(f"{compared} values compared ({sum(np.asarray(a[k]).size for k in set(a) & set(b) if k not in skip)} "
          f"numbers and lines), {len(skip)} skipped as noise: {len(differ)} differ, {len(missing)} missing")
    return len(differ) + len(missing)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="run the outputs into a folder")
    rec.add_argument("out", type=Path)
    rec.add_argument("--python", default=sys.executable, help="the interpreter whose arpy runs (default: this)")
    rec.add_argument("--tree", type=Path, default=HERE.parent, help="the tree whose benchmarks run (default: this)")
    rec.add_argument("--only", nargs="+", choices=[*BENCHMARKS, *RUNS], help="these benchmarks and runs only")
    cmp = sub.add_parser("compare", help="compare two records")
    cmp.add_argument("before", type=Path)
    cmp.add_argument("after", type=Path)
    cmp.add_argument("--noise", type=Path, help="a second record of BEFORE: values that differ there are skipped")
    args = parser.parse_args(argv)
    if args.command == "record":
        record(args.out, args.python, args.tree.resolve(), args.only)
        return 0
    return 1 if compare(args.before, args.after, args.noise) else 0


if __name__ == "__main__":
    sys.exit(main())
