"""The documentation: the Sphinx build passes with warnings as errors, the docstrings' examples
print what they show, and the getting-started page runs as written."""

from __future__ import annotations

import doctest
import importlib
import importlib.util
import pickle
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
    """Fail the test if a test dependency is not installed: Sphinx and MyST are in pyproject.toml's
    ``test`` extra, so a missing one is a broken test environment, not a reason to skip the docs build.
    (Found, not imported: the build imports them in its own process; one that is installed but does
    not import fails the build.)"""
    if importlib.util.find_spec(module) is None:
        pytest.fail(f"{module} is missing; it is a test dependency (pip install -e '.[test]')")


def test_docs_build_with_warnings_as_errors(tmp_path):
    """Sphinx reads every page, runs autodoc on every module and resolves every reference with warnings as
    errors.  (The ``dummy`` builder: everything of an HTML build but writing the theme's pages, which
    costs as much again and raises no warning of arpy's; the doctrees are checked instead.)"""
    require("sphinx")
    require("myst_parser")
    require("furo")
    out = tmp_path / "build"
    run = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-b", "dummy", "-q",
                          "-d", str(out / "doctrees"), str(DOCS), str(out)], capture_output=True, text=True, cwd=ROOT)
    assert run.returncode == 0, f"sphinx-build failed:\n{run.stdout}\n{run.stderr}"
    from docutils import nodes

    def doctree(page: str) -> nodes.document:
        return pickle.loads((out / "doctrees" / f"{page}.doctree").read_bytes())

    # the pages of every part, the API reference from the docstrings, the figures found
    for page in ("index", "tour", "guide", "cases/pulse", "results/simulation", "api/lists"):
        assert (out / "doctrees" / f"{page}.doctree").is_file(), page
    api = doctree("api/lists")
    assert "arpy.lists.search.neighbor_list" in {i for n in api.findall(nodes.Element) for i in n.get("ids", [])}
    pulse = doctree("cases/pulse")
    assert "--mass-every" in pulse.astext()
    figures = [Path(n["uri"]).name for n in pulse.findall(nodes.image)]
    assert "simulation_fig44.png" in figures and (ROOT / "benchmarks" / "results" / "simulation_fig44.png").is_file()


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


#: The pages whose code blocks must run in the tests (or say why not): the README and the written pages of
#: the docs (docs/results/ holds the benchmarks' generated pages).  The tests that run their python blocks:
#: README.md (tests/test_readme.py), tour.md and guide.md (here).
CODE_PAGES = [ROOT / "README.md", *sorted(DOCS.glob("*.md")), *sorted(DOCS.glob("cases/*.md"))]
RUN_PYTHON = {"README.md", "docs/tour.md", "docs/guide.md", "docs/index.md"}
#: The comment before a fenced block that the tests do not run, with the reason; the README's sample output
#: has its own marker (benchmarks/main_job.py writes it, tests/test_readme.py checks it).
NOT_RUN = re.compile(r"(<!-- not run: \S.*? -->|<!-- main-job-output: .*? -->)\n$")


def _fenced_blocks(text: str):
    """(info string, code, text before the block) of each fenced block of a Markdown page."""
    for m in re.finditer(r"^```([^\n]*)\n(.*?)^```[ \t]*$", text, flags=re.S | re.M):
        yield m.group(1).strip(), m.group(2), text[:m.start()]


def test_every_code_block_runs_in_the_tests_or_says_why_not():
    """Every fenced block of the README, docs/*.md and docs/cases/*.md is a python block that a test runs, a Sphinx
    directive ({toctree}, {figure}, {literalinclude} of a script the tests run, ...), or is marked
    ``<!-- not run: reason -->`` just before it."""
    unmarked = []
    for page in CODE_PAGES:
        name = page.relative_to(ROOT).as_posix()
        for info, _, before in _fenced_blocks(page.read_text(encoding="utf-8")):
            if info.startswith("{"):
                continue
            marked = NOT_RUN.search(before) is not None
            if info == "python" and name in RUN_PYTHON:
                assert not marked, f"{name}: a python block that runs is marked not run"
                continue
            if not marked:
                unmarked.append(f"{name}:{before.count(chr(10)) + 1}: ```{info}")
    assert not unmarked, "blocks that neither run in the tests nor say why not:\n" + "\n".join(unmarked)


def test_the_landing_page_example_runs_as_written(capsys):
    """docs/index.md's three lines: the pulse to T = 0.1 prints its particle count and an error below 1e-2."""
    (code,) = re.findall(r"```python\n(.*?)```", (DOCS / "index.md").read_text(encoding="utf-8"), flags=re.S)
    exec(compile(code, "index.md", "exec"), {"__name__": "index"})
    n, error = capsys.readouterr().out.split()
    assert int(n) > 500 and 0 < float(error) < 1e-2


def test_the_guide_python_blocks_run_as_written():
    blocks = re.findall(r"```python\n(.*?)```", (DOCS / "guide.md").read_text(encoding="utf-8"), flags=re.S)
    assert len(blocks) >= 2
    for code in blocks:                  # each block stands alone
        exec(compile(code, "guide.md", "exec"), {"__name__": "guide"})


def _gray_scott():
    """docs/examples/gray_scott.py as a module (not run)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("arpy_gray_scott", DOCS / "examples" / "gray_scott.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_guide_gray_scott_example_makes_patterns():
    """The guide's Gray-Scott example (docs/examples/gray_scott.py) to T = 40 (its full run goes to 2000):
    the fields stay finite and in their range, and the reactions build structure: the spatial variance of v
    rises from its initial value (by 1.5 times at T = 40), which diffusion alone can only lower (d/dt of the
    integral of (v - mean v)^2 is -2 D_v times that of |grad v|^2).  About 3 s."""
    import numpy as np

    gs = _gray_scott()
    sim = gs.run(0.0)
    var0 = sim.fields["v"].var()
    sim.run(40.0)
    u, v = sim.fields["u"], sim.fields["v"]
    assert sim.t == 40.0 and np.isfinite(sim.F).all() and np.isfinite(sim.x).all()
    assert u.min() > -0.01 and u.max() < 1.01 and v.min() > -0.01 and v.max() < 1.0
    assert v.var() > 1.3 * var0, (var0, v.var())
