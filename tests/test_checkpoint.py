"""Checkpoint and restart of ``arpy run``: a run killed after a checkpoint and resumed with
--resume writes the same results, bit for bit, as one that was never interrupted; --json prints
a machine-readable summary."""

import json

import numpy as np
import pytest

from arpy.cli import main
from arpy.simulation import Simulation


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
    args = ["run", case, *CASES[case], "--quiet", "--checkpoint-every", "2"]
    assert main(args + ["--out", str(tmp_path / "whole")]) == 0
    steps = json.loads((tmp_path / "whole" / case / "checkpoint.json").read_text())["parameters"]["steps"]
    assert steps >= 4
    step = Simulation.step

    def dying(self, dt=None):
        if self.steps == steps - 1:        # after the last checkpoint but one
            raise Killed
        return step(self, dt)

    monkeypatch.setattr(Simulation, "step", dying)
    with pytest.raises(Killed):
        main(args + ["--out", str(tmp_path / "cut")])
    monkeypatch.setattr(Simulation, "step", step)
    assert not (tmp_path / "cut" / case / FILES[case]).exists()
    assert main(args + ["--out", str(tmp_path / "cut"), "--resume"]) == 0
    with np.load(tmp_path / "whole" / case / FILES[case]) as a, np.load(tmp_path / "cut" / case / FILES[case]) as b:
        assert set(a.files) == set(b.files)
        for key in set(a.files) - {"parameters"}:
            if key.startswith("history_t_"):           # wall-clock times of the phases
                continue
            assert a[key].dtype == b[key].dtype and np.array_equal(a[key], b[key], equal_nan=True), key


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
