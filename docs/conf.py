"""Sphinx configuration: the lidarcam documentation site (`make docs`, warnings as errors).

Sphinx with the furo theme: the site is Markdown (MyST) pages beside an API reference that autodoc builds from the
docstrings and a CLI reference that sphinx-argparse builds from the parser itself, so neither can drift from the
code. The notebooks (``docs/notebooks`` links to ``notebooks/``) are executed by myst-nb (at the small sizes
their ``LIDARCAM_NOTEBOOK_FAST`` switch selects unless ``LIDARCAM_DOCS_FULL=1``), so they render with outputs.
"""
from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(ROOT))

import estimators  # noqa: E402

project = "lidarcam"
author = "the lidarcam developers"
copyright = "2026, the lidarcam developers"
release = estimators.__version__
version = release

extensions = [
    "myst_nb",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "sphinxarg.ext",
]
source_suffix = {".md": "myst-nb", ".ipynb": "myst-nb"}
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store", "**.ipynb_checkpoints", "notebooks/README.md"]
html_theme = "furo"
html_title = f"lidarcam {release}"
myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 4

autodoc_typehints = "description"
autodoc_member_order = "bysource"
napoleon_numpy_docstring = True
napoleon_google_docstring = False
napoleon_use_ivar = True

# myst-nb reads each Markdown page as a notebook without cell ids; nbformat's warning about it is not ours.
warnings.filterwarnings("ignore", message="Cell is missing an id field")

# Notebooks: docs/notebooks is a link to notebooks/ (Sphinx reads only its source folder); each runs in its own
# folder, as a user runs it.
if os.environ.get("LIDARCAM_DOCS_FULL") != "1":
    os.environ["LIDARCAM_NOTEBOOK_FAST"] = "1"
# The kernels use their own inline backend, so that each figure appears under its cell.
os.environ.pop("MPLBACKEND", None)
nb_execution_mode = os.environ.get("LIDARCAM_DOCS_EXECUTE", "cache")
nb_execution_timeout = 900
nb_execution_raise_on_error = True
nb_execution_in_temp = False
nb_execution_cache_path = str(DOCS / "_build" / ".jupyter_cache")

# The benchmark pages (one per `make bench` row, about 90) are linked from bench/index.md's list rather than its
# toctree: furo renders the whole navigation tree into every page, and with them in it that was 40% of the site's
# build (22 -> 14 s). The list is made here from the folder (each page's title), so a new page needs no edit.
BENCH = DOCS / "bench"
BENCH_LIST = "{the benchmark pages}"


def _bench_pages(app, docname: str, source: list) -> None:
    if docname == "bench/index":
        pages = sorted(p for p in BENCH.glob("*.md") if p.stem != "index")
        titles = [p.read_text().split("\n", 1)[0].lstrip("# ").strip() or p.stem for p in pages]
        source[0] = source[0].replace(BENCH_LIST, "\n".join(f"- [{p.stem}]({p.name}): {t}"
                                                            for p, t in zip(pages, titles)))
    elif docname.startswith("bench/"):  # reached from that list: not in a toctree
        source[0] = "---\norphan: true\n---\n" + source[0]


def setup(app):
    app.connect("source-read", _bench_pages)
