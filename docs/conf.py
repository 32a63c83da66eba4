"""Sphinx configuration: the user guide (Markdown, MyST) and the API reference (autodoc, numpydoc
docstrings through napoleon). Built with warnings as errors:
python3 -m sphinx -W -b html docs docs/_build/html"""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

project = "elo-mitsuba"
author = "the elo-mitsuba developers"
copyright = "2026, the elo-mitsuba developers"
extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx.ext.mathjax"]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
exclude_patterns = ["_build"]
myst_enable_extensions = ["dollarmath"]
myst_heading_anchors = 3
napoleon_google_docstring = False
napoleon_numpy_docstring = True
autodoc_member_order = "bysource"
autodoc_typehints = "none"
# Mitsuba, Dr.Jit and the optional sweep packages are not needed to read the docstrings
autodoc_mock_imports = ["mitsuba", "drjit", "dask", "distributed", "xarray", "zarr"]
# the guide links to files of the repository outside docs/ (benchmark results, the validation
# report, examples): real files (tests/test_house.py checks each exists), not documents of this site
suppress_warnings = ["myst.xref_missing"]
html_theme = "alabaster"
