"""Small timing and comparison helpers shared by the CLI demo and benchmarks/."""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

__all__ = ["benchmark_args", "best_time", "kdtree_pairs", "kdtree_ball_pairs", "peak_memory_growth"]


def benchmark_args(doc: str, argv: list[str] | None, out: Path,
                   extra: Callable[[argparse.ArgumentParser], None] | None = None) -> argparse.Namespace:
    """The command line shared by benchmarks/*.py: ``--quick``, ``--out`` (created) and
    the options ``extra`` adds; matplotlib is switched to its off-screen backend."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small sizes only (for tests)")
    parser.add_argument("--out", type=Path, default=out, help="output folder for JSON and PNG")
    if extra is not None:
        extra(parser)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    return args


def best_time(fn: Callable[[], object], repeat: int = 3) -> tuple[float, object]:
    """Run ``fn`` ``repeat`` times; return (shortest wall time in s, last result)."""
    best, out = np.inf, None
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def _min_rule(x: np.ndarray, rc: np.ndarray, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d2 = ((x[j] - x[i]) ** 2).sum(axis=1)
    rm = np.minimum(rc[i], rc[j])
    keep = d2 <= rm * rm
    return i[keep], j[keep]


def kdtree_pairs(x: np.ndarray, rc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs under the min rule with ``scipy.spatial.cKDTree.query_pairs`` at the largest cutoff.

    With one cutoff this is a single ``query_pairs`` call; with several, the
    candidates are filtered by the min rule afterwards.  Returns (i, j), i < j, unsorted.
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(x)
    pairs = tree.query_pairs(float(rc.max()), output_type="ndarray")
    i, j = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)
    if rc.min() == rc.max():
        return i, j
    return _min_rule(x, rc, i, j)


def kdtree_ball_pairs(x: np.ndarray, rc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs under the min rule with ``cKDTree.query_ball_point`` using each particle's own radius.

    Each particle gathers the points within its own cutoff; a pair is kept
    once (i < j) and only if it also lies within the other particle's cutoff.
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(x)
    lists = tree.query_ball_point(x, rc, return_sorted=False)
    counts = np.fromiter((len(v) for v in lists), dtype=np.int64, count=len(lists))
    i = np.repeat(np.arange(len(lists), dtype=np.int64), counts)
    j = np.fromiter((q for v in lists for q in v), dtype=np.int64, count=int(counts.sum()))
    keep = j > i
    return _min_rule(x, rc, i[keep], j[keep])


def peak_memory_growth(setup: str, run: str) -> int:
    """Peak resident-memory growth (bytes) while ``run`` executes, in a fresh Python process.

    ``setup`` (imports, data) runs first; then the high-water mark is reset
    through /proc/self/clear_refs (Linux) so earlier peaks do not hide the
    one of ``run``.
    """
    code = (
        f"{setup}\n"
        "def _status(key):\n"
        "    for line in open('/proc/self/status'):\n"
        "        if line.startswith(key):\n"
        "            return int(line.split()[1]) * 1024\n"
        "open('/proc/self/clear_refs', 'w').write('5')\n"
        "_before = _status('VmRSS:')\n"
        f"{run}\n"
        "print(_status('VmHWM:') - _before)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return int(out.stdout.strip().splitlines()[-1])
