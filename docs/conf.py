"""Sphinx configuration of the documentation site (GitHub issue 45).

Build it offline with ``python -m sphinx -W --keep-going -b html docs docs/_build/html``
(``pip install -e ".[docs]"``), then open ``docs/_build/html/index.html``.
"""

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the checkout's package, even where it is not installed
sys.path.insert(0, str(ROOT / "docs" / "_ext"))  # this site's own extension
os.environ.setdefault("MUJOCO_GL", "egl")  # what torchrl_dalir sets on import; no rendering happens here

import torchrl_dalir  # noqa: E402

project = "torchrl_dalir"
author = "torchrl_dalir contributors"
copyright = "torchrl_dalir contributors, MIT license"
version = release = torchrl_dalir.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "myst_parser",
    "dalir_autodoc",  # docs/_ext: re-exported constants' "#:" comments, classes' __init__ signatures
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
# Not pages: the build output, and the generated markdown tables next to the results' JSON
# (each is a bare table that docs/results/README.md describes; the JSON files hold the same numbers).
exclude_patterns = [
    "_build",
    "Thumbs.db",
    ".DS_Store",
    "results/table*.md",
    "results/trusted_selection_screen.md",
    "results/student_summary.md",
]

# --- autodoc and napoleon: Google-style docstrings (Args, Returns, Example) ---
autoclass_content = "class"  # the arguments are documented in the class docstring
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_default_options = {"show-inheritance": True}  # "Bases: LossModule", "Bases: TensorDictModuleBase"
autodoc_inherit_docstrings = False  # torch's and TorchRL's own docstrings stay on their sites
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
napoleon_use_ivar = True
# Every optional dependency (ray, wandb, zarr) is installed with the [test] extra; none is mocked.
autodoc_mock_imports: list[str] = []

# No intersphinx (the build is offline), so torch, TorchRL and tensordict types cannot resolve: nitpicky stays
# off and an unresolved Python reference renders as plain code. MyST links between pages are still checked:
# a link to a missing page or heading fails the build.
nitpicky = False

# --- MyST: the Markdown guides and results pages ---
myst_heading_anchors = 3  # "page.md#a-heading" links, as GitHub renders them

# --- HTML ---
html_theme = "furo"
html_title = f"torchrl_dalir {release}"
html_static_path: list[str] = []
html_show_sourcelink = True
