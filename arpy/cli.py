"""Command-line interface: ``arpy <command> [options]`` (also ``python -m arpy``).

``arpy run <case>`` has one subcommand per case of the registry :data:`arpy.cases.CASES`, built
from each case's parameters (options, defaults, help, checks); ``arpy run`` without a case runs
the first, ``pulse``.  Every option is checked before any work starts, those of ``arpy demo``
from :data:`DEMO`.  A bad value, or an option the case does not take, ends the command with
argparse's one-line error and exit code 2.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from . import plotting
from .io import StateFileError, json_default
from ._version import __version__
from .cases import CASES
from .cases.registry import COMMON, NATURAL, Case, Check, Param, at_least
from .state import StateMismatchError

__all__ = ["DEMO", "build_parser", "main"]


def _demo(args: argparse.Namespace) -> int:
    """Neighbour lists for the AR benchmark distribution with every available method."""
    from ._bench import best_time, kdtree_pairs
    from .distributions import ar_benchmark
    from .lists.search import neighbor_list

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


#: The options of ``arpy demo``.
DEMO: dict[str, tuple[Check, ...]] = {
    "--n": (at_least(1, kind="an integer"),),
    "--lam": (at_least(1, what=" (the resolution span, the largest cutoff over the smallest)"),),
    "--d": (),
    "--repeat": (at_least(1, kind="an integer"),),
    "--brute-max": (NATURAL,),
}
#: ``arpy run`` without a case runs this one.
DEFAULT_CASE = next(iter(CASES))


def _failure(value: Any, checks: tuple[Check, ...], context: dict[str, Any]) -> str | None:
    """The message of the first check the value fails, or None."""
    for ok, message in checks:
        try:
            if ok(value, context):
                continue
            reason = ""
        except ValueError as exc:
            reason = f" ({exc})"
        return message.format(value=value, **context) + reason
    return None


def _check(args: argparse.Namespace, options: dict[str, tuple[Check, ...]], context: dict[str, Any]) -> None:
    """Ends the command with its parser's error at the first value (of a list: element) that fails its
    option's checks; None, the case function's own default, is not checked."""
    for flag, checks in options.items():
        value = getattr(args, flag[2:].replace("-", "_"))
        for v in value if isinstance(value, list) else [value]:
            failure = None if v is None else _failure(v, checks, context)
            if failure:
                args.parser.error(f"argument {flag}: {v}: {failure}")


def _settle(args: argparse.Namespace) -> None:
    """Checks the options of ``args.command`` before any work; for ``run``, first fills in the
    defaults that depend on other options (:attr:`Param.default_for`)."""
    if args.command == "demo":
        _check(args, DEMO, vars(args))
        return
    case: Case = args.spec
    params: tuple[Param, ...] = (*case.params, *COMMON)
    for p in params:
        if p.default_for is not None and getattr(args, p.dest) is None:
            setattr(args, p.dest, p.default_for(args))
    _check(args, {p.flag: p.checks for p in params}, {**vars(args), **case.context(args)})
    checkpoint = case.checkpoint(args)
    if checkpoint is not None:
        try:
            t = checkpoint.check()
        except ValueError as exc:                  # (of another run, or a file that is not what it should be)
            args.parser.error(f"argument --resume: {exc}")
        if t is not None and args.T < t:
            args.parser.error(f"argument --T: {args.T:g}: must be >= {t:g}, the time of the checkpoint to resume "
                              f"({checkpoint.path}); a resumed run goes on from there")


def _run(args: argparse.Namespace) -> int:
    """Runs the case of ``arpy run``; its outputs go into --out/<case> (figures with matplotlib, the
    ``plot`` extra).  With --json the case's text goes nowhere and one JSON object is printed: the
    case, the run's record (:func:`arpy.io.run_record`: the options and seed, the case's summary, the
    ranks, threads and versions; the sidecar of each ``.npz`` holds the same) and the files in
    --out/<case>.  Started
    by ``mpiexec -n P``, the case runs across the P ranks, and rank 0 prints and writes.
    A checkpoint that is unreadable or of another run when the run loads it (changed after the options
    were checked) ends one process with one ``arpy: error:`` line and exit code 1."""
    from .distributed import launched_comm

    args.comm = comm = launched_comm()
    root = comm is None or comm.rank == 0
    out = Path(args.out) / args.case
    out.mkdir(parents=True, exist_ok=True)
    if root and not args.no_figure and plotting.available():      # (only rank 0 draws: the others need no matplotlib)
        import matplotlib

        matplotlib.use("Agg")
    try:
        if not args.json and root:
            args.spec.run(args, out)
            print(f"  wrote {out}/")
            return 0
        with contextlib.redirect_stdout(io.StringIO()):        # (under mpiexec, rank 0 prints)
            summary = args.spec.run(args, out)
    except (StateFileError, StateMismatchError) as exc:
        if comm is not None:                # (every rank read the file: the MPI job ends as for any error)
            raise
        print(f"arpy: error: {exc}", file=sys.stderr)      # (a checkpoint changed after the options were checked)
        return 1
    if not root:
        return 0
    record = {"case": args.case, **args.spec.record(args, summary),
              "outputs": sorted(str(p) for p in out.iterdir() if p.is_file())}
    print(json.dumps(record, indent=1, default=json_default))
    return 0


def _options(case: Case) -> str:
    return " ".join(p.flag for p in case.params)


def _cases_help() -> str:
    """The options each case of ``arpy run`` takes, from the registry."""
    width = max(map(len, CASES)) + 1
    return "\n".join(["options by case (arpy run CASE --help: their meaning and defaults):",
                      *(f"  {name + ':':{width}s} {_options(case)}" for name, case in CASES.items()),
                      f"  {'all:':{width}s} {' '.join(p.flag for p in COMMON)}"])


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``arpy`` command: ``demo``, and ``run`` with one subcommand per case."""
    parser = argparse.ArgumentParser(prog="arpy", description="Adaptive-resolution particle methods.")
    parser.add_argument("--version", action="version", version=f"arpy {__version__} (distribution arpy-particles)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="command")
    demo = sub.add_parser("demo", help="neighbour lists of the AR benchmark distribution, every method timed")
    demo.add_argument("--n", type=int, default=20000, help="number of small particles (default 20000)")
    demo.add_argument("--lam", type=float, default=10.0, help="resolution span lambda (default 10)")
    demo.add_argument("--d", type=int, default=2, choices=(2, 3), help="dimension (default 2)")
    demo.add_argument("--repeat", type=int, default=3, help="timing repeats, best is shown (default 3)")
    demo.add_argument("--brute-max", type=int, default=30000, help="largest n for brute force (default 30000)")
    demo.set_defaults(func=_demo, parser=demo)
    run = sub.add_parser("run", help=f"a test case of the JCP paper: {', '.join(CASES)} (default {DEFAULT_CASE})",
                         description=f"Runs a test case of Reboux et al. (2012); without a case, {DEFAULT_CASE}.",
                         epilog=_cases_help(), formatter_class=argparse.RawDescriptionHelpFormatter)
    cases = run.add_subparsers(dest="case", required=True, metavar="case", title="cases")
    for name, case in CASES.items():
        p = cases.add_parser(name, help=case.title, description=f"{case.title}. {case.run_time()}".strip(),
                             allow_abbrev=False)
        for param in (*case.params, *COMMON):
            param.add_to(p)
        p.set_defaults(func=_run, parser=p, spec=case)
    return parser


def _default_case(argv: list[str]) -> list[str]:
    """``arpy run [options]`` without a case: the default case's subcommand."""
    if argv[:1] == ["run"] and (len(argv) == 1 or (argv[1].startswith("-") and argv[1] not in ("-h", "--help"))):
        return ["run", DEFAULT_CASE, *argv[1:]]
    return argv


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``arpy`` command; returns the process exit code."""
    parser = build_parser()
    args, extra = parser.parse_known_args(_default_case(sys.argv[1:] if argv is None else list(argv)))
    if extra:
        if args.command != "run":
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        args.parser.error(f"unrecognized arguments: {' '.join(extra)}; case {args.case} takes {_options(args.spec)} "
                          f"(and {' '.join(p.flag for p in COMMON)})")
    _settle(args)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
