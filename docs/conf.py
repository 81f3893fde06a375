"""Sphinx configuration of the metadesign documentation (``make docs``; warnings are errors).

Why Sphinx: the tools this project's users already read (hcipy, poppy, prysm, gdsfactory) publish Sphinx
sites; autodoc builds the API reference from the docstrings the code already has, and sphinx-gallery runs
every example at build time (a broken example fails the build) and renders its figures.  The guide pages
are Markdown (MyST), so the prose the README used to hold moved here unchanged.
"""
import os
import sys
from pathlib import Path

for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_k, "1")
os.environ.setdefault("MPLBACKEND", "Agg")

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "_ext"))

from measured import measured  # noqa: E402

import metadesign  # noqa: E402

project = "metadesign"
author = "the metadesign developers"
copyright = "2026, the metadesign developers"
release = version = metadesign.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx_gallery.gen_gallery",
    "cli_reference",
    "measured",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "examples/README.txt", "gallery/*.ipynb", "gallery/*.py", "gallery/*.zip",
                    "gallery/*.json", "gallery/*.md5", "gallery/*.pickle"]
myst_enable_extensions = ["dollarmath", "substitution"]
# the measured results the pages quote ({{ name }}), read from the committed JSON records at build time
# (docs/_ext/measured.py: one source; a missing record fails the build)
myst_substitutions = measured()
myst_heading_anchors = 3
suppress_warnings = ["myst.xref_missing"] if os.environ.get("METADESIGN_DOCS_LAX") else []

autodoc_typehints = "none"          # the signatures stay readable; types are in the docstrings
autodoc_member_order = "bysource"
autodoc_default_options = {"members": True, "undoc-members": False}
napoleon_google_docstring = False

sphinx_gallery_conf = {
    "examples_dirs": ["examples"],
    "gallery_dirs": ["gallery"],
    "filename_pattern": r"/plot_",     # every plot_*.py runs at build time
    "abort_on_example_error": True,     # a broken example fails the build
    "download_all_examples": False,
    "remove_config_comments": True,
    "within_subsection_order": "FileNameSortKey",
    "show_memory": False,
    "image_scrapers": ("matplotlib",),
    "matplotlib_animations": False,
}

html_theme = "furo"
html_title = f"metadesign {version}"
html_static_path = []
