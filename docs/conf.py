"""Sphinx configuration of the formtwin documentation (``make docs``).

The Markdown pages stay Markdown (MyST). Two reference pages are generated at build time
and are not kept in the repository: ``reference/commands.md`` from the ``formtwin``
argument parser and ``reference/api/*.md`` (one page per module, autodoc). The build is
offline: no intersphinx, no link checks outside the site.
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "src"))
sys.path.insert(0, str(HERE / "_ext"))

from reference_pages import write_api_pages, write_cli_page  # noqa: E402

import formtwin  # noqa: E402

project = "formtwin"
author = "formtwin authors"
copyright = "formtwin authors, MIT licence"  # noqa: A001 - Sphinx's name
release = formtwin.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "_ext", "figures/*.py", "study_results/report.html",
                    "**/.ipynb_checkpoints"]

myst_heading_anchors = 4
myst_enable_extensions = ["colon_fence", "dollarmath"]
# numpydoc types such as "ndarray, shape (n, n_t)" name several attributes called n or
# n_t; an ambiguous word in a type is not a broken reference
suppress_warnings = ["ref.python"]

autodoc_default_options = {"members": True, "undoc-members": False, "show-inheritance": True}
autodoc_typehints = "description"
autodoc_member_order = "bysource"
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False
# attributes as fields of their class: the dataclasses' fields are documented once
napoleon_use_ivar = True

html_theme = "furo"
html_title = f"formtwin {release}"
html_static_path: list[str] = []

write_cli_page(HERE / "reference" / "commands.md")
write_api_pages(HERE / "reference" / "api")
