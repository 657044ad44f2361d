"""`arpy run` and `arpy demo` check every option before any work: a bad one ends the
command with exit code 2 and a one-line error naming the option, without a traceback."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from arpy import cases, distributions
from arpy.cli import main

CASE_FUNCTIONS = ("gaussian_pulse", "remeshed_pulse", "advection", "burgers", "remeshed_burgers", "five_spot",
                  "bud_surface", "consistency")


class Called(Exception):
    """Raised by a stand-in for a case function."""


@pytest.fixture(autouse=True)
def no_work(monkeypatch, tmp_path):
    """Every case function (and the demo's distribution) fails the test if called, and
    outputs go to a temporary folder: an option must be refused before any work."""
    def refuse(*args, **kwargs):
        raise AssertionError("work started before the options were checked")

    for name in CASE_FUNCTIONS:
        monkeypatch.setattr(cases, name, refuse)
    monkeypatch.setattr(distributions, "ar_benchmark", refuse)
    monkeypatch.chdir(tmp_path)


def refused(argv: list[str], capsys) -> str:
    """Run ``arpy argv``, assert exit code 2; return the error line."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and err[-1].startswith(f"arpy {argv[0]}: error: ")
    return err[-1]


BAD = [
    # the command line | the words its error line must contain
    "run pulse --T nan | --T | nan | > 0",
    "run --T 0 | --T | > 0",
    "run --T -1 | --T | > 0",
    "run advection --T inf | --T | finite",
    "run five-spot --T 0 | --T | > 0",
    "run --pe 0 | --pe | Peclet | > 0",
    "run --pe -5 | --pe | > 0",
    "run --pe inf | --pe | finite",
    "run burgers --re 0 | --re | Reynolds | > 0",
    "run burgers --re inf | --re | finite",
    "run five-spot --mu 0 | --mu | viscosity ratio | > 0",
    "run five-spot --mu -1 | --mu | > 0",
    "run five-spot --nu -0.01 | --nu | >= 0",
    "run five-spot --nu nan | --nu | finite",
    "run --remeshed -4 | --remeshed | >= 0",
    "run --d 3 --remeshed 1000 | --remeshed | 5e+06",
    "run --D0 1e-6 | --D0 | particles | 5e+06 | >= 0.000894",
    "run --d 3 --D0 0.01 | --D0 | particles | >= 0.0175",
    "run bud-surface --D0 1e-3 | --D0 | particles | 2e+07 | >= 0.00368",
    "run --D0 0 | --D0 | > 0",
    "run --D0 -0.1 | --D0 | > 0",
    "run --D0 nan | --D0 | finite",
    "run five-spot --D0 inf | --D0 | finite",
    "run burgers --D0 0 | --D0 | > 0",
    "run burgers --D0 0.3 | --D0 | periodic | give 0.52",
    "run advection --reach 2 | --D0 | periodic | --reach 2",
    "run consistency --D0 0.39 | --D0 | <= 0.361",
    "run consistency --field blob --D0 0.24 | --D0 | <= 0.226",
    "run consistency --field blob --reach 2 | --reach | periodic | give 0.866",
    "run burgers --d 3 --mu 7 | --d | --mu | do not apply to case burgers | --re",
    "run burgers --d 2 | --d | does not apply to case burgers",
    "run consistency --T 1 | --T | does not apply to case consistency",
    "run pulse --field blob | --field | does not apply to case pulse",
    "run five-spot --monitor fourth | --monitor | does not apply to case five-spot",
    "run --L 0.4 | --L | does not apply to case pulse",
    "run bud-surface --reach 2 | --reach | does not apply to case bud-surface",
    "run bud-surface --k 4 | --k | does not apply to case bud-surface",
    "run --k -1 | --k | >= 0",
    "run --mass-every -3 | --mass-every | >= 0",
    "run --reach 0 | --reach | >= 1",
    "run --reach 0.5 | --reach | >= 1",
    "run five-spot --reach nan | --reach | finite",
    "run --seed -1 | --seed | >= 0",
    "run bud-surface --L 0.4 0.6 | --L | 0.6 | pinched off",
    "run bud-surface --L 0 | --L | > 0",
    "run bud-surface --L nan | --L | finite",
    "run bud-surface --L 0.1 | --L | too small",
    "demo --n -5 | --n | >= 1",
    "demo --n 0 | --n | >= 1",
    "demo --lam 0.5 | --lam | >= 1",
    "demo --lam nan | --lam | finite",
    "demo --repeat 0 | --repeat | >= 1",
    "demo --brute-max -1 | --brute-max | >= 0",
]


@pytest.mark.parametrize("row", BAD, ids=[row.split(" | ")[0] for row in BAD])
def test_bad_option_is_refused_before_any_work(row, capsys):
    command, *words = row.split(" | ")
    line = refused(command.split(), capsys)
    for word in words:
        assert word in line


def test_out_must_be_a_folder(tmp_path, capsys):
    (tmp_path / "taken").write_text("")
    assert "--out" in refused(["run", "--out", str(tmp_path / "taken")], capsys)
    assert "--out" in refused(["run", "--out", str(tmp_path / "taken" / "below")], capsys)


@pytest.mark.parametrize("argv, error", [(["run", "--T", "0"], "arpy run: error: argument --T: 0.0: "),
                                         (["run", "burgers", "--d", "3", "--mu", "7"],
                                          "arpy run: error: --d, --mu do not apply to case burgers")])
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
    # (argv, case function, the arguments it is called with: the defaults of a valid command stay as they were)
    (["run"], "gaussian_pulse",
     dict(d=2, Pe=None, D0=None, T=1.0, reorganize_every=10, seed=1, mass_every=10, reach=1.0, monitor="gradient",
          progress=False)),
    (["run", "pulse", "--d", "3", "--pe", "50", "--D0", "0.4", "--T", "0.5", "--k", "5", "--mass-every", "0",
      "--reach", "2", "--monitor", "fourth", "--seed", "0"], "gaussian_pulse",
     dict(d=3, Pe=50.0, D0=0.4, T=0.5, reorganize_every=5, seed=0, mass_every=0, reach=2.0, monitor="fourth",
          progress=False)),
    (["run", "advection"], "advection",
     dict(D0=0.2, T=2.5, reorganize_every=4, seed=1, reach=1.0, monitor="gradient", progress=False)),
    (["run", "advection", "--monitor", "fourth", "--k", "0"], "advection",
     dict(D0=0.25, T=2.5, reorganize_every=0, seed=1, reach=1.0, monitor="fourth", progress=False)),
    (["run", "burgers"], "burgers",
     dict(Re=100.0, D0=0.1, T=0.1, reorganize_every=10, seed=1, reach=1.0, progress=False)),
    (["run", "burgers", "--re", "1000", "--T", "0.17", "--D0", "0.15"], "burgers",
     dict(Re=1000.0, D0=0.15, T=0.17, reorganize_every=10, seed=1, reach=1.0, progress=False)),
    (["run", "five-spot", "--nu", "0"], "five_spot",
     dict(mu=0.5, nu=0.0, D0=0.1, T=0.09, reorganize_every=10, seed=1, reach=1.0, progress=False)),
    (["run", "consistency"], "consistency",
     dict(d0_start=0.4, d0_end=0.2, seed=1, reach=1.0, field="tanh", monitor="gradient", progress=False)),
    (["run", "consistency", "--field", "blob", "--D0", "0.22"], "consistency",
     dict(d0_start=0.25, d0_end=0.22, seed=1, reach=1.0, field="blob", monitor="gradient", progress=False)),
    (["run", "bud-surface", "--L", "0.45", "0.4"], "bud_surface",
     dict(D0=0.1, Dmin=None, seed=1, progress=False)),
]


@pytest.mark.parametrize("argv, name, expected", CALLS, ids=[" ".join(a) for a, _, _ in CALLS])
def test_valid_command_calls_the_case_with_its_defaults(argv, name, expected, monkeypatch):
    calls = []

    def record(*args, **kwargs):
        calls.append((args, kwargs))
        raise Called

    monkeypatch.setattr(cases, name, record)
    with pytest.raises(Called):
        main([*argv, "--quiet"])
    args, kwargs = calls[0]
    assert kwargs == expected
    assert args == ((0.45,) if name == "bud_surface" else ())
