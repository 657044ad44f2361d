"""The documentation: the Sphinx build passes with warnings as errors, the docstrings' examples
print what they show, and the getting-started page runs as written."""

from __future__ import annotations

import doctest
import importlib
import pkgutil
import re
import subprocess
import sys
from pathlib import Path

import pytest

import arpy

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def require(module: str) -> None:
    """Import a test dependency or fail the test: Sphinx and MyST are in pyproject.toml's ``test``
    extra, so a missing one is a broken test environment, not a reason to skip the docs build."""
    try:
        importlib.import_module(module)
    except ImportError as exc:
        pytest.fail(f"{module} is missing; it is a test dependency (pip install -e '.[test]'): {exc}")


def test_docs_build_with_warnings_as_errors(tmp_path):
    require("sphinx")
    require("myst_parser")
    require("furo")
    out = tmp_path / "html"
    run = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-b", "html", "-q",
                          str(DOCS), str(out)], capture_output=True, text=True, cwd=ROOT)
    assert run.returncode == 0, f"sphinx-build failed:\n{run.stdout}\n{run.stderr}"
    # the pages of every part, the API reference from the docstrings, the figures copied
    for page in ("index", "tour", "guide", "cases/pulse", "results/simulation", "api/lists"):
        assert (out / f"{page}.html").is_file(), page
    api = (out / "api" / "lists.html").read_text(encoding="utf-8")
    assert 'id="arpy.lists.search.neighbor_list"' in api
    assert "--mass-every" in (out / "cases" / "pulse.html").read_text(encoding="utf-8")
    assert (out / "_images" / "simulation_fig44.png").is_file()


def _arpy_modules():
    """arpy and every module in it (the private ones too: their examples must hold as well)."""
    names = ["arpy"] + [m.name for m in pkgutil.walk_packages(arpy.__path__, "arpy.")]
    return [importlib.import_module(name) for name in names if not name.endswith("__main__")]


def test_docstring_examples_print_what_they_show():
    finder, runner = doctest.DocTestFinder(), doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    tested = set()
    for module in _arpy_modules():
        for test in finder.find(module, module.__name__):
            if test.examples and test.name not in tested:
                tested.add(test.name)
                runner.run(test)
    results = runner.summarize(verbose=False)
    assert results.failed == 0, f"{results.failed} of {results.attempted} docstring examples failed (output above)"
    # the main entry points have examples
    for name in ("arpy.lists.search.neighbor_list", "arpy.lists.neighborlist.NeighborList", "arpy.lists.ar.ARCellList",
                 "arpy.lists.search.cross_neighbor_list", "arpy.domain.Domain", "arpy.dcpse.kernel.DCPSE",
                 "arpy.dcpse.domain.DomainDCPSE", "arpy.adapt.organize.self_organize", "arpy.particles.Particles",
                 "arpy.simulation.Simulation", "arpy.adapt.resolution.field_resolution"):
        assert name in tested, f"{name} has no example"


def test_getting_started_page_runs_as_written():
    page = DOCS / "tour.md"
    blocks = re.findall(r"```python\n(.*?)```", page.read_text(encoding="utf-8"), flags=re.S)
    assert len(blocks) >= 5, "the getting-started page has lost its examples"
    namespace = {"__name__": "tour"}
    for code in blocks:                  # one namespace: the blocks build on each other
        exec(compile(code, str(page), "exec"), namespace)


def test_the_guide_particle_container_example_runs_and_is_right(capsys):
    """The guide's example of arpy.particles.Particles (a box with lo != 0) runs as written, and what
    it prints is right: the count, the smallest spacing by the minimum image (brute force) and the
    exact sum of the field (math.fsum)."""
    import math

    import numpy as np

    page = (DOCS / "guide.md").read_text(encoding="utf-8")
    code = next(b for b in re.findall(r"```python\n(.*?)```", page, flags=re.S) if "Particles.dealt" in b)
    namespace = {"__name__": "guide"}
    exec(compile(code, "guide.md", "exec"), namespace)
    n, total, h, s = capsys.readouterr().out.split()
    x = namespace["x"]
    e = x[:, None, :] - x[None, :, :]
    e[..., 0] -= 3.0 * np.round(e[..., 0] / 3.0)
    dist = np.sqrt((e ** 2).sum(axis=2))
    np.fill_diagonal(dist, np.inf)
    assert int(n) == int(total) == len(x)
    assert float(h) == dist.min() and float(s) == math.fsum(np.sin(x[:, 0]))
