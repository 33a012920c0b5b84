"""Sphinx configuration of the knitfem documentation (``make docs``)."""

import os
import sys

ROOT = os.path.abspath("..")
sys.path[:0] = [ROOT, os.path.abspath("_ext")]

project = "knitfem"
author = "the knitfem developers"
copyright = "2026, the knitfem developers"
release = "0.1.0"

extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon",
              "knitfem_docs"]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
exclude_patterns = ["_build", "_generated"]
myst_heading_anchors = 3
html_theme = "furo"
html_title = "knitfem"
autodoc_member_order = "bysource"
autodoc_typehints = "none"
napoleon_numpy_docstring = True
napoleon_google_docstring = False
