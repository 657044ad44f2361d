"""Small timing and comparison helpers shared by the CLI demo and benchmarks/."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence, TypeVar, cast

import numpy as np

__all__ = ["benchmark_args", "best_time", "break_even", "compare_lists", "kdtree_pairs", "kdtree_ball_pairs",
           "md_table", "peak_memory_growth", "run_info", "run_process_group", "span", "uniform_checks", "write_outputs",
           "write_page", "write_result"]

#: Uniform cell-list runs above this many distance checks are estimated, not run.
MAX_CHECKS_MEASURED = 3e9
#: cKDTree.query_pairs at the largest radius is run only below this many candidate pairs.
MAX_KD_PAIRS_CANDIDATES = 5e7


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


def run_info() -> dict:
    """The first entries of a benchmark's JSON: the machine and the Python version."""
    return {"machine": platform.platform(), "python": sys.version.split()[0]}


def write_result(out: Path, tag: str, result: dict, also: str, gap: bool = True) -> None:
    """Write a benchmark's ``result`` to ``out/<tag>.json`` and print that it did, naming
    ``also``, the other files written; ``gap``: after a blank line."""
    path = out / f"{tag}.json"
    path.write_text(json.dumps(result, indent=1))
    if gap:
        print()
    print(f"wrote {path}" + (f" and {also}" if also else ""))


def write_outputs(out: Path, tag: str, result: dict, plot: Callable[[dict, Path], None],
                  report: Callable[[dict], str]) -> None:
    """The outputs of a benchmark with one figure: ``out/<tag>.png`` (``plot(result, path)``), the JSON
    and the page (:func:`write_result`, :func:`write_page`)."""
    plot(result, out / f"{tag}.png")
    write_result(out, tag, result, f"{tag}.png", gap=False)
    print(f"wrote {write_page(out, tag, report)}")


_T = TypeVar("_T")


def md_table(header: list[str], rows: list[list]) -> list[str]:
    """The lines of a Markdown table: the header, the rule and one line per row (cells as str)."""
    return (["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
            + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows])


def span(values, fmt: Callable[[float], str]) -> str:
    """``"lo–hi"`` of the values printed by ``fmt`` (one value if both print alike)."""
    lo, hi = fmt(min(values)), fmt(max(values))
    return lo if lo == hi else f"{lo}–{hi}"


def write_page(out: Path, tag: str, report: Callable[[dict], str]) -> Path:
    """Write ``out/<tag>.md``, the results page that ``report`` makes from ``out/<tag>.json`` (as
    ``benchmarks/report.py`` writes the committed pages); returns its path."""
    page = out / f"{tag}.md"
    page.write_text(report(json.loads((out / f"{tag}.json").read_text())))
    return page


def best_time(fn: Callable[[], _T], repeat: int = 3) -> tuple[float, _T]:
    """Run ``fn`` ``repeat`` times; return (shortest wall time in s, last result)."""
    best, out = np.inf, None
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, cast(_T, out)         # (fn ran at least once)


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


#: Seconds a process group has to end after SIGTERM (an ``mpiexec`` ends its ranks) before SIGKILL.
KILL_GRACE = 5.0


@contextlib.contextmanager
def _terminate_as_exit() -> Iterator[None]:
    """While in the block (main thread only), SIGTERM raises SystemExit(143) instead of ending the
    process at once, so that the block's clean-up runs."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, frame: Any) -> None:
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _end_group(proc: subprocess.Popen) -> tuple[str, str]:
    """End the process group of ``proc`` (SIGTERM, then after :data:`KILL_GRACE` s SIGKILL to what is
    left of it); returns what it wrote to stdout and stderr."""
    def signal_group(sig: int) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, sig)

    signal_group(signal.SIGTERM)
    try:
        out, err = proc.communicate(timeout=KILL_GRACE)
    except subprocess.TimeoutExpired:
        signal_group(signal.SIGKILL)
        try:
            out, err = proc.communicate(timeout=KILL_GRACE)
        except subprocess.TimeoutExpired:             # (a process outside the group holds its output)
            proc.kill()
            out, err = "", ""
    else:
        signal_group(signal.SIGKILL)                  # (what is left of the group)
    return out or "", err or ""


def run_process_group(cmd: Sequence[str], timeout: float, **kwargs: Any) -> subprocess.CompletedProcess:
    """``subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, **kwargs)`` with ``cmd`` in
    a process group of its own (a new session), ended whole (SIGTERM, then SIGKILL) when the timeout
    passes or this process is interrupted or terminated: an ``mpiexec`` and its ranks are not left
    behind.  After the timeout, raises subprocess.TimeoutExpired with what ``cmd`` wrote."""
    proc = subprocess.Popen(list(cmd), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, **kwargs)
    with _terminate_as_exit():
        try:
            out, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            out, err = _end_group(proc)
            raise subprocess.TimeoutExpired(list(cmd), timeout, output=out, stderr=err) from None
        except BaseException:
            _end_group(proc)
            raise
    return subprocess.CompletedProcess(list(cmd), proc.returncode, out, err)


def uniform_checks(x: np.ndarray, rc: np.ndarray) -> float:
    """Distance checks of a half-shell uniform cell list with cell edge max(rc) (counted from occupancy)."""
    h = rc.max()
    ci = np.floor((x - x.min(axis=0)) / h).astype(np.int64)
    counts = np.zeros(tuple(ci.max(axis=0) + 1), np.float64)
    np.add.at(counts, tuple(ci.T), 1.0)
    padded = np.pad(counts, 1)
    stencil = np.zeros_like(counts)
    for off in np.ndindex(*([3] * x.shape[1])):
        stencil += padded[tuple(slice(o, o + s) for o, s in zip(off, counts.shape))]
    return float(0.5 * (counts * stencil).sum())


def _sorted_pairs(out) -> tuple[np.ndarray, np.ndarray]:
    from .lists.neighborlist import NeighborList

    if isinstance(out, NeighborList):
        return out.pairs()
    i, j = out
    a, b = np.minimum(i, j), np.maximum(i, j)
    order = np.lexsort((b, a))
    return a[order], b[order]


def compare_lists(x: np.ndarray, rc: np.ndarray, repeat: int, ns_per_check: list[float], memory: bool = False,
                  kd_pairs_max: float = MAX_KD_PAIRS_CANDIDATES) -> dict:
    """Time half Verlet lists of (x, rc) with AR cell lists, the uniform cell list and cKDTree.

    Returns a dict of wall times in s (best of ``repeat``): ``ar_build`` (the AR
    tree alone), ``ar_total`` (tree + list), ``uniform_build``,
    ``uniform_total``, ``kd_ball``, ``kd_pairs`` (None when skipped),
    ``kd_best``; ``pairs``; ``same_pairs`` (every method found the same pairs);
    ``ar_ns_per_particle``.  A uniform run that would make more than
    ``MAX_CHECKS_MEASURED`` distance checks is *estimated* (``uniform_estimated``)
    from the counted checks times the median cost per check measured so far
    (``ns_per_check`` collects it).  ``memory``: also the AR list's peak memory
    growth per particle (in a subprocess).  ``cKDTree.query_pairs`` at the largest cutoff runs only
    up to ``kd_pairs_max`` candidate pairs (the uniform list's distance checks).
    """
    from . import _bridge
    from ._codes import METHODS, STATUS
    from .lists.search import neighbor_list

    n = len(x)
    xc = np.ascontiguousarray(x, dtype=np.float64)          # (handed to the core without a copy)
    row: dict = {"n": n}

    def build(method: int):
        info = _bridge.build_only(xc, rc, method)
        if info != STATUS["OK"]:
            raise RuntimeError(f"arpy_build_only failed with info = {info}")

    row["ar_build"], _ = best_time(lambda: build(METHODS["ar"]), repeat)
    row["ar_total"], ar = best_time(lambda: neighbor_list(x, rc, method="ar"), repeat)
    reference = ar.pairs()
    row["pairs"] = int(reference[0].size)
    row["uniform_build"], _ = best_time(lambda: build(METHODS["cell"]), repeat)
    checks = uniform_checks(x, rc)
    row["uniform_checks"] = checks
    same = True
    if checks <= MAX_CHECKS_MEASURED:
        row["uniform_total"], cl = best_time(lambda: neighbor_list(x, rc, method="cell"), repeat if checks < 1e8 else 1)
        row["uniform_estimated"] = False
        ns_per_check.append(1e9 * (row["uniform_total"] - row["uniform_build"]) / max(checks, 1.0))
        same &= all(np.array_equal(a, b) for a, b in zip(_sorted_pairs(cl), reference))
    else:
        cost = float(np.median(ns_per_check)) if ns_per_check else 2.0
        row["uniform_total"] = row["uniform_build"] + 1e-9 * cost * checks
        row["uniform_estimated"] = True
    kd_repeat = 1 if n > 200_000 else repeat
    row["kd_ball"], kb = best_time(lambda: kdtree_ball_pairs(x, rc), kd_repeat)
    same &= all(np.array_equal(a, b) for a, b in zip(_sorted_pairs(kb), reference))
    if checks <= kd_pairs_max:
        row["kd_pairs"], kp = best_time(lambda: kdtree_pairs(x, rc), kd_repeat)
        same &= all(np.array_equal(a, b) for a, b in zip(_sorted_pairs(kp), reference))
    else:
        row["kd_pairs"] = None
    row["kd_best"] = min(t for t in (row["kd_ball"], row["kd_pairs"]) if t is not None)
    row["same_pairs"] = bool(same)
    row["ar_ns_per_particle"] = 1e9 * row["ar_total"] / n
    if memory:
        import tempfile
        from pathlib import Path

        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "xrc.npz"
            np.savez(path, x=x, rc=rc)
            setup = (f"import numpy as np, arpy\nd = np.load({str(path)!r})\nx, rc = d['x'], d['rc']\n"
                     "arpy.neighbor_list(x[:10], rc[:10])")
            grow = peak_memory_growth(setup, "nl = arpy.neighbor_list(x, rc, method='ar')")
        row["ar_peak_bytes_per_particle"] = grow / n
    return row


def break_even(rows: list[dict], key: str = "lam") -> float | None:
    """The ``key`` value (lambda) where uniform total / AR total crosses 1 (log-linear
    interpolation); the smallest one if AR is already faster there; None if never."""
    rows = sorted(rows, key=lambda r: r[key])
    ratio = [r["uniform_total"] / r["ar_total"] for r in rows]
    if ratio[0] >= 1.0:
        return rows[0][key]
    for (r0, q0), (r1, q1) in zip(zip(rows, ratio), zip(rows[1:], ratio[1:])):
        if q0 < 1.0 <= q1:
            t = -np.log(q0) / (np.log(q1) - np.log(q0))
            return float(np.exp(np.log(r0[key]) + t * (np.log(r1[key]) - np.log(r0[key]))))
    return None
