"""Static typing: mypy over the package (configured in pyproject.toml, [tool.mypy]), and the stub
of the f2py extension (arpy/_core.pyi) against the extension itself.

The stub is generated from the signatures f2py writes into the docstrings of ``arpy._core``;
after a change of fortran/bind/_core.pyf, rewrite it with

    .venv/bin/python tests/test_typing.py --write-core-stub
"""

from __future__ import annotations

import difflib
import importlib
import inspect
import pkgutil
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STUB = ROOT / "arpy" / "_core.pyi"

# f2py's type letters (array('d'), ...) and scalar names, as argument and result types
_ARRAY_DTYPES = {"d": "np.float64", "i": "np.int32", "q": "np.int64"}
_SCALAR_IN = {"int": "SupportsInt", "long": "SupportsInt", "float": "SupportsFloat"}
_SCALAR_OUT = {"int": "int", "long": "int", "float": "float"}

_HEADER = '''\
# The f2py extension of the Fortran core (fortran/bind/_core.pyf): one function per bind(C) routine.
# Generated from the signatures in the extension's docstrings by tests/test_typing.py
# (`python tests/test_typing.py --write-core-stub`), which also checks that it is current.
# Array arguments take anything NumPy converts (f2py copies them when dtype or order differ);
# several results come back as a tuple, one as itself, none as None.

from typing import SupportsFloat, SupportsInt

import numpy as np
import numpy.typing as npt
'''


def _field_type(kind: str, *, result: bool) -> str:
    """The annotation of one 'name : kind' line of an f2py docstring."""
    m = re.fullmatch(r"(input |in/output )?rank-\d+ array\('(\w)'\) with bounds \(.*\)", kind)
    if m:
        dtype = _ARRAY_DTYPES[m.group(2)]
        # (an in/output array is written in place: an ndarray of its exact dtype, not a conversion)
        return f"npt.NDArray[{dtype}]" if result or m.group(1) == "in/output " else "npt.ArrayLike"
    return (_SCALAR_OUT if result else _SCALAR_IN)[kind.removeprefix("input ")]


def _sections(doc: str) -> dict[str, list[tuple[str, str]]]:
    """The 'name : kind' lines of each numpydoc section (Parameters, Other Parameters, Returns)."""
    out: dict[str, list[tuple[str, str]]] = {}
    current = None
    lines = doc.splitlines()
    for i, line in enumerate(lines):
        if i + 1 < len(lines) and set(lines[i + 1]) == {"-"} and line.strip():
            current = out.setdefault(line.strip(), [])
            continue
        m = re.fullmatch(r"(\w+) : (.+)", line.strip())
        if m and current is not None:
            current.append((m.group(1), m.group(2)))
    return out


def core_stub_text() -> str:
    """The stub of arpy._core as its current build describes itself."""
    from arpy import _core as core
    defs = []
    for name in sorted(n for n in dir(core) if not n.startswith("_")):
        sections = _sections(getattr(core, name).__doc__ or "")
        unknown = set(sections) - {"Parameters", "Returns"}
        if unknown:        # optional arguments (Other Parameters) would need defaults in the stub
            raise ValueError(f"{name}: docstring sections {sorted(unknown)} are not handled")
        args = [f"{a}: {_field_type(k, result=False)}" for a, k in sections.get("Parameters", [])]
        results = [_field_type(k, result=True) for _, k in sections.get("Returns", [])]
        ret = ("None" if not results else results[0] if len(results) == 1
               else f"tuple[{', '.join(results)}]")
        defs.append(f"def {name}({', '.join(args)}) -> {ret}: ...\n")
    return _HEADER + "\n" + "".join(defs)


def test_core_stub_matches_extension():
    want = core_stub_text()
    have = STUB.read_text() if STUB.exists() else ""
    if have != want:
        diff = "".join(difflib.unified_diff(have.splitlines(True), want.splitlines(True),
                                            "arpy/_core.pyi", "from arpy._core"))
        pytest.fail("arpy/_core.pyi is out of date; rewrite it with "
                    f"`python tests/test_typing.py --write-core-stub`:\n{diff}")


def test_core_stub_parser_reads_f2py_docstrings():
    doc = ("a,n = f(x,k,t)\n\nWrapper for ``f``.\n\nParameters\n----------\n"
           "x : input rank-2 array('d') with bounds (d,n)\nk : input int\nt : input float\n\n"
           "Returns\n-------\na : rank-1 array('q') with bounds (n)\nn : int\n")
    s = _sections(doc)
    assert [_field_type(k, result=False) for _, k in s["Parameters"]] == \
        ["npt.ArrayLike", "SupportsInt", "SupportsFloat"]
    assert [_field_type(k, result=True) for _, k in s["Returns"]] == ["npt.NDArray[np.int64]", "int"]
    with pytest.raises(KeyError):
        _field_type("input complex", result=False)


def _public_functions() -> list[tuple[str, object]]:
    """Every function and method of the public API: the names in ``__all__`` of arpy and of its
    public modules (no leading underscore) defined there, and the public methods of those classes
    (with ``__init__`` and ``__call__``, properties by their getters)."""
    import arpy

    modules = [arpy] + [importlib.import_module(m.name) for m in pkgutil.walk_packages(arpy.__path__, "arpy.")
                        if not any(part.startswith("_") for part in m.name.split("."))]
    found: dict[object, str] = {}
    for mod in modules:
        for name in mod.__all__:
            obj = getattr(mod, name)
            if getattr(obj, "__module__", None) != mod.__name__:
                continue                      # re-exported: checked where it is defined
            members = [(name, obj)] if inspect.isfunction(obj) else []
            if inspect.isclass(obj):
                for attr, member in vars(obj).items():
                    if attr.startswith("_") and attr not in ("__init__", "__call__"):
                        continue
                    if isinstance(member, (staticmethod, classmethod)):
                        member = member.__func__
                    elif isinstance(member, property):
                        member = member.fget
                    if inspect.isfunction(member) and member.__module__ == mod.__name__:
                        members.append((f"{name}.{attr}", member))
            for qual, fn in members:
                found.setdefault(fn, f"{mod.__name__}.{qual}")
    return [(qual, fn) for fn, qual in found.items()]


def _unannotated(fn) -> list[str]:
    sig = inspect.signature(fn)
    out = [p.name for i, p in enumerate(sig.parameters.values())
           if p.annotation is inspect.Parameter.empty and not (i == 0 and p.name in ("self", "cls"))]
    if sig.return_annotation is inspect.Signature.empty:
        out.append("return")
    return out


def test_public_api_is_annotated():
    """Every parameter and the result of every public function and method carry a type (which
    mypy then checks in their bodies and at their calls)."""
    functions = _public_functions()
    assert len(functions) > 200                      # the walk found the package
    missing = [f"{qual}: {', '.join(names)}" for qual, fn in functions if (names := _unannotated(fn))]
    assert not missing, "public functions without annotations:\n" + "\n".join(missing)


def test_unannotated_finds_what_is_missing():
    def f(self, a: int, b, *args, **kw: float):
        return a

    def g(x: int = 0) -> None:
        pass

    assert _unannotated(f) == ["b", "args", "return"]
    assert _unannotated(g) == []


def test_mypy(tmp_path_factory):
    """mypy over arpy/ with the project's configuration, from a fresh cache (mypy is in the test extra:
    missing, the test fails)."""
    import mypy  # noqa: F401
    cache = tmp_path_factory.mktemp("mypy-cache")
    proc = subprocess.run(
        [sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml"),
         "--cache-dir", str(cache), "--no-error-summary", "--hide-error-context"],
        cwd=ROOT, capture_output=True, text=True, timeout=600)
    output = (proc.stdout + proc.stderr).strip()
    print(output)
    assert proc.returncode == 0, f"mypy found errors (exit {proc.returncode}):\n{output}"


if __name__ == "__main__":
    if sys.argv[1:] != ["--write-core-stub"]:
        sys.exit("usage: python tests/test_typing.py --write-core-stub")
    STUB.write_text(core_stub_text())
    print(f"wrote {STUB}")
