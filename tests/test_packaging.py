"""What an installed arpy says about itself: its distribution name and version, the typing marker,
and figures as an extra (matplotlib is not needed to run a case)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from importlib import metadata, resources
from pathlib import Path

import numpy as np

import arpy

ROOT = Path(__file__).resolve().parents[1]


def test_version_is_meson_project_version_and_the_cli_prints_it():
    meson = re.search(r"version:\s*'([^']+)'", (ROOT / "meson.build").read_text()).group(1)
    assert arpy.__version__ == meson == metadata.version("arpy-particles")
    out = subprocess.run([sys.executable, "-m", "arpy", "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == f"arpy {meson} (distribution arpy-particles)"


def test_distribution_metadata():
    meta = metadata.metadata("arpy-particles")
    assert meta["Name"] == "arpy-particles"
    assert "BSD" in (meta.get("License") or "") or any("BSD License" in c for c in meta.get_all("Classifier"))
    requires = metadata.requires("arpy-particles")
    core = [r for r in requires if "extra ==" not in r]
    assert not any(r.startswith("matplotlib") for r in core), "matplotlib belongs to the plot extra"
    assert any(r.startswith("matplotlib") and 'extra == "plot"' in r for r in requires)
    # the mpi extra brings an MPI library (the MPICH wheel) with mpi4py, not mpi4py alone
    assert {re.match(r"[\w-]+", r).group(0) for r in requires if 'extra == "mpi"' in r} == {"mpi4py", "mpich"}
    assert (resources.files("arpy") / "py.typed").is_file()


BLOCK_MATPLOTLIB = """
import sys, importlib.abc
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "matplotlib" or name.startswith("matplotlib."):
            raise ModuleNotFoundError(f"No module named {name!r}")
        return None
sys.meta_path.insert(0, Block())
import arpy
assert "matplotlib" not in sys.modules
from arpy.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_case_runs_without_matplotlib(tmp_path):
    """Without matplotlib (no plot extra) `arpy run` writes its data and says which figure it left out;
    the data file records the options and the version."""
    out = subprocess.run([sys.executable, "-c", BLOCK_MATPLOTLIB, "run", "advection", "--D0", "0.25", "--T", "0.05",
                          "--out", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "advection.png not drawn: matplotlib is not installed" in out.stdout
    files = {p.name for p in (tmp_path / "advection").iterdir()}
    assert "advection.npz" in files and "advection.png" not in files
    # the results carry what made them: the case's options and the arpy version (also as JSON)
    meta = json.loads(str(np.load(tmp_path / "advection" / "advection.npz")["parameters"]))
    assert meta == json.loads((tmp_path / "advection" / "advection.json").read_text())
    assert meta["arpy_version"] == arpy.__version__
    assert meta["parameters"]["case"] == "advection" and meta["parameters"]["D0"] == 0.25
    assert meta["parameters"]["T"] == 0.05 and meta["parameters"]["seed"] == 1
