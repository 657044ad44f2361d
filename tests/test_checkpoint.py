"""Checkpoint and restart of ``arpy run``: a run killed after a checkpoint and resumed with
--resume writes the same results, bit for bit, as one that was never interrupted (its time series of
--output-every too); --json prints a machine-readable summary."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import arpy
import arpy.state
from arpy.cases import pulse
from arpy.cli import main
from arpy.simulation import Simulation
from test_cli_validation import refused
from test_simulation import damage


class Killed(Exception):
    """Stands for the end of a process in the middle of a run."""


# case options: 6 to 10 steps, re-organizations (with random insertions) on both sides of a checkpoint, and
# the records of each case's callback (error and mass histories; a snapshot at T/2; snapshots at given times)
CASES = {
    "pulse": ["--D0", "0.3", "--T", "0.3", "--k", "3", "--remeshed", "0"],
    "advection": ["--D0", "0.28", "--T", "0.15", "--k", "3"],
    "five-spot": ["--D0", "0.3", "--T", "0.004", "--k", "3"],
}
FILES = {"pulse": "pulse.npz", "advection": "advection.npz", "five-spot": "five_spot.npz"}


@pytest.mark.parametrize("case", list(CASES))
def test_a_resumed_run_equals_an_uninterrupted_one_bitwise(case, tmp_path, monkeypatch, capsys):
    args = ["run", case, *CASES[case], "--quiet", "--checkpoint-every", "2", "--output-every", "1"]
    assert main(args + ["--out", str(tmp_path / "whole")]) == 0
    steps = json.loads((tmp_path / "whole" / case / "checkpoint.json").read_text())["parameters"]["steps"]
    assert steps >= 4
    step = Simulation._step                    # (what run() and step() take every step through)

    def dying(self, dt):
        if self.steps == steps - 1:        # after the last checkpoint but one
            raise Killed
        return step(self, dt)

    monkeypatch.setattr(Simulation, "_step", dying)
    with pytest.raises(Killed):
        main(args + ["--out", str(tmp_path / "cut")])
    monkeypatch.setattr(Simulation, "_step", step)
    assert not (tmp_path / "cut" / case / FILES[case]).exists()
    # (read_state streams the whole state file through its checksums: the resume opens it once, for the
    # checks of the command line and the case, the simulation's state and the case's records)
    opened, real = [], arpy.state.open_results
    monkeypatch.setattr(arpy.state, "open_results", lambda path, *a, **k: opened.append(Path(path).resolve())
                        or real(path, *a, **k))
    assert main(args + ["--out", str(tmp_path / "cut"), "--resume"]) == 0
    assert opened.count((tmp_path / "cut" / case / "checkpoint.npz").resolve()) == 1
    with np.load(tmp_path / "whole" / case / FILES[case]) as a, np.load(tmp_path / "cut" / case / FILES[case]) as b:
        assert set(a.files) == set(b.files)
        for key in set(a.files) - {"parameters"}:
            if key.startswith("history_t_"):           # wall-clock times of the phases
                continue
            assert a[key].dtype == b[key].dtype and np.array_equal(a[key], b[key], equal_nan=True), key
    # the time series of --output-every goes on from the checkpoint: the same frames (and files) as the whole run's
    series = f"{FILES[case][:-4]}_series"
    whole, cut = (tmp_path / run / case for run in ("whole", "cut"))
    assert (cut / f"{series}.pvd").read_text() == (whole / f"{series}.pvd").read_text()
    frames = sorted(p.name for p in (whole / series).iterdir())
    total = json.loads((whole / FILES[case].replace(".npz", ".json")).read_text())["summary"]["steps"]
    assert len(frames) == total + 1 and sorted(p.name for p in (cut / series).iterdir()) == frames
    for name in frames:
        assert (cut / series / name).read_bytes() == (whole / series / name).read_bytes(), name


def test_resume_refuses_a_missing_checkpoint_or_other_options(tmp_path, capsys):
    out = ["--out", str(tmp_path), "--quiet"]
    with pytest.raises(SystemExit) as exc:
        main(["run", "advection", "--D0", "0.25", "--T", "0.05", "--resume", *out])
    assert exc.value.code == 2 and "nothing to resume" in capsys.readouterr().err
    assert main(["run", "advection", "--D0", "0.25", "--T", "0.05", "--checkpoint-every", "1", *out]) == 0
    with pytest.raises(SystemExit) as exc:
        main(["run", "advection", "--D0", "0.24", "--T", "0.1", "--resume", *out])
    assert exc.value.code == 2 and "D0 = 0.25 (now 0.24)" in capsys.readouterr().err
    assert main(["run", "advection", "--D0", "0.25", "--T", "0.1", "--resume", *out]) == 0   # a later T is fine


def test_json_summary(tmp_path, capsys):
    assert main(["run", "burgers", "--D0", "0.25", "--T", "0.01", "--remeshed", "8", "--quiet", "--json",
                 "--out", str(tmp_path)]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["case"] == "burgers" and record["parameters"]["D0"] == 0.25
    s = record["summary"]
    with np.load(tmp_path / "burgers" / "burgers.npz") as data:
        assert s["N"] == data["x"].shape[0]
        assert s["error"] == np.abs(data["f"] - data["f_reference"]).max()
    assert s["t"] == pytest.approx(0.01) and s["remeshed"]["N"] == 64
    assert sorted(p.rsplit("/", 1)[-1] for p in record["outputs"]) == [
        "burgers.json", "burgers.npz", "burgers.png", "burgers_particles.vtu"]


# ---------------------------------------------------------------- checkpoints that belong to their run

class Finished(Exception):
    """The end of :func:`tiny_pulse` (the case's runner, which would write its results, is not reached)."""


def tiny_pulse(*, D0, seed, checkpoint, T, **_):
    """A stand-in for the case function of ``arpy run pulse`` that goes through the case's checkpoint as
    the cases do: 40 particles, D0 and the seed from the options, steps of 0.1 up to T."""
    x = np.random.default_rng(seed).random((40, 2))
    box = arpy.Domain([1.0, 1.0], periodic=True)
    ps = checkpoint.particles(lambda: arpy.Particles(x, np.full(40, 0.3), 2.0, 6, domain=box))
    sim = arpy.Simulation(ps, x[:, 0], nu=0.01, D0=D0, dt=0.1, reorganize_every=0)
    raise Finished(checkpoint.run(sim, T))


def pulse_run(out, D0="0.3", *more):
    return ["run", "pulse", "--D0", D0, "--T", "0.4", "--quiet", "--out", str(out), *more]


def finished(argv) -> Simulation:
    with pytest.raises(Finished) as end:
        main(argv)
    return end.value.args[0]


def test_a_second_run_with_other_options_in_the_same_out_does_not_resume_the_first(tmp_path, monkeypatch, capsys):
    """A second run with other options in the same --out rewrote checkpoint_case.json but left the first
    run's checkpoint.npz, which --resume then continued under the second run's options.  Now the second
    run replaces the first's state when it starts (and says so): with no checkpoint of its own yet,
    --resume finds nothing to resume, with its options or the first run's.  (A second run that writes
    no checkpoint leaves the first's, which --resume refuses with other options: the test above.)"""
    monkeypatch.setattr(pulse, "gaussian_pulse", tiny_pulse)
    assert finished(pulse_run(tmp_path, "0.3", "--checkpoint-every", "1")).steps == 4
    capsys.readouterr()
    assert finished(pulse_run(tmp_path, "0.25", "--checkpoint-every", "10")).steps == 4      # (writes no state)
    note = capsys.readouterr().err
    for D0 in ("0.25", "0.3"):
        line = refused(pulse_run(tmp_path, D0, "--resume"), capsys)
        assert "argument --resume: True: nothing to resume" in line and "checkpoint.npz does not exist" in line
    assert "arpy: starting afresh: the checkpoint of an earlier run in" in note and "D0 = 0.3 (now 0.25)" in note


def test_a_checkpoint_copied_from_another_run_is_refused(tmp_path, monkeypatch, capsys):
    """A checkpoint.npz (or initial set) copied from a run with other options was resumed silently; now
    --resume refuses it, naming the file and the options that differ, and resumes the run's own."""
    monkeypatch.setattr(pulse, "gaussian_pulse", tiny_pulse)
    for out, D0 in (("a", "0.3"), ("b", "0.25")):
        finished(pulse_run(tmp_path / out, D0, "--checkpoint-every", "2"))
    a, b = tmp_path / "a" / "pulse", tmp_path / "b" / "pulse"
    for name in ("checkpoint.npz", "checkpoint_initial.npz"):
        shutil.copy(b / name, tmp_path / name)
        shutil.copy(a / name, b / name)
        line = refused(pulse_run(tmp_path / "b", "0.25", "--resume"), capsys)
        assert line.endswith(f"argument --resume: {b / name} belongs to another run than checkpoint_case.json: "
                             "D0 = 0.3 (now 0.25) (start the run afresh, without --resume)")
        shutil.copy(tmp_path / name, b / name)
    resumed = finished(pulse_run(tmp_path / "b", "0.25", "--resume") + ["--T", "0.6"])
    assert resumed.steps == 6 and resumed.D0 == 0.25


@pytest.mark.parametrize("kind", ["corrupted", "empty", "foreign archive"])
def test_a_damaged_checkpoint_gives_one_error_line(kind, tmp_path, monkeypatch, capsys):
    """A damaged or foreign checkpoint printed a traceback (BadZipFile, KeyError); now --resume ends
    with one error line naming the file before any work, and a checkpoint damaged after that check
    (when the run loads it) with one ``arpy: error:`` line and exit code 1."""
    monkeypatch.setattr(pulse, "gaussian_pulse", tiny_pulse)
    finished(pulse_run(tmp_path, "0.3", "--checkpoint-every", "2"))
    path = tmp_path / "pulse" / "checkpoint.npz"
    damage(kind, path, path.read_bytes())
    line = refused(pulse_run(tmp_path, "0.3", "--resume"), capsys)
    assert line.startswith(f"arpy run pulse: error: argument --resume: {path} is not a readable arpy state file: ")
    monkeypatch.setattr(arpy.cases.checkpoint.Checkpoint, "check", lambda self: None)
    assert main(pulse_run(tmp_path, "0.3", "--resume")) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"arpy: error: {path} is not a readable arpy state file: ") and "Traceback" not in err

