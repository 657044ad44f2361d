"""The package's layout: its imports run one way (no import cycle between arpy's modules, and no module
imports another module's private names; read from the source with ``ast``, function-level imports
count), its modules stay short, and its subpackages say what they hold."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "arpy"
ROOT = PACKAGE.parent
#: The longest a module of the package may be, in lines.
MAX_LINES = 700
#: Modules allowed over MAX_LINES for now, while they are being shrunk.  This set must become empty:
#: remove a module from it as soon as it is under the limit, and add none.
TOO_LONG_FOR_NOW = {"arpy/simulation.py", "arpy/adapt/organize.py"}
#: The subpackages of arpy, one concept each.
SUBPACKAGES = {"adapt", "cases", "dcpse", "distributed", "lists", "reference"}
#: Compiled modules of the package (the f2py wrapper of the Fortran core; an editable install builds it
#: outside the source tree).
EXTENSIONS = {"_core"}


def module_name(root: Path, path: Path) -> str:
    """The dotted name of a source file below ``root`` (the package folder)."""
    parts = [root.name, *path.relative_to(root).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(root: Path) -> tuple[dict[str, set[str]], list[str]]:
    """Every module's imports of the package's own modules, and the private names imported across modules."""
    modules = {module_name(root, p): p for p in root.rglob("*.py")}
    graph: dict[str, set[str]] = {name: set() for name in modules}
    private: list[str] = []
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")
                    base = base[:len(base) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
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
    (root / "sub").mkdir(parents=True)
    (root / "__init__.py").write_text("")
    (root / "a.py").write_text("from .b import thing\n")
    (root / "b.py").write_text("def f():\n    from .sub.c import _hidden\n")
    (root / "sub" / "__init__.py").write_text("")
    (root / "sub" / "c.py").write_text("from ..a import thing\n_hidden = 1\n")
    graph, private = imports(root)
    assert cycles(graph) == [["arpy.a", "arpy.b", "arpy.sub.c"]]
    assert private == ["arpy.b imports _hidden from arpy.sub.c"]


def test_no_module_is_longer_than_the_limit():
    lengths = {p.relative_to(ROOT).as_posix(): len(p.read_text().splitlines()) for p in PACKAGE.rglob("*.py")}
    too_long = {name for name, n in lengths.items() if n > MAX_LINES}
    assert too_long <= TOO_LONG_FOR_NOW, {name: lengths[name] for name in too_long - TOO_LONG_FOR_NOW}
    # the allowlist names real modules that are still too long (shrunk ones leave it)
    assert {name: lengths.get(name) for name in TOO_LONG_FOR_NOW} == {name: lengths[name] for name in too_long
                                                                      if name in TOO_LONG_FOR_NOW}


def test_every_subpackage_has_an_init_and_every_module_a_docstring():
    found = {p.name for p in PACKAGE.iterdir() if p.is_dir() and any(p.glob("*.py"))}
    assert found == SUBPACKAGES
    for name in sorted(SUBPACKAGES):
        init = PACKAGE / name / "__init__.py"
        assert init.is_file(), f"arpy/{name} has no __init__.py"
        assert ast.get_docstring(ast.parse(init.read_text())), f"arpy/{name}/__init__.py has no module docstring"
    for path in PACKAGE.rglob("*.py"):
        assert ast.get_docstring(ast.parse(path.read_text())), f"{path.relative_to(ROOT)} has no module docstring"
