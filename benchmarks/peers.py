"""Benchmark: arpy's neighbour lists against the peers users compare it with.

Peers (each optional: ``pip install ".[peers]"``; a peer that is not installed is skipped, and the
run says so):

  kdtree_pairs   scipy.spatial.cKDTree(x).query_pairs(r)            (one thread: it has no workers=)
  kdtree_ball    cKDTree(x).query_ball_point(x, r_i, workers=T)      (per-particle radii; full rows)
  vesin          vesin.NeighborList(cutoff, full_list=False, n_threads=T).compute(...)
  freud          freud.locality.AABBQuery(box, x).query(x, r_max=...).toNeighborList()  (TBB, T threads)
  matscipy       matscipy.neighbours.neighbour_list("ij", ...)      (one thread; full list)

Cases: uniform random positions in the unit box, N = 1e5 and 1e6, d = 2 and 3, free space and a
periodic box, and two rules:

  min   one cutoff r for every particle (16 neighbours on average): every library's own rule
  sum   polydisperse radii r_p, log-uniform over a factor 10 (16 contacts on average): p and q are
        neighbours iff |x_p - x_q| <= r_p + r_q (granular contacts).  matscipy takes per-atom radii
        natively (its pair cutoff is the sum of the two radii); the others search with the largest
        reach, 2 max(r), and filter the candidates by distance (cKDTree's ball query searches
        r_p + max(r) around each p).  arpy: ``neighbor_list(x, r, rule="sum")`` if this build has
        it, else the row says it is not available.

Each measurement runs in a fresh process (``peers.py --worker``): it loads the inputs, imports the
library, resets the resident-memory high-water mark (Linux /proc; ``ru_maxrss`` cannot be reset, and
the imports' own peak would hide a smaller list's) and reads the resident memory (the baseline), then
runs the list (plus the filter of the sum rule and the conversion to index arrays where the peer needs
one) several times and reports the shortest wall time, the CPU time of that run, and the growth of
the high-water mark over the baseline (peak memory).  Then it reduces the result
to the sorted unordered pairs, and the parent compares them with arpy's (or, when arpy has no sum
rule, with cKDTree's query_pairs).  Threads: 2 where a library threads (``OMP_NUM_THREADS``,
``n_threads``, ``workers``, ``freud.parallel``); the machine may be shared, so times are minima.
2D inputs are given to the 3D-only peers (vesin, freud, matscipy) with z = 0 and no periodicity
along z; freud has no free-space queries, so its free box is periodic and padded by the search radius,
and it computes in single precision (float32 positions and distances), so its pairs can differ from
the others' where a distance lies within float32 rounding of the reach.

    python benchmarks/peers.py                  # the cases above (long: the slowest peers take minutes)
    python benchmarks/peers.py --quick          # N = 1000, 2D periodic, seconds (tests)

Results: ``results/peers.json`` and ``results/peers.md`` (generated from the JSON by :func:`report`).
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

#: peer -> the module it needs
PEERS = {"arpy": "arpy", "kdtree_pairs": "scipy", "kdtree_ball": "scipy", "vesin": "vesin", "freud": "freud",
         "matscipy": "matscipy"}
#: Mean number of neighbours (contacts) per particle.
NEIGHBOURS = 16
#: Factor between the largest and the smallest radius of the sum rule's particles.
RADIUS_SPAN = 10.0
#: Seconds after which a measurement's repeats stop (at least one run is made).
REPEAT_SECONDS = 4.0
#: Seconds a measurement may take before it is given up.
TIMEOUT = 900.0
FULL = dict(sizes=(100_000, 1_000_000), dims=(2, 3), domains=("free", "periodic"), rules=("min", "sum"), repeat=3,
            threads=2)
QUICK = dict(sizes=(1_000,), dims=(2,), domains=("periodic",), rules=("min", "sum"), repeat=1, threads=2)


def ball_volume(d: int) -> float:
    """Volume of the unit ball in d = 2 or 3 dimensions."""
    return np.pi if d == 2 else 4.0 * np.pi / 3.0


def make_case(n: int, d: int, rule: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Uniform positions in [0, 1)^d and the cutoffs (min rule, all equal) or radii (sum rule, log-uniform
    over RADIUS_SPAN), scaled to NEIGHBOURS neighbours per particle on average."""
    rng = np.random.default_rng(seed)
    x = rng.random((n, d))
    if rule == "min":
        return x, np.full(n, (NEIGHBOURS / (n * ball_volume(d))) ** (1.0 / d))
    r = np.exp(rng.uniform(0.0, np.log(RADIUS_SPAN), n))
    p, q = rng.integers(0, n, (2, 200_000))
    mean = float(np.mean((r[p] + r[q]) ** d))                  # E[(r_p + r_q)^d]
    return x, r * (NEIGHBOURS / (n * ball_volume(d) * mean)) ** (1.0 / d)


def canonical(i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The unordered pairs of (i, j) (half or full lists), each once as (a, b), a < b, sorted."""
    i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
    a, b = np.minimum(i, j), np.maximum(i, j)
    keep = a != b
    m = int(b.max(initial=0)) + 1
    key = np.unique(a[keep] * m + b[keep])
    return key // m, key % m


def pair_digest(i: np.ndarray, j: np.ndarray) -> str:
    """A digest of the canonical pairs."""
    a, b = canonical(i, j)
    return hashlib.sha1(a.tobytes() + b"|" + b.tobytes()).hexdigest()


def min_image(v: np.ndarray, periodic: bool) -> np.ndarray:
    """Pair vectors by the minimum image in the unit box (if periodic)."""
    return v - np.round(v) if periodic else v


def sum_filter(x: np.ndarray, r: np.ndarray, i: np.ndarray, j: np.ndarray, periodic: bool,
               dist: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The candidate pairs (i, j) with |x_i - x_j| <= r_i + r_j (distances given or computed)."""
    if dist is None:
        v = min_image(x[j] - x[i], periodic)
        d2 = np.einsum("ij,ij->i", v, v)
    else:
        d2 = dist * dist
    s = r[i] + r[j]
    keep = d2 <= s * s
    return i[keep], j[keep]


def as3(x: np.ndarray) -> np.ndarray:
    """Positions with 3 columns (z = 0 for 2D)."""
    return x if x.shape[1] == 3 else np.column_stack([x, np.zeros(len(x))])


def runner(peer: str, x: np.ndarray, r: np.ndarray, rule: str, periodic: bool, threads: int):
    """A function that builds the list of one peer and returns (i, j) index arrays (or arpy's list)."""
    d = x.shape[1]
    one = float(r[0])
    reach = one if rule == "min" else 2.0 * float(r.max())       # the search radius of one-cutoff peers
    if peer == "arpy":
        import arpy

        arpy.set_num_threads(threads)
        dom = arpy.Domain(np.ones(d), periodic=True) if periodic else None
        if rule == "min":
            return lambda: arpy.neighbor_list(x, one, domain=dom)
        return lambda: arpy.neighbor_list(x, r, rule="sum", domain=dom)
    if peer in ("kdtree_pairs", "kdtree_ball"):
        from scipy.spatial import cKDTree

        box = 1.0 if periodic else None
        if peer == "kdtree_pairs":
            def pairs():
                p = cKDTree(x, boxsize=box).query_pairs(reach, output_type="ndarray")
                i, j = p[:, 0].astype(np.int64), p[:, 1].astype(np.int64)
                return (i, j) if rule == "min" else sum_filter(x, r, i, j, periodic)
            return pairs

        def ball():
            radius = np.full(len(x), one) if rule == "min" else r + float(r.max())
            rows = cKDTree(x, boxsize=box).query_ball_point(x, radius, workers=threads, return_sorted=False)
            counts = np.fromiter((len(v) for v in rows), np.int64, len(rows))
            i = np.repeat(np.arange(len(rows), dtype=np.int64), counts)
            j = np.fromiter((q for v in rows for q in v), np.int64, int(counts.sum()))
            keep = j > i
            i, j = i[keep], j[keep]
            return (i, j) if rule == "min" else sum_filter(x, r, i, j, periodic)
        return ball
    x3 = as3(x)
    flags = [periodic] * d + [False] * (3 - d)
    if peer == "vesin":
        import vesin

        box = np.eye(3) if periodic else np.zeros((3, 3))
        calc = vesin.NeighborList(cutoff=reach, full_list=False, n_threads=threads)

        def run_vesin():
            if rule == "min":
                i, j = calc.compute(x3, box, flags, "ij")
                return i, j
            i, j, dist = calc.compute(x3, box, flags, "ijd")
            return sum_filter(x, r, i.astype(np.int64), j.astype(np.int64), periodic, dist)
        return run_vesin
    if peer == "freud":
        import freud

        freud.parallel.set_num_threads(threads)
        edge = [1.0 if periodic else 1.0 + 2.0 * reach] * d
        box = freud.box.Box(*edge, is2D=True) if d == 2 else freud.box.Box(*edge)
        pts = x3 - np.array([0.5, 0.5, 0.5 if d == 3 else 0.0])

        def run_freud():
            nl = freud.locality.AABBQuery(box, pts).query(pts, dict(r_max=reach, exclude_ii=True)).toNeighborList()
            i, j = nl.query_point_indices.astype(np.int64), nl.point_indices.astype(np.int64)
            return (i, j) if rule == "min" else sum_filter(x, r, i, j, periodic, nl.distances)
        return run_freud
    if peer == "matscipy":
        from matscipy.neighbours import neighbour_list

        cell = np.diag([1.0] * d + [1.0] * (3 - d))
        return lambda: neighbour_list("ij", positions=x3, cell=cell, pbc=flags, cutoff=one if rule == "min" else r)
    raise ValueError(f"unknown peer {peer!r}")


def has_sum_rule() -> bool:
    """Whether this build's arpy.neighbor_list takes rule= (the sum rule)."""
    import arpy

    return "rule" in inspect.signature(arpy.neighbor_list).parameters


def memory_status(key: str) -> int:
    """A line of /proc/self/status in bytes (``VmRSS``: resident now, ``VmHWM``: its high-water mark)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"no {key} in /proc/self/status")


def worker(spec: dict) -> dict:
    """One measurement (in its own process): the shortest wall time and the CPU time of that run, the peak
    memory growth, the pairs' digest."""
    data = np.load(spec["data"])
    x, r = data["x"], data["r"]
    run = runner(spec["peer"], x, r, spec["rule"], spec["domain"] == "periodic", spec["threads"])
    # the baseline: inputs loaded and library imported; the high-water mark reset to what is resident now
    # (ru_maxrss cannot be reset, and the imports' own peak would hide a smaller list's)
    with open("/proc/self/clear_refs", "w") as clear:
        clear.write("5")
    base = memory_status("VmRSS")
    best, cpu, out, t_all = np.inf, np.inf, None, time.perf_counter()
    for _ in range(spec["repeat"]):
        out = None
        t0, c0 = time.perf_counter(), time.process_time()
        out = run()
        t, c = time.perf_counter() - t0, time.process_time() - c0
        if t < best:
            best, cpu = t, c
        if time.perf_counter() - t_all > REPEAT_SECONDS:
            break
    peak = memory_status("VmHWM")
    i, j = out.pairs() if hasattr(out, "pairs") else out
    return dict(seconds=best, cpu_seconds=cpu, peak_bytes=peak - base, pairs=int(canonical(i, j)[0].size),
                digest=pair_digest(i, j))


def measure(peer: str, spec: dict) -> dict:
    """Run :func:`worker` for ``peer`` in a fresh process (OMP_NUM_THREADS = the thread count)."""
    env = dict(os.environ, OMP_NUM_THREADS=str(spec["threads"]))
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(dict(spec, peer=peer))]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        return dict(error=f"no result within {TIMEOUT:.0f} s")
    if out.returncode != 0:
        return dict(error=(out.stderr.strip().splitlines() or ["failed"])[-1])
    return json.loads(out.stdout.strip().splitlines()[-1])


def installed(peer: str) -> bool:
    """Whether the module a peer needs can be imported."""
    return importlib.util.find_spec(PEERS[peer]) is not None


def fmt_time(s: float | None) -> str:
    return "-" if s is None else (f"{1e3 * s:.1f} ms" if s < 1 else f"{s:.2f} s")


def report(res: dict) -> str:
    """The Markdown page of a result (``results/peers.md`` is this of ``results/peers.json``)."""
    meta, rows = res["meta"], res["rows"]
    lines = ["# arpy against its peers: cKDTree, vesin, freud, matscipy", "",
             f"Neighbour lists of N uniform random particles in the unit box ({meta['neighbours']} neighbours per "
             f"particle on average), {meta['threads']} threads where a library threads. Each measurement ran in a "
             f"fresh process: time = the shortest wall time of up to {meta['repeat']} runs (one when a run takes "
             f"more than {meta['repeat_seconds']:g} s), CPU = the CPU time of that run (all threads; robust to "
             "other work on the machine), peak = the growth of the resident memory's high-water mark over the "
             "process after loading the inputs and importing the library. `same pairs`: the sorted unordered "
             "pairs equal arpy's (or, for the sum rule without arpy, cKDTree query_pairs'). "
             + (f"The machine was shared with other work during the run (load average {meta['load']:.0f} on "
                f"{meta['cpus']} cores at the start): wall times are inflated and noisy, the CPU times less so."
                if meta.get("load") is not None else ""), "",
             "    python benchmarks/peers.py            # this page",
             "    python benchmarks/peers.py --quick    # N = 1000, seconds", "",
             "- min rule: one cutoff; every library's own rule.",
             f"- sum rule: radii log-uniform over a factor {meta['radius_span']:g}, neighbours when |x_p - x_q| <= "
             "r_p + r_q. matscipy takes per-atom radii natively; the others search 2 max(r) (cKDTree's ball query "
             "r_p + max(r)) and filter by distance (the filter is in the time).",
             "- arpy: " + ("`neighbor_list(x, r, rule=\"sum\")` for the sum rule." if meta["arpy_sum_rule"]
                           else "arpy sum rule: not available in this build."),
             "- versions: " + ", ".join(f"{k} {v}" for k, v in meta["versions"].items()) + ".",
             *(f"- measured again on {u['date']} (`--update`, load average {u['load']:.0f}): the {', '.join(u['rules'])} "
               f"rule's cases, {', '.join(u['peers'])}." for u in meta.get("updated", [])),
             *(f"- the cases missing before measured on {a['date']} (`--missing`, load average {a['load']:.0f}): "
               f"the {', '.join(a['rules'])} rule, {', '.join(a['peers'])}." for a in meta.get("added", [])),
             ""]
    if meta["skipped"]:
        lines += ["Not installed, skipped: " + ", ".join(meta["skipped"]) + ".", ""]
    cases = {(r["n"], r["d"], r["rule"], r["domain"]) for r in rows}
    missing = [f"N = {n:,} {d}D {rule} {domain}" for n in meta["sizes"] for d in meta["dims"]
               for rule in meta["rules"] for domain in meta["domains"] if (n, d, rule, domain) not in cases]
    if missing:
        lines += ["**Not measured in this run** (stopped there: on the shared machine the run would have taken "
                  "hours; `python benchmarks/peers.py --missing` measures them): " + "; ".join(missing) + ".", ""]
    header = ["rule", "d", "domain", "N", "pairs", "peer", "time", "x arpy", "CPU", "x arpy (CPU)", "peak MB",
              "same pairs"]
    table = []
    for row in rows:
        ref = row["results"].get("arpy", {})
        for peer, m in row["results"].items():
            if "error" in m:
                table.append([row["rule"], row["d"], row["domain"], f"{row['n']:,}", "-", peer, m["error"]]
                             + ["-"] * 5)
                continue
            mine = "seconds" in ref and peer != "arpy"
            table.append([row["rule"], row["d"], row["domain"], f"{row['n']:,}", f"{m['pairs']:,}", peer,
                          fmt_time(m["seconds"]), f"{m['seconds'] / ref['seconds']:.1f}" if mine else "",
                          fmt_time(m["cpu_seconds"]), f"{m['cpu_seconds'] / ref['cpu_seconds']:.1f}" if mine else "",
                          f"{m['peak_bytes'] / 2**20:.1f}", "yes" if m["digest"] == row["reference"] else "NO"])
    lines += md_table(header, table)
    lines += ["", "## Findings", ""]
    for rule in meta["rules"]:
        ratios = {}
        for row in rows:
            ref = row["results"].get("arpy", {})
            if row["rule"] != rule or "seconds" not in ref:
                continue
            for peer, m in row["results"].items():
                if peer != "arpy" and "seconds" in m:
                    ratios.setdefault(peer, []).append((m["seconds"] / ref["seconds"],
                                                        m["cpu_seconds"] / ref["cpu_seconds"]))
        if ratios:
            lines.append(f"- {rule} rule, peer time / arpy time over the cases (wall; CPU): "
                         + "; ".join(f"{p} {min(w for w, _ in v):.1f}-{max(w for w, _ in v):.1f}x; "
                                     f"{min(c for _, c in v):.1f}-{max(c for _, c in v):.1f}x"
                                     for p, v in ratios.items()) + ".")
        elif rule == "sum" and not meta["arpy_sum_rule"]:
            lines.append("- sum rule: arpy sum rule: not available in this build; the peers' pairs are compared "
                         "with cKDTree query_pairs'.")
    bad = [f"{row['rule']} d={row['d']} {row['domain']} N={row['n']} {p}" for row in rows
           for p, m in row["results"].items() if "digest" in m and m["digest"] != row["reference"]]
    lines.append("- Every peer found the same pairs as the reference." if not bad
                 else "- Pairs differ from the reference: " + "; ".join(bad) + "."
                 + (" freud computes in single precision (it converts positions to float32, and its distances "
                    "are float32): a pair whose distance lies within float32 rounding of the reach can fall on "
                    "the other side." if any(b.endswith(" freud") for b in bad) else ""))
    lines += ["", f"Run of {meta['date']} on {res['machine']}, Python {res['python']}."]
    return "\n".join(lines) + "\n"


def md_table(header: list[str], rows: list[list]) -> list[str]:
    from arpy._bench import md_table as table

    return table(header, rows)


def versions(peers: list[str]) -> dict:
    """The version of each installed peer's module (and of arpy, NumPy and SciPy)."""
    out = {}
    for name in sorted({"arpy", "scipy", "numpy"} | {PEERS[p] for p in peers}):
        out[name] = str(getattr(importlib.import_module(name), "__version__", "?"))
    return out


def main(argv: list[str] | None = None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if argv[:1] == ["--worker"]:
        print(json.dumps(worker(json.loads(argv[1]))))
        return 0
    from arpy._bench import benchmark_args, run_info, write_page, write_result

    def extra(parser):
        parser.add_argument("--peers", nargs="+", choices=list(PEERS), default=list(PEERS),
                            help="the peers to run (default: all; arpy always runs)")
        parser.add_argument("--update", action="store_true",
                            help="measure again only the cases already in the JSON under --rules, with arpy and "
                                 "--peers, keeping every other stored measurement")
        parser.add_argument("--missing", action="store_true",
                            help="measure only the cases not yet in the JSON (with arpy and --peers), keeping "
                                 "every stored one")
        parser.add_argument("--rules", nargs="+", choices=["min", "sum"], default=["min", "sum"],
                            help="the rules to measure (default: both)")

    args = benchmark_args(__doc__, argv, HERE / "results", extra)
    cfg = QUICK if args.quick else FULL
    sum_rule = has_sum_rule()
    print("arpy sum rule: " + ("rule='sum'" if sum_rule else "not available in this build"), flush=True)
    wanted = ["arpy"] + [p for p in args.peers if p != "arpy"]
    skipped = [p for p in wanted if not installed(p)]
    for p in skipped:
        print(f"{p}: not installed ({PEERS[p]}), skipped", flush=True)
    peers = [p for p in wanted if p not in skipped]
    rows: list[dict] = []
    meta = dict(date=time.strftime("%Y-%m-%d"), quick=args.quick, threads=cfg["threads"], repeat=cfg["repeat"],
                repeat_seconds=REPEAT_SECONDS, load=os.getloadavg()[0], cpus=os.cpu_count(), neighbours=NEIGHBOURS,
                radius_span=RADIUS_SPAN, rules=list(cfg["rules"]), sizes=list(cfg["sizes"]), dims=list(cfg["dims"]),
                domains=list(cfg["domains"]), arpy_sum_rule=sum_rule,
                skipped=[f"{p} ({PEERS[p]})" for p in skipped], versions=versions(peers))
    res = dict(run_info(), meta=meta, rows=rows)
    tag = "peers_quick" if args.quick else "peers"
    stored: dict[tuple, dict] = {}
    if args.update or args.missing:                  # (the stored run, its cases kept or measured again)
        res = json.loads((args.out / f"{tag}.json").read_text())
        res["meta"]["arpy_sum_rule"] = sum_rule
        res["meta"].setdefault("added" if args.missing else "updated", []).append(
            dict(date=meta["date"], rules=args.rules, peers=peers, load=meta["load"]))
        rows = res["rows"]
        stored = {(r["rule"], r["d"], r["domain"], r["n"]): r for r in rows}
    with tempfile.TemporaryDirectory() as tmp:
        for n in cfg["sizes"]:
            for d in cfg["dims"]:
                for rule in [r for r in cfg["rules"] if r in args.rules]:
                    if args.update and not any((rule, d, dm, n) in stored for dm in cfg["domains"]):
                        continue
                    x, r = make_case(n, d, rule)
                    path = Path(tmp) / f"case_{n}_{d}_{rule}.npz"
                    np.savez(path, x=x, r=r)
                    for domain in cfg["domains"]:
                        if args.update and (rule, d, domain, n) not in stored:
                            continue
                        if args.missing and (rule, d, domain, n) in stored:
                            continue
                        spec = dict(data=str(path), rule=rule, domain=domain, threads=cfg["threads"],
                                    repeat=cfg["repeat"])
                        old = stored.get((rule, d, domain, n))
                        results = dict(old["results"]) if old else {}
                        for p in peers:
                            if p == "arpy" and rule == "sum" and not sum_rule:
                                continue
                            results[p] = measure(p, spec)
                            m = results[p]
                            print(f"{rule:3s} d={d} {domain:8s} N={n:8d} {p:13s} "
                                  + (m["error"] if "error" in m else
                                     f"{fmt_time(m['seconds']):>10s} CPU {fmt_time(m['cpu_seconds']):>10s} "
                                     f"{m['peak_bytes'] / 2**20:7.0f} MB {m['pairs']:10d} pairs"), flush=True)
                        ref = results.get("arpy", results.get("kdtree_pairs", {}))
                        row = dict(rule=rule, d=d, domain=domain, n=n, results=results, reference=ref.get("digest"))
                        if old:
                            old.update(row)
                        else:
                            rows.append(row)
                        # after every case, so that an interrupted run keeps what it measured
                        (args.out / f"{tag}.json").write_text(json.dumps(res, indent=1))
    write_result(args.out, tag, res, f"{tag}.md")
    print(f"wrote {write_page(args.out, tag, report)}")
    same = all(m.get("digest") == row["reference"] for row in rows for m in row["results"].values()
               if "digest" in m)
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
