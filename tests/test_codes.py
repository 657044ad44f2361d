"""The code tables of arpy/_codes.py against the named parameters of the Fortran core.

The Fortran sources under fortran/ (every topic folder) are read as text: every public integer parameter
(``integer, parameter, public :: NAME = value[, NAME2 = value2 ...]``, any case, continuation
lines and comments allowed) is collected, and each table of arpy._codes must name exactly the
parameters of its family (STATUS: ARPY_*, METHODS: METHOD_*, ...) with the same values.  No
core routine runs.
"""

from __future__ import annotations

import copy
import re
import types
from collections.abc import Callable
from pathlib import Path

import pytest

from arpy import _codes, _errors

FORTRAN = Path(__file__).resolve().parents[1] / "fortran"

# ---------------------------------------------------------------- reading the Fortran


def _strip_comment(line: str) -> str:
    """The line without its ``!`` comment (a ``!`` inside a string is kept)."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch == "!":
            return line[:i]
    return line


def _split_top(text: str, sep: str) -> list[str]:
    """Split at ``sep`` outside parentheses, brackets and strings."""
    parts, depth, quote, start = [], 0, None, 0
    for i, ch in enumerate(text):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch in "([":
            depth += 1
        elif ch in ")]":
            depth -= 1
        elif ch == sep and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    parts.append(text[start:])
    return parts


def statements(text: str) -> list[str]:
    """The statements of free-form Fortran source: comments removed, continuation lines
    (``&`` at the end, optionally ``&`` at the start of the next) joined, ``;`` split."""
    out: list[str] = []
    pending = None                       # a statement continued on the next line
    for raw in text.splitlines():
        line = _strip_comment(raw).strip()
        if pending is not None:
            if not line:                 # a comment or blank line inside a continued statement
                continue
            line = pending + " " + line.removeprefix("&").lstrip()
            pending = None
        if line.endswith("&"):
            pending = line[:-1].rstrip()
            continue
        out.extend(s.strip() for s in _split_top(line, ";") if s.strip())
    if pending:
        out.append(pending)
    return out


_DECL = re.compile(r"integer\s*(?:\(\s*(?:kind\s*=\s*)?\w+\s*\)|\*\s*\d+)?\s*,(?P<attrs>.*?)::(?P<entities>.*)",
                   re.I)
_ENTITY = re.compile(r"(?P<name>[a-z_]\w*)\s*(?P<dims>\([^)]*\))?\s*=\s*(?P<value>.+)", re.I | re.S)
_INT = re.compile(r"[+-]?\d+(?:_\w+)?")


def public_parameters(text: str) -> dict[str, int | str]:
    """Every scalar public integer parameter declared in ``text``: NAME (upper case) -> value,
    an int for an integer literal (with or without kind), else the expression as written.
    Array parameters are left out."""
    found: dict[str, int | str] = {}
    for stmt in statements(text):
        m = _DECL.fullmatch(stmt)
        if not m:
            continue
        attrs = {a.strip().lower() for a in _split_top(m["attrs"], ",")}
        if not {"parameter", "public"} <= attrs:
            continue
        for entity in _split_top(m["entities"], ","):
            e = _ENTITY.fullmatch(entity.strip())
            if e is None:
                raise ValueError(f"cannot read the parameter declaration {entity.strip()!r} in {stmt!r}")
            value = e["value"].strip()
            if e["dims"] or value.startswith(("[", "(/")):
                continue
            found[e["name"].upper()] = int(value.split("_")[0]) if _INT.fullmatch(value) else value
    return found


def fortran_parameters(sources: dict[str, str]) -> tuple[dict[str, int | str], list[str]]:
    """The public integer parameters of all sources (file name -> text), and the names declared
    with different values in different files."""
    params: dict[str, int | str] = {}
    where: dict[str, str] = {}
    clashes = []
    for file, text in sorted(sources.items()):
        for name, value in public_parameters(text).items():
            if name in params and params[name] != value:
                clashes.append(f"{name} = {params[name]} in {where[name]}, {value} in {file}")
            params.setdefault(name, value)
            where.setdefault(name, file)
    return params, clashes


def read_sources() -> dict[str, str]:
    return {path.relative_to(FORTRAN).as_posix(): path.read_text() for path in sorted(FORTRAN.rglob("*.f90"))}


# ---------------------------------------------------------------- the tables

#: table of arpy._codes: (the prefix of its family of Fortran names, its entries as (Fortran name, code) pairs)
TABLES: dict[str, tuple[str, Callable[[dict], list[tuple[str | None, int]]]]] = {
    "STATUS": ("ARPY_", lambda t: [(f"ARPY_{key}", v) for key, v in t.items()]),
    "METHODS": ("METHOD_", lambda t: [(f"METHOD_{key.upper()}", v) for key, v in t.items()]),
    "RULES": ("RULE_", lambda t: [(f"RULE_{key.upper()}", v) for key, v in t.items()]),
    "AR_OPS": ("AR_OP_", lambda t: [(f"AR_OP_{key.upper()}", v) for key, v in t.items()]),
    "DCPSE_OPERATORS": ("OP_", lambda t: [
        ({"derivative": "OP_DERIV", "laplacian": "OP_LAPLACIAN", "interpolation": "OP_INTERP"}.get(key), v)
        for key, v in t.items()]),
    "DCPSE_FORMS": ("FORM_", lambda t: [(f"FORM_{key.upper()}", v) for key, v in t.items()]),
    "STENCIL_STATUS": ("DC_", lambda t: [
        ({"too few neighbours": "DC_FEW", "singular moment matrix": "DC_SINGULAR",
          "ill-conditioned moment matrix": "DC_ILLCOND"}.get(meaning), code) for code, meaning in t.items()]),
    "POTENTIALS": ("POT_", lambda t: [("POT_" + key.upper().replace("-", "_"), v) for key, v in t.items()]),
}
#: Fortran names with a table's prefix that the table leaves out: DC_OK is the status of a good stencil,
#: which arpy.dcpse reads as status 0 (np.flatnonzero(status) are the failed points).
NOT_IN_TABLE = {"DC_OK": 0}


def table_problems(codes, params: dict[str, int | str]) -> list[str]:
    """Every disagreement between the tables of ``codes`` (a module like arpy._codes) and the
    Fortran parameters ``params``; empty if they agree exactly."""
    problems = []
    unchecked = set(codes.__all__) - set(TABLES) - {"RANGE_EXP"}
    if unchecked:
        problems.append(f"tables without a check against the Fortran: {sorted(unchecked)}")
    for table, (prefix, as_fortran) in TABLES.items():
        entries = as_fortran(getattr(codes, table))
        names = [name for name, _ in entries]
        if None in names:
            problems.append(f"{table}: entries without a Fortran name: {getattr(codes, table)}")
        for name in sorted({n for n in names if n is not None and names.count(n) > 1}):
            problems.append(f"{table}: two entries are {name}")
        if len({v for _, v in entries}) != len(entries):
            problems.append(f"{table}: two entries share a code: {getattr(codes, table)}")
        expected = {name: value for name, value in entries if name is not None}
        family = {n: v for n, v in params.items() if n.startswith(prefix) and n not in NOT_IN_TABLE}
        for name, value in entries:
            if name is None:
                continue
            if name not in family:
                problems.append(f"{table}: {name} is not a public integer parameter of fortran/")
            elif family[name] != value:
                problems.append(f"{table}: {name} = {family[name]} in the Fortran, {value} in arpy/_codes.py")
        for name in sorted(set(family) - set(expected)):
            problems.append(f"{table}: the Fortran's {name} = {family[name]} is missing from the table")
    for name, value in NOT_IN_TABLE.items():
        if params.get(name) != value:
            problems.append(f"{name} = {params.get(name)} in the Fortran, arpy reads it as {value}")
    if params.get("RANGE_EXP") != codes.RANGE_EXP:
        problems.append(f"RANGE_EXP = {params.get('RANGE_EXP')} in the Fortran, {codes.RANGE_EXP} in arpy/_codes.py")
    return problems


def codes_copy() -> types.SimpleNamespace:
    """A copy of arpy._codes whose tables a test may change."""
    return types.SimpleNamespace(__all__=list(_codes.__all__),
                                 **{name: copy.deepcopy(getattr(_codes, name)) for name in _codes.__all__})


# ---------------------------------------------------------------- tests


def test_parser_reads_declarations():
    text = """
    module m
      integer, parameter, public :: A_ONE = 1, &   ! a comment, with A_X = 9 in it
           ! a comment line inside the statement
           & A_TWO = 2                              ! A_Y = 8
      integer, parameter :: PRIVATE_X = 5
      INTEGER , Public, PARAMETER::B_NEG = -4_i8; integer, parameter, public :: C = 7
      integer(i8), parameter, public :: ARR(2:3) = [30, 20], D = 1000000000000_i8
      integer, parameter, public :: KINDNAME = real64
      ! integer, parameter, public :: COMMENTED = 9
      character(*), parameter, public :: S = "integer, parameter, public :: IN_STRING = 3 ! no"
      real(dp), parameter, public :: R = 1.0_dp
      integer, public :: NOT_A_PARAMETER = 6
    end module m
    """
    assert public_parameters(text) == {"A_ONE": 1, "A_TWO": 2, "B_NEG": -4, "C": 7, "D": 10 ** 12,
                                       "KINDNAME": "real64"}


def test_fortran_parameters_are_read():
    params, clashes = fortran_parameters(read_sources())
    assert clashes == []
    # one of each family, including one on a continuation line (arpy_arops.f90)
    for name in ("ARPY_OK", "ARPY_ERR_RANGE", "METHOD_AR", "AR_OP_FIND_CELL", "AR_OP_NEIGHBORS", "OP_INTERP",
                 "FORM_B", "DC_ILLCOND", "POT_V2_PURE", "RANGE_EXP"):
        assert isinstance(params.get(name), int), name


def test_tables_agree_with_the_fortran():
    params, _ = fortran_parameters(read_sources())
    assert table_problems(_codes, params) == []


def test_every_status_has_a_message():
    """arpy._errors turns every status but OK into its own exception message, and OK into none."""
    assert set(_errors._CODES) == set(_codes.STATUS.values()) - {_codes.STATUS["OK"]}
    assert _errors.raise_for_info(_codes.STATUS["OK"]) is None
    for name, code in _codes.STATUS.items():
        if name == "OK":
            continue
        with pytest.raises(Exception) as err:
            _errors.raise_for_info(code, bad=1)
        assert "unknown status" not in str(err.value), name


def _alter(table: str, change: Callable[[dict], None]) -> types.SimpleNamespace:
    codes = codes_copy()
    change(getattr(codes, table))
    return codes


ALTERED_TABLES = {
    "status value": ("STATUS", lambda t: t.update(ERR_RANGE=14), "ARPY_ERR_RANGE"),
    "status missing": ("STATUS", lambda t: t.pop("ERR_LIST"), "ARPY_ERR_LIST"),
    "status added": ("STATUS", lambda t: t.update(ERR_NEW=14), "ARPY_ERR_NEW"),
    "method added": ("METHODS", lambda t: t.update(octree=3), "METHOD_OCTREE"),
    "method value": ("METHODS", lambda t: t.update(ar=3), "METHOD_AR"),
    "codes shared": ("METHODS", lambda t: t.update(ar=1), "share a code"),
    "ops swapped": ("AR_OPS", lambda t: t.update(children=4, parent=3), "AR_OP_CHILDREN"),
    "operator renamed": ("DCPSE_OPERATORS", lambda t: t.update(laplace=t.pop("laplacian")), "OP_LAPLACIAN"),
    "forms swapped": ("DCPSE_FORMS", lambda t: t.update(a=1, b=0), "FORM_A"),
    "stencil status": ("STENCIL_STATUS", lambda t: t.update({4: "too few neighbours"}), "two entries are DC_FEW"),
    "stencil renamed": ("STENCIL_STATUS", lambda t: t.update({3: "bad"}), "without a Fortran name"),
    "potential value": ("POTENTIALS", lambda t: t.update({"V2-PURE": 5}), "POT_V2_PURE"),
}


@pytest.mark.parametrize("case", ALTERED_TABLES)
def test_checker_fails_on_an_altered_table(case):
    table, change, expect = ALTERED_TABLES[case]
    params, _ = fortran_parameters(read_sources())
    problems = table_problems(_alter(table, change), params)
    assert any(expect in p for p in problems), problems


def test_checker_fails_on_an_unchecked_table_or_range():
    params, _ = fortran_parameters(read_sources())
    codes = codes_copy()
    codes.RANGE_EXP = 400
    codes.__all__.append("NEW_TABLE")
    problems = table_problems(codes, params)
    assert any("RANGE_EXP" in p for p in problems) and any("NEW_TABLE" in p for p in problems), problems


ALTERED_SOURCES = {
    # case: (file, (text, its replacement), a name the checker must report)
    "method value": ("core/arpy_kinds.f90", ("METHOD_AR = 2", "METHOD_AR = 3"), "METHOD_AR"),
    "status added": ("core/arpy_kinds.f90", ("  integer, parameter, public :: RANGE_EXP",
                                             "  integer, parameter, public :: ARPY_ERR_NEW = 14\n"
                                             "  integer, parameter, public :: RANGE_EXP"), "ARPY_ERR_NEW"),
    "status made private": ("core/arpy_kinds.f90", ("parameter, public :: ARPY_ERR_LIST", "parameter :: ARPY_ERR_LIST"),
                            "ARPY_ERR_LIST"),
    "op on a continuation line": ("ar/arpy_arops.f90", ("AR_OP_PARENT = 4", "AR_OP_PARENT = 6"), "AR_OP_PARENT"),
    "potential": ("selforg/arpy_selforg.f90", ("POT_V1_PURE = 3", "POT_V1_PURE = 5"), "POT_V1_PURE"),
    "stencil ok": ("dcpse/arpy_dcpse.f90", ("DC_OK = 0", "DC_OK = 4"), "DC_OK"),
    "range": ("core/arpy_kinds.f90", ("RANGE_EXP = 500", "RANGE_EXP = 400"), "RANGE_EXP"),
}


@pytest.mark.parametrize("case", ALTERED_SOURCES)
def test_checker_fails_on_an_altered_source(case):
    file, (old, new), expect = ALTERED_SOURCES[case]
    sources = read_sources()
    assert old in sources[file]
    sources[file] = sources[file].replace(old, new)
    params, _ = fortran_parameters(sources)
    problems = table_problems(_codes, params)
    assert any(expect in p for p in problems), problems


def test_a_name_with_two_values_is_reported():
    sources = read_sources()
    sources["extra.f90"] = "integer, parameter, public :: METHOD_AR = 5\n"
    _, clashes = fortran_parameters(sources)
    assert clashes and "METHOD_AR" in clashes[0]
