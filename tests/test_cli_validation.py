"""`arpy run` and `arpy demo` check every option before any work: a bad one ends the
command with exit code 2 and a one-line error naming the option, without a traceback."""

from __future__ import annotations

import inspect
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import arpy
from arpy import cases, distributions
from arpy.cli import main

CASE_FUNCTIONS = ("gaussian_pulse", "remeshed_pulse", "advection", "burgers", "remeshed_burgers", "five_spot",
                  "bud_surface", "consistency", "manufactured")


class Called(Exception):
    """Raised by a stand-in for a case function."""


def replace_case_function(monkeypatch, name: str, stand_in) -> None:
    """Replaces the case function ``name`` in arpy.cases and in the section module that defines it
    (whose runner calls it)."""
    owner, = (m for m in vars(cases).values() if inspect.ismodule(m) and name in getattr(m, "__all__", ()))
    monkeypatch.setattr(owner, name, stand_in)
    monkeypatch.setattr(cases, name, stand_in)


@pytest.fixture(autouse=True)
def no_work(monkeypatch, tmp_path):
    """Every case function (and the demo's distribution) fails the test if called, and
    outputs go to a temporary folder: an option must be refused before any work."""
    def refuse(*args, **kwargs):
        raise AssertionError("work started before the options were checked")

    for name in CASE_FUNCTIONS:
        replace_case_function(monkeypatch, name, refuse)
    monkeypatch.setattr(distributions, "ar_benchmark", refuse)
    monkeypatch.chdir(tmp_path)


def refused(argv: list[str], capsys) -> str:
    """Run ``arpy argv``, assert exit code 2; return the error line."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and err[-1].startswith(f"arpy {argv[0]}") and ": error: " in err[-1]
    return err[-1]


BAD = [
    # (argv, words the error line must contain)
    (["run", "pulse", "--T", "nan"], ["--T", "nan", "> 0"]),
    (["run", "--T", "0"], ["--T", "> 0"]),
    (["run", "--T", "-1"], ["--T", "> 0"]),
    (["run", "advection", "--T", "inf"], ["--T", "finite"]),
    (["run", "five-spot", "--T", "0"], ["--T", "> 0"]),
    (["run", "--pe", "0"], ["--pe", "Peclet", "> 0"]),
    (["run", "--pe", "-5"], ["--pe", "> 0"]),
    (["run", "--pe", "inf"], ["--pe", "finite"]),
    (["run", "burgers", "--re", "0"], ["--re", "Reynolds", "> 0"]),
    (["run", "burgers", "--re", "inf"], ["--re", "finite"]),
    (["run", "five-spot", "--mu", "0"], ["--mu", "viscosity ratio", "> 0"]),
    (["run", "five-spot", "--mu", "-1"], ["--mu", "> 0"]),
    (["run", "five-spot", "--nu", "-0.01"], ["--nu", ">= 0"]),
    (["run", "five-spot", "--nu", "nan"], ["--nu", "finite"]),
    (["run", "--remeshed", "-4"], ["--remeshed", ">= 0"]),
    (["run", "--d", "3", "--remeshed", "1000"], ["--remeshed", "5e+06"]),
    (["run", "--D0", "1e-6"], ["--D0", "particles", "5e+06", ">= 0.000894"]),
    (["run", "--d", "3", "--D0", "0.01"], ["--D0", "particles", ">= 0.0175"]),
    (["run", "bud-surface", "--D0", "1e-3"], ["--D0", "particles", "2e+07", ">= 0.00368"]),
    (["run", "--D0", "0"], ["--D0", "> 0"]),
    (["run", "--D0", "-0.1"], ["--D0", "> 0"]),
    (["run", "--D0", "nan"], ["--D0", "finite"]),
    (["run", "five-spot", "--D0", "inf"], ["--D0", "finite"]),
    (["run", "manufactured", "--D0", "0.1", "-0.05"], ["--D0", "-0.05", "> 0"]),
    (["run", "manufactured", "--walls", "slip"], ["--walls", "invalid choice"]),
    (["run", "burgers", "--D0", "0"], ["--D0", "> 0"]),
    (["run", "burgers", "--D0", "0.3"], ["--D0", "periodic", "give 0.52"]),
    (["run", "advection", "--reach", "2"], ["--D0", "periodic", "--reach 2"]),
    (["run", "consistency", "--D0-end", "0.39"], ["--D0-end", "<= 0.361"]),
    (["run", "consistency", "--field", "blob", "--D0-end", "0.24"], ["--D0-end", "<= 0.226"]),
    (["run", "consistency", "--D0", "0.3"], ["--D0 0.3", "unrecognized", "--D0-end"]),
    (["run", "consistency", "--field", "blob", "--reach", "2"], ["--reach", "periodic", "give 0.866"]),
    (["run", "burgers", "--d", "3", "--mu", "7"], ["arpy run burgers", "unrecognized arguments: --d 3 --mu 7",
                                                   "case burgers takes", "--re"]),
    (["run", "burgers", "--d", "2"], ["unrecognized arguments: --d 2"]),
    (["run", "consistency", "--T", "1"], ["unrecognized arguments: --T 1", "case consistency"]),
    (["run", "pulse", "--field", "blob"], ["unrecognized arguments: --field blob", "case pulse"]),
    (["run", "five-spot", "--monitor", "fourth"], ["unrecognized arguments: --monitor fourth", "case five-spot"]),
    (["run", "--L", "0.4"], ["unrecognized arguments: --L 0.4", "case pulse"]),
    (["run", "bud-surface", "--reach", "2"], ["unrecognized arguments: --reach 2", "case bud-surface"]),
    (["run", "bud-surface", "--k", "4"], ["unrecognized arguments: --k 4", "case bud-surface"]),
    (["run", "pulse", "--mass", "4"], ["unrecognized arguments: --mass 4"]),
    (["run", "sphere"], ["invalid choice: 'sphere'"]),
    (["run", "--k", "-1"], ["--k", ">= 0"]),
    (["run", "--mass-every", "-3"], ["--mass-every", ">= 0"]),
    (["run", "--reach", "0"], ["--reach", ">= 1"]),
    (["run", "--reach", "0.5"], ["--reach", ">= 1"]),
    (["run", "five-spot", "--reach", "nan"], ["--reach", "finite"]),
    (["run", "--seed", "-1"], ["--seed", ">= 0"]),
    (["run", "bud-surface", "--L", "0.4", "0.6"], ["--L", "0.6", "pinched off"]),
    (["run", "bud-surface", "--L", "0"], ["--L", "> 0"]),
    (["run", "bud-surface", "--L", "nan"], ["--L", "finite"]),
    (["run", "bud-surface", "--L", "0.1"], ["--L", "too small"]),
    (["run", "--pe", "1e-300"], ["--pe", "more than 1e+07 time steps"]),
    (["run", "pulse", "--T", "1e12"], ["--pe", "--T 1e+12", "more than 1e+07 time steps"]),
    (["run", "burgers", "--re", "1e-12"], ["--re", "more than 1e+07 time steps"]),
    (["run", "five-spot", "--nu", "1e9"], ["--nu", "more than 1e+07 time steps"]),
    (["demo", "--n", "-5"], ["--n", ">= 1"]),
    (["demo", "--n", "0"], ["--n", ">= 1"]),
    (["demo", "--lam", "0.5"], ["--lam", ">= 1"]),
    (["demo", "--lam", "nan"], ["--lam", "finite"]),
    (["demo", "--repeat", "0"], ["--repeat", ">= 1"]),
    (["demo", "--brute-max", "-1"], ["--brute-max", ">= 0"]),
]


@pytest.mark.parametrize("argv, words", BAD, ids=[" ".join(a) for a, _ in BAD])
def test_bad_option_is_refused_before_any_work(argv, words, capsys):
    line = refused(argv, capsys)
    for word in words:
        assert word in line


def test_out_must_be_a_folder(tmp_path, capsys):
    (tmp_path / "taken").write_text("")
    assert "--out" in refused(["run", "--out", str(tmp_path / "taken")], capsys)
    assert "--out" in refused(["run", "--out", str(tmp_path / "taken" / "below")], capsys)


UNUSABLE = [pytest.param(lambda tmp: tmp / ("x" * 300), "File name too long", id="name too long"),
            pytest.param(lambda tmp: Path("/proc/arpy-out"), "/proc", id="/proc",
                         marks=pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="no /proc")),
            pytest.param(lambda tmp: tmp / "locked" / "out", "Permission denied", id="read-only folder",
                         marks=pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0,
                                                  reason="root writes into read-only folders"))]


@pytest.mark.parametrize("where, reason", UNUSABLE)
def test_out_that_cannot_be_written_is_refused_with_the_reason(where, reason, tmp_path, capsys):
    """Checked by making a folder there (os.access passed /proc for root, and a name too long raised
    OSError from the check): one error line with the system's reason, before any work."""
    (tmp_path / "locked").mkdir(mode=0o500)
    line = refused(["run", "--out", str(where(tmp_path))], capsys)
    assert "argument --out" in line and "can be written" in line and reason in line
    assert not [p for p in tmp_path.rglob("*") if p.name != "locked"]          # (the probe left nothing)


@pytest.mark.parametrize("argv, error", [(["run", "--T", "0"], "arpy run pulse: error: argument --T: 0.0: "),
                                         (["run", "burgers", "--d", "3", "--mu", "7"],
                                          "arpy run burgers: error: unrecognized arguments: --d 3 --mu 7; "),
                                         (["run", "--out", "x" * 300], "arpy run pulse: error: argument --out: x")])
def test_command_exits_2_without_traceback(argv, error, tmp_path):
    out = subprocess.run([sys.executable, "-m", "arpy", *argv], capture_output=True, text=True, cwd=tmp_path,
                         timeout=120)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr
    assert out.stderr.strip().splitlines()[-1].startswith(error)
    assert not (tmp_path / "arpy-output").exists()


def test_run_help_lists_each_case_options(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["run", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "--remeshed" in out
    lines = dict(re.findall(r"^ +([a-z-]+): +(--.*)$", out, flags=re.M))
    assert "--re" in lines["burgers"] and "--mu" not in lines["burgers"]
    assert "--L" in lines["bud-surface"] and "--T" not in lines["bud-surface"]
    assert "--pe" in lines["pulse"] and "--mass-every" in lines["pulse"]
    assert "--field" in lines["consistency"] and "--nu" in lines["five-spot"]


CALLS = [
    # (argv, case function, the arguments it is called with: the defaults of a valid command stay as they were;
    # comm: None when not started by mpiexec)
    (["run"], "gaussian_pulse",
     dict(d=2, Pe=1000.0, D0=0.08, T=1.0, reorganize_every=10, seed=1, mass_every=20, reach=1.0, monitor="gradient",
          progress=False, comm=None)),
    (["run", "pulse", "--d", "3", "--monitor", "fourth"], "gaussian_pulse",
     dict(d=3, Pe=100.0, D0=1.0, T=1.0, reorganize_every=10, seed=1, mass_every=20, reach=1.0, monitor="fourth",
          progress=False, comm=None)),
    (["run", "pulse", "--d", "3", "--pe", "50", "--D0", "0.4", "--T", "0.5", "--k", "5", "--mass-every", "0",
      "--reach", "2", "--monitor", "fourth", "--seed", "0"], "gaussian_pulse",
     dict(d=3, Pe=50.0, D0=0.4, T=0.5, reorganize_every=5, seed=0, mass_every=0, reach=2.0, monitor="fourth",
          progress=False, comm=None)),
    (["run", "advection"], "advection",
     dict(D0=0.2, T=2.5, reorganize_every=4, seed=1, reach=1.0, monitor="gradient", progress=False, comm=None)),
    (["run", "advection", "--monitor", "fourth", "--k", "0"], "advection",
     dict(D0=0.25, T=2.5, reorganize_every=0, seed=1, reach=1.0, monitor="fourth", progress=False, comm=None)),
    (["run", "burgers"], "burgers",
     dict(Re=100.0, D0=0.1, T=0.1, reorganize_every=10, seed=1, reach=1.0, progress=False, comm=None)),
    (["run", "burgers", "--re", "1000", "--T", "0.17", "--D0", "0.15"], "burgers",
     dict(Re=1000.0, D0=0.15, T=0.17, reorganize_every=10, seed=1, reach=1.0, progress=False, comm=None)),
    (["run", "five-spot", "--nu", "0"], "five_spot",
     dict(mu=0.5, nu=0.0, D0=0.1, T=0.09, reorganize_every=10, seed=1, reach=1.0, progress=False, comm=None)),
    (["run", "consistency"], "consistency",
     dict(d0_start=0.4, d0_end=0.1, seed=1, reach=1.0, field="tanh", monitor="gradient", progress=False, comm=None)),
    (["run", "consistency", "--field", "blob", "--D0-end", "0.22"], "consistency",
     dict(d0_start=0.25, d0_end=0.22, seed=1, reach=1.0, field="blob", monitor="gradient", progress=False,
          comm=None)),
    (["run", "bud-surface", "--L", "0.45", "0.4"], "bud_surface",
     dict(D0=0.1, Dmin=None, seed=1, progress=False, comm=None)),
    (["run", "manufactured", "--walls", "neumann", "--D0", "0.08", "0.06", "--k", "0"], "manufactured",
     dict(walls="neumann", T=0.5, reorganize_every=0, seed=1, progress=False, series=None, comm=None)),
]


@pytest.mark.parametrize("argv, name, expected", CALLS, ids=[" ".join(a) for a, _, _ in CALLS])
def test_valid_command_calls_the_case_with_its_defaults(argv, name, expected, monkeypatch):
    calls = []

    def record(*args, **kwargs):
        calls.append((args, kwargs))
        raise Called

    replace_case_function(monkeypatch, name, record)
    with pytest.raises(Called):
        main([*argv, "--quiet"])
    args, kwargs = calls[0]
    checkpoint = kwargs.pop("checkpoint", None)          # the time-stepping cases: no checkpoint asked for
    assert kwargs == expected
    assert args == {"bud_surface": (0.45,), "manufactured": (0.08,)}.get(name, ())
    if name in ("gaussian_pulse", "advection", "burgers", "five_spot"):
        assert checkpoint.every == 0 and not checkpoint.resume and checkpoint.series is None     # (no --output-every)
    else:
        assert checkpoint is None


def test_case_help_shows_its_options_with_defaults_and_units(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["run", "advection", "--help"])
    assert exc.value.code == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "--D0" in out and "a length" in out and "0.2 with --monitor gradient, 0.25 with --monitor fourth" in out
    assert "(default: 2.5)" in out and "--pe" not in out and "--remeshed" not in out
    with pytest.raises(SystemExit):
        main(["run", "consistency", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "--D0-end" in out and "(default: 0.1)" in out and "0.4 (tanh) or 0.25 (blob)" in out


def test_every_case_help_states_its_run_time_at_the_defaults(capsys):
    """Each case's --help gives its measured run time at the defaults and the machine it was measured on
    (Case.seconds); the advection case's minute-long default run is not a surprise."""
    from arpy.cases.registry import RUN_TIME_MACHINE

    for name, case in cases.CASES.items():
        assert case.seconds > 0, name
        with pytest.raises(SystemExit):
            main(["run", name, "--help"])
        out = " ".join(capsys.readouterr().out.split())
        assert f"At the defaults it takes about {case.run_time().split('about ')[1]}" in out, name
        assert RUN_TIME_MACHINE in out
    import dataclasses

    pulse = cases.CASES["pulse"]
    assert dataclasses.replace(pulse, seconds=6.4).run_time().startswith("At the defaults it takes about 6 s (")
    assert "about 3 min" in dataclasses.replace(pulse, seconds=170).run_time()
    assert dataclasses.replace(pulse, seconds=0).run_time() == ""


def test_one_default_seed_for_self_organize_simulation_and_every_case(monkeypatch):
    """The seed policy (arpy.adapt.organize.DEFAULT_SEED): self_organize, Simulation, every case function
    and every case's --seed default to the same seed."""
    from arpy.adapt.organize import DEFAULT_SEED

    monkeypatch.undo()                                  # the case functions themselves, not no_work's stand-ins

    def default(function):
        return inspect.signature(function).parameters["seed"].default

    assert default(arpy.self_organize) == default(arpy.Simulation) == DEFAULT_SEED == 1
    for name, case in cases.CASES.items():
        seed = next(p for p in case.params if p.flag == "--seed")
        assert seed.default == default(getattr(cases, seed.function)) == DEFAULT_SEED, name


def test_registry_defaults_are_the_case_functions_defaults(monkeypatch):
    """One source per default: a parameter that sets a keyword of a case function has that function's
    default (a list of it for --L), or None with a rule of the case's module (``default_for``)
    that the function also applies to None."""
    monkeypatch.undo()                                  # the case functions themselves, not no_work's stand-ins
    modules = {sys.modules[case.run.__module__] for case in cases.CASES.values()}
    checked = 0
    for case in cases.CASES.values():
        module = sys.modules[case.run.__module__]
        for p in case.params:
            if p.function is None:
                continue
            default = inspect.signature(getattr(module, p.function)).parameters[p.keyword].default
            assert p.default == ([default] if p.nargs else default), (case.name, p.flag)
            assert (p.default_for is None) == (default is not None), (case.name, p.flag)
            checked += 1
    assert len(modules) == len(cases.CASES) and checked >= 35


@pytest.mark.parametrize("argv, function, keyword, resolve", [
    (["run", "pulse", "--d", "3"], "gaussian_pulse", "Pe", lambda a: cases.pulse_pe(a["d"])),
    (["run", "pulse", "--d", "3", "--monitor", "fourth"], "gaussian_pulse", "D0",
     lambda a: cases.pulse_d0(a["d"], a["monitor"])),
    (["run", "advection", "--monitor", "fourth"], "advection", "D0", lambda a: cases.advection_d0(a["monitor"]))])
def test_default_rules_are_the_functions(argv, function, keyword, resolve, monkeypatch):
    """Where the CLI fills in a default that depends on other options, it is the function's own rule."""
    calls = []

    def record(*args, **kwargs):
        calls.append(kwargs)
        raise Called

    replace_case_function(monkeypatch, function, record)
    with pytest.raises(Called):
        main([*argv, "--quiet"])
    assert calls[0][keyword] == resolve(calls[0])



def test_resume_before_the_time_of_the_checkpoint_is_refused(monkeypatch, capsys):
    """--resume with a --T before the checkpoint's time printed Simulation.run's traceback ("T must be
    >= the current time") after loading the state; a checkpoint that cannot be read, a zip traceback.
    Both are now one error line before any work, naming the file.  (The first run, a stand-in for the
    case, writes the files through its checkpoint: 40 particles stepped once to t = 0.5.)"""
    def first_run(**kwargs):
        cp = kwargs["checkpoint"]
        x = np.random.default_rng(0).random((40, 2))
        ps = cp.particles(lambda: arpy.Particles(x, np.full(40, 0.3), 2.0, 6, domain=arpy.Domain([1, 1])))
        sim = arpy.Simulation(ps, x[:, 0], nu=0.01, D0=0.3, dt=0.5, reorganize_every=0)
        cp.run(sim, 0.5)                       # (one step, then the state with the run's parameters)
        raise Called

    replace_case_function(monkeypatch, "gaussian_pulse", first_run)
    with pytest.raises(Called):
        main(["run", "--T", "1", "--checkpoint-every", "1", "--quiet"])
    def no_work(**kwargs):
        raise AssertionError("work started before the options were checked")

    replace_case_function(monkeypatch, "gaussian_pulse", no_work)
    line = refused(["run", "--T", "0.2", "--resume"], capsys)
    assert "argument --T: 0.2: must be >= 0.5, the time of the checkpoint to resume" in line
    assert str(Path("arpy-output", "pulse", "checkpoint.npz")) in line

    def resumed(**kwargs):
        raise Called

    replace_case_function(monkeypatch, "gaussian_pulse", resumed)
    for T in ("0.5", "2"):
        with pytest.raises(Called):
            main(["run", "--T", T, "--resume", "--quiet"])
    path = Path("arpy-output", "pulse", "checkpoint.npz")
    path.write_bytes(path.read_bytes()[:200])                                 # truncated
    line = refused(["run", "--T", "2", "--resume"], capsys)
    assert line.endswith(f"argument --resume: {path} is not a readable arpy state file: it is not a NumPy archive "
                         "(.npz): truncated, or another kind of file")
