"""Sphinx configuration: ``make docs`` builds the site into ``docs/_build/html``.

The API pages are autodoc (Google-style docstrings through napoleon), the prose pages are
Markdown (MyST) and the tutorials are scripts executed by sphinx-gallery at every build, so a
broken example fails it. Nothing is fetched from the network and nothing is mocked.
"""
import os
import sys
import warnings
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path[:0] = [str(ROOT), str(DOCS / "_ext")]
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("OMP_NUM_THREADS", "1")
warnings.filterwarnings("ignore", category=DeprecationWarning)

project = "torchrl_brsl"
author = "torchrl_brsl contributors"
copyright = "2022-2026, torchrl_brsl contributors"
release = version = "0.1.0"

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
    "brsl_docs",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "runs", "tutorials/README.rst", "**/GALLERY_HEADER.rst"]  # runs: archived runs
templates_path = []

# Markdown: anchors for headings down to ###, so pages can link to sections of one another
smartquotes = False  # "--reuse" stays two hyphens, quotes stay straight
myst_heading_anchors = 3
myst_enable_extensions = ["dollarmath"]

# API reference
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_class_signature = "separated"
autodoc_default_options = {"show-inheritance": True}
autodoc_preserve_defaults = True
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
napoleon_attr_annotations = True
napoleon_use_ivar = True  # an Attributes section beside autodoc's members would describe them twice

# Tutorials: every script under tutorials/ runs at every build; an error fails the build
sphinx_gallery_conf = {
    "examples_dirs": "tutorials",
    "gallery_dirs": "auto_tutorials",
    "filename_pattern": r"/plot_",
    "within_subsection_order": "FileNameSortKey",
    "download_all_examples": False,
    "remove_config_comments": True,
    "abort_on_example_error": True,
    "only_warn_on_example_error": False,
    "image_scrapers": ("matplotlib",),
    "matplotlib_animations": False,
    "reset_modules": ("matplotlib",),
    "show_memory": False,
    "plot_gallery": "True",
    "run_stale_examples": True,  # rerun unchanged tutorials too: a library change that breaks one fails the build
}

html_theme = "sphinx_rtd_theme"
html_title = "torchrl_brsl"
html_static_path = ["_static"]
html_css_files = ["brsl.css"]
html_theme_options = {"navigation_depth": 3, "collapse_navigation": False}
html_show_sourcelink = False
