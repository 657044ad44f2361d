"""Command-line interface: ``arpy <command> [options]`` (also ``python -m arpy``)."""

from __future__ import annotations

import argparse
import sys

import numpy as np

__all__ = ["main"]


def _demo(args: argparse.Namespace) -> int:
    """Neighbour lists for the AR benchmark distribution with every available method."""
    from ._bench import best_time, kdtree_pairs
    from .distributions import ar_benchmark
    from .neighbors import neighbor_list

    x, rc = ar_benchmark(args.n, args.lam, d=args.d)
    n = x.shape[0]
    print(f"arpy demo: AR benchmark distribution (Awile et al. 2012, Sec. 3.1), d = {args.d}")
    print(f"  {n} particles: {10 ** args.d} large (rc = {rc.max():g}) + {args.n} small (rc = {rc.min():g}),"
          f" resolution span lambda = {args.lam:g}")
    methods = {
        "ar (adaptive-resolution cells)": lambda: neighbor_list(x, rc, method="ar").pairs(),
        "cell (uniform cell list)": lambda: neighbor_list(x, rc, method="cell").pairs(),
        "cKDTree.query_pairs + min rule": lambda: _sorted(*kdtree_pairs(x, rc)),
    }
    if n <= args.brute_max:
        methods["brute (all pairs)"] = lambda: neighbor_list(x, rc, method="brute").pairs()
    rows, reference = [], None
    for name, fn in methods.items():
        t, (i, j) = best_time(fn, repeat=args.repeat)
        if reference is None:
            reference = (i, j)
        same = np.array_equal(i, reference[0]) and np.array_equal(j, reference[1])
        rows.append((name, i.size, t, same))
    print(f"\n  {'method':34s} {'pairs':>10s} {'time [ms]':>10s} {'ns/particle':>12s}  same pairs")
    for name, npairs, t, same in rows:
        print(f"  {name:34s} {npairs:10d} {1e3 * t:10.2f} {1e9 * t / n:12.1f}  {'yes' if same else 'NO'}")
    if n > args.brute_max:
        print(f"\n  (brute force skipped above {args.brute_max} particles; raise --brute-max to include it)")
    return 0 if all(r[3] for r in rows) else 1


def _sorted(i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order = np.lexsort((j, i))
    return i[order], j[order]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``arpy`` command."""
    parser = argparse.ArgumentParser(prog="arpy", description="Adaptive-resolution particle methods.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="command")
    demo = sub.add_parser("demo", help="neighbour lists of the AR benchmark distribution, every method timed")
    demo.add_argument("--n", type=int, default=20000, help="number of small particles (default 20000)")
    demo.add_argument("--lam", type=float, default=10.0, help="resolution span lambda (default 10)")
    demo.add_argument("--d", type=int, default=2, choices=(2, 3), help="dimension (default 2)")
    demo.add_argument("--repeat", type=int, default=3, help="timing repeats, best is shown (default 3)")
    demo.add_argument("--brute-max", type=int, default=30000, help="largest n for brute force (default 30000)")
    demo.set_defaults(func=_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``arpy`` command; returns the process exit code."""
    args = build_parser().parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
