"""The README's tour runs as written, and its sample output of the main job is generated."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_blocks_run():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README has no python example"
    for code in blocks:
        exec(compile(code, str(README), "exec"), {"__name__": "readme"})


def _main_job_script():
    """benchmarks/main_job.py as a module (not run)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("arpy_main_job", README.parent / "benchmarks" / "main_job.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_readme_main_job_output_is_what_its_json_renders():
    """The README's sample output of the main job is benchmarks/main_job.py's rendering of the stored run
    (the case's own printing functions applied to the run's --json summary)."""
    import json

    job = _main_job_script()
    stored = json.loads(job.JSON.read_text())
    assert job.readme_block(README.read_text(encoding="utf-8")) == job.render(stored)
    summary = stored["record"]["summary"]
    assert stored["record"]["case"] == "pulse" and summary["steps"] >= len(stored["prefix"]["n"])


def test_main_job_json_is_the_run_of_this_code(monkeypatch, tmp_path):
    """The stored main job is what this code runs: its first steps (two re-organizations), re-run from
    `arpy run`'s current defaults, equal the stored ones bit for bit (t, L-infinity error, N) and so does
    the initial particle count.  (A change that moves the main job's results fails here: re-run
    benchmarks/main_job.py.)  About 1.5 s."""
    import json

    import numpy as np

    from arpy.cases import pulse
    from arpy.cli import main

    job = json.loads(_main_job_script().JSON.read_text())
    prefix, real, runs = job["prefix"], pulse.gaussian_pulse, []

    class Stop(Exception):
        pass

    def first_steps(**kwargs):
        # the main job's own arguments (the CLI's defaults), to the time of the stored prefix; the mass
        # (start and end only) on a coarse mesh: it does not feed back into the run
        kwargs.update(T=prefix["t"][-1], mass_every=0, mass_points=11, progress=False)
        runs.append(real(**kwargs))
        raise Stop

    monkeypatch.setattr(pulse, "gaussian_pulse", first_steps)
    with pytest.raises(Stop):
        main(["run", "--quiet", "--out", str(tmp_path)])
    r = runs[0]
    assert r["N_initial"] == job["record"]["summary"]["N_initial"]
    assert r["steps"] == len(prefix["n"])
    assert r["error_history"][:, 0].tolist() == prefix["t"]
    assert r["error_history"][:, 1].tolist() == prefix["error"]
    assert np.asarray(r["sim"].history()["n"]).tolist() == prefix["n"]
