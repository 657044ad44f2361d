"""What a run leaves for a scientist, read back by other readers than arpy's writers: the JSON record
beside a case's results (options, seed, summary, ranks, threads, versions, column names), the VTU time
series of ``--output-every`` through its ``.pvd`` (parsed as XML, each frame with meshio), and a
distributed run's ``.pvtu`` frames through VTK's own reader of parallel unstructured grids (the reader
ParaView uses, where VTK is installed) and, always, as XML with each piece read by meshio (meshio has
no reader of ``.pvtu`` files themselves)."""

from __future__ import annotations

import json
import sys
from importlib import metadata
from pathlib import Path
from types import SimpleNamespace
from xml.etree import ElementTree as ET

import meshio
import numpy as np
import pytest
import scipy

import arpy
from arpy.io import load_results
from arpy.timeseries import TimeSeries

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_simulation import blob_simulation  # noqa: E402


def read_pvd(path: Path) -> list[tuple[float, Path]]:
    """The data sets of a ``.pvd`` collection (ParaView's format): (timestep, file), files relative to it."""
    root = ET.parse(path).getroot()
    assert root.tag == "VTKFile" and root.get("type") == "Collection"
    return [(float(d.get("timestep")), path.parent / d.get("file")) for d in root.iter("DataSet")]


def read_pvtu(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Points (n, 3) and point data of a ``.pvtu``: its XML parsed (the ``PUnstructuredGrid`` and the
    arrays it declares), each ``Piece`` read by meshio and checked to hold exactly those arrays, the
    pieces concatenated in their order (meshio has no reader of ``.pvtu`` files themselves)."""
    root = ET.parse(path).getroot()
    assert root.tag == "VTKFile" and root.get("type") == "PUnstructuredGrid"
    grid = root.find("PUnstructuredGrid")
    declared = {a.get("Name"): int(a.get("NumberOfComponents", "1")) for a in grid.find("PPointData")}
    pieces = [meshio.read(path.parent / p.get("Source")) for p in grid.findall("Piece")]
    for piece in pieces:
        assert {k: (v.shape[1] if v.ndim > 1 else 1) for k, v in piece.point_data.items()} == declared
    points = np.concatenate([p.points for p in pieces])
    return points, {k: np.concatenate([p.point_data[k] for p in pieces]) for k in declared}


def read_pvtu_vtk(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Points (n, 3) and point data of a ``.pvtu`` read by VTK's vtkXMLPUnstructuredGridReader (the
    reader ParaView uses; VTK is not a test dependency: pip install vtk)."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLPUnstructuredGridReader

    reader = vtkXMLPUnstructuredGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    grid = reader.GetOutput()
    data = grid.GetPointData()
    arrays = {data.GetArrayName(i): vtk_to_numpy(data.GetArray(i)) for i in range(data.GetNumberOfArrays())}
    return vtk_to_numpy(grid.GetPoints().GetData()), arrays


def by_position(points: np.ndarray, *columns: np.ndarray) -> list[np.ndarray]:
    """The arrays in the lexicographic order of the points (frames of several pieces come in rank order)."""
    order = np.lexsort(points[:, ::-1].T)
    return [points[order], *(c[order] for c in columns)]


def check_case_outputs(out: Path, options: dict, steps: int) -> None:
    """The outputs of ``arpy run advection --output-every 1`` in ``out`` (OUT/advection) read back: the
    sidecar advection.json holds the run's record consistent with the run: the ``options`` given, the
    seed, the particles in advection.npz (N, the error recomputed from the exact field), ``steps``, one
    process, the threads and the versions of the packages loaded here.  Its .pvd lists a frame per step
    (``steps`` + 1), times increasing from 0 to the final time, each frame a VTU that meshio reads with
    f and D_p; the last one holds the final particles.  (tests/test_cli_and_benchmarks.py runs the case.)"""
    from arpy.cases import blob

    record = json.loads((out / "advection.json").read_text())
    parameters = record["parameters"]
    assert {k: parameters[k] for k in options} == options and parameters["output_every"] == 1
    assert record["seed"] == parameters["seed"] == 1
    assert record["ranks"] == 1 and record["threads"] == arpy.get_num_threads()
    versions = record["versions"]
    assert (versions["arpy"], versions["numpy"], versions["scipy"]) == (arpy.__version__, np.__version__,
                                                                       scipy.__version__)
    assert versions["mpi4py"] == metadata.version("mpi4py")
    assert load_results(out / "advection.npz")[0] == parameters
    summary = record["summary"]
    with np.load(out / "advection.npz") as saved:
        x, f, D = saved["x"], saved["f"], saved["D"]
    exact = blob(x)
    assert summary["N"] == len(x) and summary["steps"] == steps and summary["wall_s"] > 0
    assert summary["error"] == np.abs(f - exact).max() / np.abs(exact).max()
    assert summary["t"] == pytest.approx(parameters["T"], rel=1e-15)
    frames = read_pvd(out / "advection_series.pvd")
    times = [t for t, _ in frames]
    assert times[0] == 0.0 and times[-1] == summary["t"] and np.all(np.diff(times) > 0)
    assert [p.name for _, p in frames] == [f"advection_series_{s:06d}.vtu" for s in range(steps + 1)]
    meshes = [meshio.read(p) for _, p in frames]
    assert all(set(m.point_data) == {"f", "D"} for m in meshes)
    last = meshes[-1]
    got = by_position(last.points[:, :2], last.point_data["f"], last.point_data["D"])
    for a, b in zip(got, by_position(x, f, D)):
        np.testing.assert_array_equal(a, b)


def test_time_series_frames_hold_the_states_at_their_times(tmp_path):
    """A TimeSeries as the callback of Simulation.run, every 2 steps (with re-organizations that change
    the particles): each frame meshio reads has the positions, D_p and f the simulation had at the
    frame's time, bit for bit; a series resumed at a time keeps the frames up to it and replaces those
    after it."""
    sim = blob_simulation()
    series = TimeSeries(tmp_path / "blob.pvd", every=2)
    states = {}

    def record(s):
        states[s.t] = (s.x.copy(), s.D.copy(), s.f.copy())
        series(s)

    record(sim)
    series.start(sim)
    sim.run(0.05, callback=record)
    series.finish(sim)
    frames = read_pvd(tmp_path / "blob.pvd")
    assert [t for t, _ in frames] == [t for i, t in enumerate(states) if i % 2 == 0 or i == len(states) - 1]
    assert len({len(states[t][0]) for t, _ in frames}) > 1                     # (re-organized between frames)
    for t, path in frames:
        mesh = meshio.read(path)
        x, D, f = states[t]
        np.testing.assert_array_equal(mesh.points[:, :2], x)
        assert np.all(mesh.points[:, 2] == 0)
        np.testing.assert_array_equal(mesh.point_data["D"], D)
        np.testing.assert_array_equal(mesh.point_data["f"], f)
    resumed = TimeSeries(tmp_path / "blob.pvd", every=2)
    middle = frames[1][0]
    resumed.start(SimpleNamespace(t=middle), resume=True)
    resumed.write(0.5, 99, np.zeros((1, 2)), {"D": np.ones(1), "f": np.ones(1)})
    again = read_pvd(tmp_path / "blob.pvd")
    assert again[:2] == frames[:2] and again[2:] == [(0.5, tmp_path / "blob" / "blob_000099.vtu")]


def two_rank_series(folder: Path) -> tuple[list[tuple[float, Path]], dict]:
    """blob_simulation to t = 0.03 on 2 thread ranks with a TimeSeries in ``folder``: (its frames, the
    one-process run's (x, D, f) by time)."""
    from arpy.distributed import run_threads

    sim = blob_simulation()
    states = {0.0: (sim.x.copy(), sim.D.copy(), sim.f.copy())}
    sim.run(0.03, callback=lambda s: states.__setitem__(s.t, (s.x.copy(), s.D.copy(), s.f.copy())))

    def rank(comm):
        s = blob_simulation(comm)
        series = TimeSeries(folder / "blob.pvd", every=1)
        series.start(s)
        s.run(0.03, callback=series)
        return s.particles.n

    assert all(n > 0 for n in run_threads(2, rank))
    return read_pvd(folder / "blob.pvd"), states


def test_a_distributed_series_is_one_pvtu_per_frame(tmp_path):
    """The same simulation on 2 thread ranks with a TimeSeries: each frame is a .pvtu (one piece per
    rank) whose pieces hold the positions, D_p and f of the one-process run at that time (bitwise:
    the runs are the same at any rank count) and each particle's rank."""
    frames, states = two_rank_series(tmp_path)
    assert [t for t, _ in frames] == list(states) and all(p.suffix == ".pvtu" for _, p in frames)
    for t, path in frames:
        points, data = read_pvtu(path)
        assert sorted(data) == ["D", "f", "rank"] and set(np.unique(data["rank"])) == {0.0, 1.0}
        assert np.all(points[:, 2] == 0)
        x, D, f = states[t]
        for a, b in zip(by_position(points[:, :2], data["D"], data["f"]), by_position(x, D, f)):
            np.testing.assert_array_equal(a, b)


def test_vtk_reads_a_distributed_frame_whole(tmp_path):
    """Where VTK is installed: its parallel reader (ParaView's) opens the last .pvtu frame whole, with
    the one-process particles."""
    pytest.importorskip("vtkmodules", reason="VTK is not installed (pip install vtk); the .pvtu frames are "
                                             "read as XML with meshio pieces by the test above")
    frames, states = two_rank_series(tmp_path)
    points, data = read_pvtu_vtk(frames[-1][1])
    for a, b in zip(by_position(points[:, :2], data["D"], data["f"]), by_position(*states[frames[-1][0]])):
        np.testing.assert_array_equal(a, b)


def test_the_guide_time_series_example_runs_as_written(tmp_path, monkeypatch):
    """The guide's TimeSeries example (in a fresh folder): out/blob.pvd lists the frames of steps 0, 2,
    4 and 5 (the last, at t = 0.05), and the last frame holds the simulation's particles."""
    import re

    page = (Path(__file__).resolve().parents[1] / "docs" / "guide.md").read_text(encoding="utf-8")
    code = next(b for b in re.findall(r"```python\n(.*?)```", page, flags=re.S) if "TimeSeries(" in b)
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "guide"}
    exec(compile(code, "guide.md", "exec"), namespace)
    sim = namespace["sim"]
    frames = read_pvd(tmp_path / "out" / "blob.pvd")
    assert [p.name for _, p in frames] == [f"blob_{s:06d}.vtu" for s in (0, 2, 4, 5)] and sim.steps == 5
    assert frames[-1][0] == sim.t == pytest.approx(0.05, rel=1e-15) and np.all(np.diff([t for t, _ in frames]) > 0)
    last = meshio.read(frames[-1][1])
    np.testing.assert_array_equal(last.points[:, :2], sim.x)
    np.testing.assert_array_equal(last.point_data["f"], sim.f)


def run_case(case: str, options: list[str], out: Path, comm=None) -> dict:
    """The runner of ``arpy run CASE OPTIONS --out OUT`` (options parsed and checked as the command
    does) on one process, or on the ranks of ``comm``; its summary."""
    from arpy.cli import _settle, build_parser

    args = build_parser().parse_args(["run", case, *options, "--quiet", "--out", str(out)])
    _settle(args)
    args.comm = comm
    (out / case).mkdir(parents=True, exist_ok=True)
    return args.spec.run(args, out / case)


def test_a_case_on_ranks_writes_its_outputs_in_pieces_equal_to_the_one_process_outputs(tmp_path, monkeypatch):
    """``arpy run pulse`` (with checkpoints) on 2 thread ranks, with ``Particles.gather`` patched to
    fail: no rank gathers the particles.  The summary (errors, mass, N:
    reductions) is the one-process summary bit for bit; the .npz is an index written by rank 0 (the
    record, the arrays of the run) and one piece per rank, which read back in key order hold the
    one-process arrays bit for bit; the .pvtu's pieces hold the one-process .vtu's points and arrays; the
    figure is drawn from the pieces read back (the one-process particles), and above its count of points
    from the same sample of them as one process draws."""
    import functools

    import arpy.cases.pulse as pulse
    from arpy.cases.pulse import CASE
    from arpy.distributed import run_threads
    from arpy.io import load_run
    from arpy.particles import read_pieces

    case = name = "pulse"
    options, parts = ["--D0", "0.3", "--T", "0.004", "--k", "2", "--mass-every", "0", "--remeshed", "0",
                      "--checkpoint-every", "2"], 2
    drawn: list = []                # (what the figure is drawn from; neither it nor a fine mass mesh: CPU)
    monkeypatch.setattr("arpy.cases.pulse._plot", lambda r, path: drawn.append(r))
    monkeypatch.setattr("arpy.cases.pulse.gaussian_pulse", functools.partial(pulse.gaussian_pulse, mass_points=11))
    one = run_case(case, options, tmp_path / "one")
    monkeypatch.setattr(arpy.Particles, "gather", lambda self: pytest.fail("a rank gathered the particles"))
    many = run_threads(parts, lambda comm: run_case(case, options, tmp_path / "many", comm), timeout=120)
    skip = ("wall_s", "ranks")
    assert all({k: v for k, v in s.items() if k not in skip} == {k: v for k, v in one.items() if k not in skip}
               for s in many)
    record1, arrays1 = load_run(tmp_path / "one" / case / f"{name}.npz")
    index_path = tmp_path / "many" / case / f"{name}.npz"
    record, arrays = load_run(index_path)
    files = record["pieces"]["files"]
    assert files == [f"{name}.part{r:05d}-of-{parts:05d}.npz" for r in range(parts)]
    sizes = [np.load(index_path.parent / f)["keys"].size for f in files]
    assert min(sizes) > 0 and sum(sizes) == one["N"] and "x" not in arrays
    rows = read_pieces(index_path, record["pieces"])
    np.testing.assert_array_equal(rows.pop("keys"), np.arange(one["N"]))
    assert sorted({**arrays, **rows}) == sorted(arrays1)
    for k, v in {**arrays, **rows}.items():
        if not k.startswith("history_t_"):                  # (phase timings)
            assert v.dtype == arrays1[k].dtype and v.tobytes() == arrays1[k].tobytes(), k
    assert record["summary"]["N"] == record1["summary"]["N"] and record["ranks"] == parts
    points, data = read_pvtu(tmp_path / "many" / case / f"{name}_particles.pvtu")
    vtu = meshio.read(tmp_path / "one" / case / f"{name}_particles.vtu")
    assert sorted(data) == sorted([*vtu.point_data, "rank"])
    want = by_position(vtu.points, *(vtu.point_data[k] for k in sorted(vtu.point_data)))
    for a, b in zip(by_position(points, *(data[k] for k in sorted(vtu.point_data))), want):
        np.testing.assert_array_equal(a, b)
    assert len(drawn) == 2 and all(drawn[1][k].tobytes() == drawn[0][k].tobytes() for k in ("x", "f", "D", "f_exact"))
    # above a figure's count of points: the sample by key, the same rows from the pieces as from one process
    points = one["N"] // 3
    rank0 = SimpleNamespace(comm=SimpleNamespace(rank=0, size=parts), no_figure=False)
    alone = SimpleNamespace(comm=None, no_figure=False)
    whole = {k: arrays1[k] for k in ("x", "f", "D", "f_exact")} | {"keys": np.arange(one["N"])}
    for args in (rank0, alone):
        assert CASE.figure(args, tmp_path / "x.png", index_path, whole, lambda w, path: drawn.append(w), points=points)
    got, alone_got = drawn[2:]
    assert got["N"] == alone_got["N"] == one["N"] and sorted(got) == sorted(alone_got) == sorted([*whole, "N"])
    assert abs(got["keys"].size - points) < 5 * np.sqrt(points) and np.all(np.diff(got["keys"]) > 0)
    for k in whole:
        assert got[k].tobytes() == alone_got[k].tobytes() == whole[k][got["keys"]].tobytes(), k


def test_a_figure_sample_is_chosen_by_key_alone():
    """arpy.particles.sampled: key 0 is chosen as splitmix64's published first output from seed 0
    (0xE220A8397B1DCDAF, the hash of 0 + its increment) decides, at fractions either side of it; of 10^6
    keys about the fraction asked for (within 5 sigma); a smaller fraction's sample lies in a larger
    one's; and each key's choice does not depend on the other rows (any order, any subset: a rank's)."""
    from arpy.particles import sampled

    first = 0xE220A8397B1DCDAF / 2.0 ** 64
    assert not sampled(np.array([0]), first * (1 - 1e-9))[0] and sampled(np.array([0]), first * (1 + 1e-9))[0]
    keys = np.arange(10 ** 6)
    for fraction in (0.001, 0.2, 0.7):
        count = int(sampled(keys, fraction).sum())
        assert abs(count - fraction * keys.size) < 5 * np.sqrt(fraction * (1 - fraction) * keys.size), fraction
    small, large = sampled(keys, 0.1), sampled(keys, 0.3)
    assert np.all(large[small]) and sampled(keys, 1.0).all() and not sampled(keys, 0.0).any()
    order = np.random.default_rng(3).permutation(keys.size)[:1000]
    np.testing.assert_array_equal(sampled(keys[order], 0.3), large[order])


@pytest.mark.parametrize("case, options", [
    ("advection", ["--D0", "0.28", "--T", "0.125", "--k", "3"]),
    ("five-spot", ["--D0", "0.2", "--T", "0.001", "--k", "10"]),
])
def test_the_snapshots_of_a_case_on_ranks_go_to_the_pieces_and_resume_on_one_process(case, options, tmp_path,
                                                                                       monkeypatch):
    """``arpy run advection`` (its particles at T/2) and ``arpy run five-spot`` (its snapshots) with
    checkpoints every 2 steps on 2 thread ranks, with ``Particles.gather`` patched to fail: no rank
    gathers a snapshot.  Each rank writes its rows of them to its piece of the results (advection's, read
    back in key order, are the one-process ``half_*`` arrays bit for bit) and of the state; rank 0 draws
    the figure from the pieces read back (the one-process figure's particles, at T/2 and T or at each
    snapshot, bit for bit); one process resumed from the ranks' last checkpoint (its snapshots in pieces) writes
    the one-process results and draws the one-process figure."""
    from arpy.distributed import run_threads
    from arpy.io import load_run
    from arpy.particles import read_pieces

    name, options = case.replace("-", "_"), [*options, "--checkpoint-every", "2"]
    drawn: list = []                                 # (what each figure is drawn from, not drawn: CPU)
    if case == "advection":
        monkeypatch.setattr("arpy.cases.reversing_vortex._plot", lambda r, path: drawn.append(
            {"T": {k: r[k] for k in ("x", "f", "D")}, "half": r["half"]}))
    else:
        monkeypatch.setattr("arpy.cases.buckley_leverett.plot_five_spot", lambda r, path: drawn.append(
            dict(sorted(r["snapshots"].items()))))                  # (the particles at T: not in the figure)
    one = run_case(case, options, tmp_path / "one")
    with monkeypatch.context() as patch:
        patch.setattr(arpy.Particles, "gather", lambda self: pytest.fail("a rank gathered the particles"))
        many = run_threads(2, lambda comm: run_case(case, options, tmp_path / "many", comm), timeout=120)
    assert all(s["N"] == one["N"] and s["steps"] == one["steps"] for s in many)
    _, arrays1 = load_run(tmp_path / "one" / case / f"{name}.npz")
    index_path = tmp_path / "many" / case / f"{name}.npz"
    record, arrays = load_run(index_path)
    sets = sorted(record["pieces"].get("sets", {}))
    assert sets == (["half"] if case == "advection" else [f"shot{i}" for i in range(len(drawn[0]))])
    for s in sets:
        got = read_pieces(index_path, record["pieces"], of=s)
        assert sorted(got) == ["D", "f", "keys", "x"] and not any(k.startswith(s) for k in arrays)
        assert all(got[k].tobytes() == arrays1[f"{s}_{k}"].tobytes() for k in "xfD" if case == "advection")
    state = np.load(tmp_path / "many" / case / "checkpoint.npz")
    assert not any(k.startswith(("record_half", "record_shot0")) for k in state.files)       # (rows: in pieces)
    assert len(drawn) == 2
    for a, b in zip(drawn[0].values(), drawn[1].values()):       # (one process; rank 0, from the pieces)
        assert all(a[k].tobytes() == b[k].tobytes() for k in ("x", "f", "D"))
    assert run_case(case, [*options, "--resume"], tmp_path / "many")["steps"] == one["steps"]
    _, resumed = load_run(tmp_path / "many" / case / f"{name}.npz")
    assert sorted(resumed) == sorted(arrays1)
    assert all(resumed[k].tobytes() == arrays1[k].tobytes() for k in arrays1 if not k.startswith("history_t_"))
    for a, b in zip(drawn[0].values(), drawn[2].values()):
        assert all(a[k].tobytes() == b[k].tobytes() for k in ("x", "f", "D"))
