"""The package's layout: its imports run one way (no import cycle between arpy's modules, and no module
imports another module's private names; read from the source with ``ast``, function-level imports
count), its modules (Python and Fortran) stay short, its subpackages say what they hold, and ``import arpy`` loads no more than
NumPy and the core (the rest on first use).  The Fortran core keeps its
layout too: every source in a topic folder of fortran/, at most one module per file, the files under
fortran/ and those meson.build names the same, and core/ on its own."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "arpy"
ROOT = PACKAGE.parent
#: The longest a module of the package (Python or Fortran) may be, in lines.
MAX_LINES = 700
#: The subpackages of arpy, one concept each.
SUBPACKAGES = {"adapt", "cases", "dcpse", "distributed", "lists", "reference"}
#: Compiled modules of the package (the f2py wrapper of the Fortran core; an editable install builds it
#: outside the source tree).
EXTENSIONS = {"_core"}


def module_name(root: Path, path: Path) -> str:
    """The dotted name of a source file below ``root`` (the package folder)."""
    parts = [root.name, *path.relative_to(root).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_target(package: str, node: ast.ImportFrom) -> str:
    """The dotted module a ``from ... import`` statement in ``package`` imports from."""
    if not node.level:
        return node.module or ""
    base = package.split(".")
    base = base[:len(base) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def write_tree(root: Path, files: dict[str, str]) -> None:
    """A package tree for the checks' own tests: path below ``root`` -> source."""
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)


def imports(root: Path) -> tuple[dict[str, set[str]], list[str]]:
    """Every module's imports of the package's own modules, and the private names imported across modules."""
    modules = {module_name(root, p): p for p in root.rglob("*.py")}
    graph: dict[str, set[str]] = {name: set() for name in modules}
    private: list[str] = []
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                target = import_target(package, node)
                if target.split(".")[0] != root.name:
                    continue
                for alias in node.names:
                    sub = f"{target}.{alias.name}"
                    if sub in modules:
                        graph[name].add(sub)
                        continue
                    if alias.name in EXTENSIONS and target == root.name:
                        continue
                    if target in modules:
                        graph[name].add(target)
                    if alias.name.startswith("_") and not alias.name.startswith("__") and target != name:
                        private.append(f"{name} imports {alias.name} from {target}")
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name in modules and alias.name != name:
                        graph[name].add(alias.name)
    for name in graph:
        graph[name].discard(name)
    return graph, private


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles of a graph (one per strongly connected component with a cycle), by Tarjan's algorithm."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_arpy_has_no_import_cycle_and_no_private_cross_module_import():
    graph, private = imports(PACKAGE)
    assert "arpy.lists.search" in graph and "arpy.domain" in graph["arpy.lists.search"]
    assert cycles(graph) == []
    assert private == []


def test_the_checks_fail_on_a_cycle_and_on_a_private_import(tmp_path):
    root = tmp_path / "arpy"
    write_tree(root, {"__init__.py": "", "a.py": "from .b import thing\n",
                      "b.py": "def f():\n    from .sub.c import _hidden\n", "sub/__init__.py": "",
                      "sub/c.py": "from ..a import thing\n_hidden = 1\n"})
    graph, private = imports(root)
    assert cycles(graph) == [["arpy.a", "arpy.b", "arpy.sub.c"]]
    assert private == ["arpy.b imports _hidden from arpy.sub.c"]


#: What ``import arpy`` must not load: SciPy, plotting, MPI, progress bars, meshio, and arpy's cases,
#: plotting, distributed runs and simulation (they load on first use of a name that needs them).
NOT_AT_IMPORT = ("scipy", "matplotlib", "mpi4py", "tqdm", "meshio", "arpy.cases", "arpy.plotting",
                 "arpy.distributed", "arpy.simulation", "arpy.dcpse", "arpy.adapt", "arpy.cli")


def test_import_arpy_loads_only_numpy_and_the_core():
    """The set of modules ``import arpy`` loads (in a fresh interpreter): none of NOT_AT_IMPORT; then every
    public name and the subpackages resolve (imported on first use), and an unknown name is an
    AttributeError."""
    code = ("import sys, arpy\n"
            "print(' '.join(sorted(sys.modules)))\n"
            "names = [getattr(arpy, n) for n in arpy.__all__]\n"
            "subs = [arpy.cases.CASES, arpy.plotting.plot_particles, arpy.distributed.MPIComm, arpy.lists.ar.MAX_LEVEL]\n"
            "from arpy import Simulation, neighbor_list\n"
            "assert arpy.Simulation is arpy.simulation.Simulation and 'Simulation' in dir(arpy)\n"
            "try:\n    arpy.no_such_name\nexcept AttributeError as exc:\n    print('missing:', exc)\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT.parent)
    assert run.returncode == 0, run.stderr
    loaded, missing = run.stdout.splitlines()[-2:]
    loaded = set(loaded.split())
    assert {"numpy", "arpy", "arpy.threads", "arpy._core"} <= loaded
    assert [m for m in loaded if m.split(".")[0] in NOT_AT_IMPORT or m.startswith(NOT_AT_IMPORT)] == []
    assert missing == "missing: module 'arpy' has no attribute 'no_such_name'"


# ---------------------------------------------------------------- the Fortran layout

#: The topic folders of fortran/ (fortran/README.md says what each holds).
FORTRAN_TOPICS = {"core", "lists", "ar", "dcpse", "selforg", "bind"}
#: Files under fortran/ that are not built (everything else must be named in meson.build).
FORTRAN_NOT_BUILT = {"README.md"}
_MODULE = re.compile(r"^\s*module\s+(?!procedure\b)(\w+)\s*(?:!.*)?$", re.I | re.M)
_USE = re.compile(r"^\s*use\s*(?:,\s*non_intrinsic\s*::\s*|::\s*|\s)\s*(\w+)", re.I | re.M)


def fortran_layout_problems(root: Path) -> list[str]:
    """What breaks the layout of ``root / "fortran"`` against ``root / "meson.build"``: a Fortran source
    outside the topic folders, a file with more than one module, a file under fortran/ that meson.build
    does not name or a name in meson.build with no file (the sources belong to the one target
    ``core_sources``; the signature file is the f2py target's input), a module of core/ that uses a
    module of another folder."""
    fortran = root / "fortran"
    meson = (root / "meson.build").read_text()
    problems: list[str] = []
    files = {p.relative_to(root).as_posix() for p in fortran.rglob("*") if p.is_file()}
    files -= {f"fortran/{name}" for name in FORTRAN_NOT_BUILT}
    sources = {f for f in files if f.endswith((".f90", ".F90"))}
    for f in sorted(sources):
        parts = f.split("/")
        if len(parts) != 3 or parts[1] not in FORTRAN_TOPICS:
            problems.append(f"{f} is not in a topic folder of fortran/ ({', '.join(sorted(FORTRAN_TOPICS))})")
    block = re.search(r"^core_sources\s*=\s*files\((.*?)^\)", meson, re.S | re.M)
    listed = set(re.findall(r"'(fortran/[^']+)'", block.group(1))) if block else set()
    named = set(re.findall(r"'(fortran/[^']+)'", meson))
    for f in sorted(sources - listed):
        problems.append(f"{f} is not in core_sources of meson.build")
    for f in sorted(files - sources - named):
        problems.append(f"{f} is not named in meson.build")
    for f in sorted(named - files):
        problems.append(f"meson.build names {f}, which is not a file under fortran/")
    folder_of: dict[str, str] = {}
    uses: dict[str, set[str]] = {}
    for f in sorted(sources):
        text = (root / f).read_text()
        modules = [m.lower() for m in _MODULE.findall(text)]
        if len(modules) > 1:
            problems.append(f"{f} holds {len(modules)} modules ({', '.join(modules)}); one file per module")
        for m in modules:
            folder_of[m] = f.split("/")[1]
            uses[m] = {u.lower() for u in _USE.findall(text)}
    for m, used in sorted(uses.items()):
        if folder_of[m] == "core":
            for u in sorted(used):
                if folder_of.get(u, "core") != "core":
                    problems.append(f"core module {m} uses {u} of {folder_of[u]}/")
    return problems


def test_fortran_layout():
    assert (ROOT / "fortran" / "core" / "arpy_kinds.f90").is_file()
    assert fortran_layout_problems(ROOT) == []


def test_the_layout_check_fails_on_a_misplaced_file(tmp_path):
    (tmp_path / "fortran" / "core").mkdir(parents=True)
    (tmp_path / "fortran" / "bind").mkdir()
    (tmp_path / "fortran" / "misc").mkdir()
    (tmp_path / "fortran" / "README.md").write_text("")
    (tmp_path / "fortran" / "core" / "a.f90").write_text("module a\n  use b, only: x\nend module a\n")
    (tmp_path / "fortran" / "core" / "two.F90").write_text(
        "module c\n  interface f\n     module procedure g\n  end interface\nend module c\nMODULE d\nend module d\n")
    (tmp_path / "fortran" / "misc" / "b.f90").write_text("module b\nend module b\n")
    (tmp_path / "fortran" / "top.f90").write_text("subroutine s()\nend subroutine s\n")
    (tmp_path / "fortran" / "bind" / "_core.pyf").write_text("")
    (tmp_path / "meson.build").write_text(
        "core_sources = files(\n  'fortran/core/a.f90',\n  'fortran/misc/b.f90',\n  'fortran/gone.f90',\n)\n"
        "x = custom_target('w', input: 'fortran/core/two.F90')\n")
    assert fortran_layout_problems(tmp_path) == [
        "fortran/misc/b.f90 is not in a topic folder of fortran/ (ar, bind, core, dcpse, lists, selforg)",
        "fortran/top.f90 is not in a topic folder of fortran/ (ar, bind, core, dcpse, lists, selforg)",
        "fortran/core/two.F90 is not in core_sources of meson.build",
        "fortran/top.f90 is not in core_sources of meson.build",
        "fortran/bind/_core.pyf is not named in meson.build",
        "meson.build names fortran/gone.f90, which is not a file under fortran/",
        "fortran/core/two.F90 holds 2 modules (c, d); one file per module",
        "core module a uses b of misc/",
    ]

def core_importers(root: Path) -> list[str]:
    """The modules below ``root`` that import the f2py extension ``_core`` (any form of import, at any
    level of the module)."""
    found = []
    for path in sorted(root.rglob("*.py")):
        name = module_name(root, path)
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                target = import_target(package, node)
                hit = target.endswith("._core") or any(a.name in EXTENSIONS and target == root.name
                                                       for a in node.names)
            elif isinstance(node, ast.Import):
                hit = any(a.name == f"{root.name}._core" or a.name.startswith(f"{root.name}._core.")
                          for a in node.names)
            else:
                continue
            if hit and name not in found:
                found.append(name)
    return found


def test_exactly_one_module_calls_the_core():
    """arpy._bridge is the one bridge to the Fortran core: no other module imports arpy._core."""
    assert core_importers(PACKAGE) == ["arpy._bridge"]


def test_the_core_check_finds_every_form_of_import(tmp_path):
    root = tmp_path / "arpy"
    write_tree(root, {"__init__.py": "", "a.py": "from . import _core\n",
                      "b.py": "def f():\n    from arpy._core import arpy_knn\n", "c.py": "import arpy._core as core\n",
                      "sub/__init__.py": "", "sub/d.py": "from .. import _core, other\n",
                      "sub/e.py": "from ..a import _core_helper\n"})
    assert core_importers(root) == ["arpy.a", "arpy.b", "arpy.c", "arpy.sub.d"]


def too_long(root: Path) -> dict[str, int]:
    """The modules below ``root`` longer than MAX_LINES lines, path -> lines: the Python modules of
    ``root / "arpy"`` and the Fortran modules of ``root / "fortran"`` (one module per file)."""
    paths = [*(root / "arpy").rglob("*.py"), *(root / "fortran").rglob("*.[fF]90")]
    lengths = {p.relative_to(root).as_posix(): len(p.read_text().splitlines()) for p in paths}
    return {name: n for name, n in sorted(lengths.items()) if n > MAX_LINES}


def test_no_module_is_longer_than_the_limit():
    assert {p.suffix for p in (ROOT / "fortran").rglob("*.[fF]90")} >= {".f90"}
    assert too_long(ROOT) == {}


def test_the_length_check_covers_python_and_fortran(tmp_path):
    write_tree(tmp_path, {"arpy/a.py": "x = 1\n" * MAX_LINES, "arpy/sub/b.py": "x = 1\n" * (MAX_LINES + 1),
                          "fortran/core/c.f90": "!\n" * MAX_LINES, "fortran/ar/d.f90": "!\n" * (MAX_LINES + 1),
                          "fortran/core/e.F90": "!\n" * (MAX_LINES + 2), "fortran/README.md": "-\n" * 800})
    assert too_long(tmp_path) == {"arpy/sub/b.py": MAX_LINES + 1, "fortran/ar/d.f90": MAX_LINES + 1,
                                  "fortran/core/e.F90": MAX_LINES + 2}


def test_every_subpackage_has_an_init_and_every_module_a_docstring():
    found = {p.name for p in PACKAGE.iterdir() if p.is_dir() and any(p.glob("*.py"))}
    assert found == SUBPACKAGES
    for name in sorted(SUBPACKAGES):
        init = PACKAGE / name / "__init__.py"
        assert init.is_file(), f"arpy/{name} has no __init__.py"
        assert ast.get_docstring(ast.parse(init.read_text())), f"arpy/{name}/__init__.py has no module docstring"
    for path in PACKAGE.rglob("*.py"):
        assert ast.get_docstring(ast.parse(path.read_text())), f"{path.relative_to(ROOT)} has no module docstring"
