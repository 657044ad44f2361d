"""Sphinx configuration of the arpy documentation.

Build it with ``python -m sphinx -W -b html docs docs/_build/html`` from the repository root.
The build needs no network access and runs no benchmark: the API reference comes from the
docstrings, the case pages from ``arpy run CASE --help``, and the results pages include the
Markdown pages and figures committed in ``benchmarks/results``.
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
# the installed arpy, not the source tree (run from the repository root, ``python -m`` puts the tree
# first on the path, and its arpy/ has no compiled core; an editable install imports either way)
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != HERE.parent]
sys.path.insert(0, str(HERE / "_ext"))

import arpy  # noqa: E402  (the installed package; its version names the release)

project = "arpy"
author = "The arpy developers"
copyright = "the arpy developers"
release = arpy.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "myst_parser",
    "arpy_docs",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]
templates_path: list[str] = []

# autodoc: the members of each module (its __all__) in source order, type hints in the signatures
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_preserve_defaults = True
autodoc_class_signature = "mixed"
autodoc_default_options = {"members": True, "show-inheritance": True}

# napoleon: numpydoc sections only; parameter types as plain text
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_param = False
napoleon_use_rtype = False
napoleon_use_ivar = False
# "Attributes" sections render like "Parameters": a field list whose types are plain text (types
# such as "int array (n,)" are descriptions, not cross-references)
napoleon_custom_sections = [("Attributes", "params_style")]
napoleon_include_init_with_doc = False

# MyST: the Markdown pages and the included results pages
myst_heading_anchors = 3
myst_enable_extensions = ["deflist"]

# HTML: Furo (the docs extra), a wide responsive layout (code blocks and --help text get the width of
# the window; a narrow one folds the sidebars away), light and dark; no remote assets
html_theme = "furo"
html_title = f"arpy {release}"
html_static_path = ["_static"]
html_css_files = ["arpy.css"]          # a wider text column (see the file)
html_theme_options = {"sidebar_hide_name": False, "navigation_with_keys": True}
