"""The parts of the arpy documentation that come from the package at build time.

``.. arpy-run-help:: CASE``
    The text of ``arpy run CASE --help`` as a literal block, so that a case page always lists
    the options, units and defaults of the installed command.

``.. arpy-public-api::``
    A table of the names in ``arpy.__all__``, each linked to its description in the module that
    defines it (every object is described once, where it is defined).

References by the path a user imports from (``arpy.self_organize``) resolve to the description
where the object is defined (``arpy.adapt.organize.self_organize``).  The docs of module data,
attributes and properties are shown as written (napoleon would read ``text: more text`` as a
type and a description), and the bases of a class are listed without ``object``.
"""

from __future__ import annotations

import contextlib
import inspect
import io
import os
import sys

from docutils import nodes
from docutils.statemachine import StringList
from sphinx.util.docutils import SphinxDirective

#: Width of the ``--help`` text on the case pages (characters).
HELP_COLUMNS = 88


def run_help(case: str) -> str:
    """The text ``arpy run CASE --help`` prints."""
    from arpy.cli import build_parser

    parser = build_parser()
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(HELP_COLUMNS)
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
            parser.parse_args(["run", case, "--help"])
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old
    return out.getvalue().rstrip()


class RunHelp(SphinxDirective):
    """``arpy run CASE --help`` as a literal block."""

    required_arguments = 1
    has_content = False

    def run(self) -> list[nodes.Node]:
        from arpy.cases import CASES

        case = self.arguments[0]
        if case not in CASES:
            raise self.error(f"arpy run has no case {case!r}; the cases are {', '.join(CASES)}")
        text = f"$ arpy run {case} --help\n{run_help(case)}"
        block = nodes.literal_block(text, text)
        block["language"] = "text"
        return [block]


def _role_and_target(name: str, obj: object) -> tuple[str, str] | None:
    """The cross-reference role and target of a public name of arpy, or None if it has none."""
    if inspect.ismodule(obj):
        return "mod", obj.__name__
    module = getattr(obj, "__module__", None)
    if module is not None and module.startswith("arpy._"):
        module = "arpy"            # defined in a private module: described on the package page
    if inspect.isclass(obj):
        role = "exc" if issubclass(obj, BaseException) else "class"
        return role, f"{module}.{obj.__qualname__}"
    if callable(obj) and module is not None:
        return "func", f"{module}.{obj.__qualname__}"
    home = DATA_HOMES.get(name)
    return None if home is None else ("data", f"{home}.{name}")


#: Public data of ``arpy.__all__`` -> the module whose page describes it.
DATA_HOMES = {"AUTO_AR_WORK": "arpy.lists.auto", "METHODS": "arpy.lists.search", "__version__": "arpy"}


#: Doc comments of module data, attributes and properties as autodoc read them, kept from napoleon.
_RAW_DOCS: dict[str, list[str]] = {}
_PLAIN = ("data", "attribute", "property")


def keep_plain_docs(app, what, name, obj, options, lines) -> None:
    """Before napoleon: remember the doc of module data, attributes and properties.

    Napoleon reads the first line of such a doc as ``type: description``; arpy writes them as plain
    sentences, which often contain a colon."""
    if what in _PLAIN:
        _RAW_DOCS[name] = list(lines)


def restore_plain_docs(app, what, name, obj, options, lines) -> None:
    """After napoleon: put back the doc of module data, attributes and properties as written."""
    if what in _PLAIN and name in _RAW_DOCS:
        lines[:] = _RAW_DOCS.pop(name)


def _canonical(target: str, module: str | None) -> str | None:
    """The documented name of a Python object that a docstring names by a shorter path.

    ``arpy.self_organize`` is documented as ``arpy.adapt.organize.self_organize`` (where it is
    defined), ``arpy.NeighborList.pairs`` as ``arpy.lists.neighborlist.NeighborList.pairs``; a bare
    ``slope`` in the docstring of :mod:`arpy.cases` is ``arpy.cases.analysis.slope``."""
    target = target.lstrip("~.")
    candidates = [target] if target.startswith("arpy.") else []
    if module and module.startswith("arpy"):
        candidates.append(f"{module}.{target}")
    for path in candidates:
        parts = path.split(".")
        # the longest prefix that is a module autodoc has imported (nothing is imported here: an
        # import of arpy checks whether the Fortran core needs a rebuild)
        cut = next((k for k in range(len(parts), 0, -1) if ".".join(parts[:k]) in sys.modules), 0)
        if cut == 0:
            continue
        obj = sys.modules[".".join(parts[:cut])]
        try:
            for attr in parts[cut:]:
                obj = getattr(obj, attr)
        except AttributeError:
            continue
        if inspect.ismodule(obj):
            return obj.__name__
        home = getattr(obj, "__module__", None)
        qual = getattr(obj, "__qualname__", None)
        if home and qual and (inspect.isclass(obj) or inspect.isroutine(obj)):
            if home.startswith("arpy._"):
                home = "arpy"             # defined in a private module: described on the package page
            return f"{home}.{qual}"
        return None
    return None


def resolve_reexports(app, env, node, contnode):
    """Resolve a reference to an object of arpy by the path a user imports it from."""
    if node.get("refdomain") != "py":
        return None
    canonical = _canonical(node["reftarget"], node.get("py:module"))
    if canonical is None or canonical == node["reftarget"]:
        return None
    domain = env.get_domain("py")
    new = node.deepcopy()
    new["reftarget"] = canonical
    return domain.resolve_xref(env, node.get("refdoc", env.docname), app.builder, node["reftype"], canonical,
                               new, contnode)


class PublicAPI(SphinxDirective):
    """The names of ``arpy.__all__`` with links to their descriptions."""

    has_content = False

    def run(self) -> list[nodes.Node]:
        import arpy

        lines = [".. list-table::", "   :header-rows: 1", "   :widths: 30 70", "",
                 "   * - ``arpy.`` name", "     - described in"]
        for name in arpy.__all__:
            ref = _role_and_target(name, getattr(arpy, name))
            if ref is None:
                raise self.error(f"arpy.{name} is public but has no description: add it to DATA_HOMES "
                                 "and describe it there")
            lines += [f"   * - ``{name}``", f"     - :py:{ref[0]}:`{ref[1]}`"]
        node = nodes.container()
        self.state.nested_parse(StringList(lines, source="arpy.__all__"), self.content_offset, node)
        return node.children


def hide_object_base(app, name, obj, options, bases) -> None:
    """Show the bases of a class, but not ``object``."""
    bases[:] = [b for b in bases if b is not object]


def setup(app):
    app.add_directive("arpy-run-help", RunHelp)
    app.add_directive("arpy-public-api", PublicAPI)
    app.connect("autodoc-process-docstring", keep_plain_docs, priority=400)
    app.connect("autodoc-process-docstring", restore_plain_docs, priority=600)
    app.connect("missing-reference", resolve_reexports)
    app.connect("autodoc-process-bases", hide_object_base)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
