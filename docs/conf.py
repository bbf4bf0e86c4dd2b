"""Sphinx configuration of cellcoadd's documentation: the narrative Markdown pages (MyST)
and an API reference generated from the numpydoc docstrings (autosummary).

Build with ``make docs`` (warnings are errors). The build needs no network:

* intersphinx links to numpy, astropy, GalSim and dask are made only for the projects
  whose inventory is present as ``docs/_inventories/<project>.inv`` (``make
  docs-inventories`` downloads them where there is network); a project without one is
  left out of ``intersphinx_mapping``, so its names are printed as plain text instead of
  links and nothing is fetched. Set ``CELLCOADD_DOCS_INTERSPHINX=online`` to fetch the
  missing inventories from the web instead.
* nothing else is downloaded (the theme and its assets come with the ``docs`` extra).
"""

from __future__ import annotations

import os
import re
import sys
import types
import typing
import warnings
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # the source tree, not an installed copy

from cellcoadd import __version__  # noqa: E402

project = "cellcoadd"
author = "the cellcoadd developers"
copyright = "the cellcoadd developers, BSD-3-Clause"
version = release = __version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.intersphinx",
    "numpydoc",
    "myst_parser",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "_inventories", "Thumbs.db", ".DS_Store"]
templates_path = ["_templates"]

# -- MyST: the Markdown pages as they are on the forge ------------------------------------
myst_heading_anchors = 3  # [text](page.md#a-heading) links
myst_enable_extensions = ["colon_fence"]

# -- API reference --------------------------------------------------------------------------
autosummary_generate = True
autosummary_imported_members = False
# each module documents the names it defines; a package's re-exports (its __all__) are
# documented once, in their home module
autodoc_default_options = {"members": True, "ignore-module-all": True, "show-inheritance": True}
autodoc_typehints = "none"  # the numpydoc Parameters sections say the types and units
autodoc_member_order = "bysource"
autoclass_content = "class"
numpydoc_show_class_members = False  # autosummary lists members; no duplicate stubs
numpydoc_class_members_toctree = False
# parameter types name numpy, astropy, GalSim and dask classes: linked through intersphinx
# when its inventory is there (only the aliased names; other words stay plain text)
numpydoc_xref_param_type = True
numpydoc_xref_ignore = "all"
numpydoc_xref_aliases = {
    # numpydoc's defaults for these are :ref: and :term: roles, which warn (errors here)
    # when their project's inventory is absent; class roles fall back to plain text
    "bool": ":class:`python:bool`",
    "boolean": ":class:`python:bool`",
    "array_like": ":class:`numpy.typing.ArrayLike`",
    "array-like": ":class:`numpy.typing.ArrayLike`",
    "scalar": ":class:`numpy.generic`",
    "iterable": ":class:`python:collections.abc.Iterable`",
    "sequence": ":class:`python:collections.abc.Sequence`",
    "generator": ":class:`python:collections.abc.Generator`",
    "ndarray": "numpy.ndarray",
    "WCS": "astropy.wcs.WCS",
    "Header": "astropy.io.fits.Header",
    "GSObject": "galsim.GSObject",
    "Executor": "concurrent.futures.Executor",
    "Client": "distributed.Client",
}
add_module_names = False

# -- intersphinx, offline first ---------------------------------------------------------------
INTERSPHINX = {
    "python": "https://docs.python.org/3/",
    "numpy": "https://numpy.org/doc/stable/",
    "astropy": "https://docs.astropy.org/en/stable/",
    "galsim": "https://galsim-developers.github.io/GalSim/_build/html/",
    "dask": "https://docs.dask.org/en/stable/",
    "distributed": "https://distributed.dask.org/en/stable/",
}
ONLINE = os.environ.get("CELLCOADD_DOCS_INTERSPHINX", "").lower() == "online"
INVENTORIES = HERE / "_inventories"


def _mapping() -> dict[str, tuple[str, str | None]]:
    mapping: dict[str, tuple[str, str | None]] = {}
    for name, url in INTERSPHINX.items():
        local = INVENTORIES / f"{name}.inv"
        if local.is_file():
            mapping[name] = (url, str(local))
        elif ONLINE:
            mapping[name] = (url, None)
    return mapping


def fetch_inventories() -> None:
    """Download the inventories into ``docs/_inventories`` (``make docs-inventories``);
    a project that cannot be reached is skipped, with a message."""
    import urllib.request

    INVENTORIES.mkdir(exist_ok=True)
    for name, url in INTERSPHINX.items():
        try:
            with urllib.request.urlopen(url + "objects.inv", timeout=30) as response:
                data = response.read()
        except OSError as err:
            print(f"{name}: not fetched ({err})")
            continue
        if not data.startswith(b"# Sphinx inventory"):
            print(f"{name}: {url}objects.inv is not a Sphinx inventory, skipped")
            continue
        (INVENTORIES / f"{name}.inv").write_bytes(data)
        print(f"{name}: {len(data)} bytes")


intersphinx_mapping = _mapping()
intersphinx_timeout = 10

# numpydoc reads the docstrings of base classes from other packages (numba's) too
warnings.filterwarnings("ignore", "Unknown section", UserWarning, "numpydoc")

# a code block the highlighter cannot parse (JSON with "..." elisions, CSV) is shown plain
suppress_warnings = ["misc.highlighting_failure"]


def _skip_type_alias(app: Any, what: str, name: str, obj: Any, skip: bool, options: Any) -> Any:
    """Type aliases (``Task = tuple[...]``) are not classes to document: skipped."""
    if isinstance(obj, types.GenericAlias) or type(obj).__module__ == typing.__name__:
        return True
    return None


#: a Markdown link to a Markdown file outside docs/ (``[README](../README.md)``)
OUTSIDE_MD_LINK = re.compile(r"\]\((\.\./[^)#\s]+\.md)(#[^)\s]*)?\)")


def _outside_links(app: Any, docname: str, source: list[str]) -> None:
    """Links from a page to Markdown files outside docs/ (the README, ...), which MyST
    would look for among the pages: made links to the file itself (``path:``, copied to
    the build as a download), as for any other file of the repository."""
    source[0] = OUTSIDE_MD_LINK.sub(r"](path:\1)", source[0])


def setup(app: Any) -> None:
    app.connect("autodoc-skip-member", _skip_type_alias)
    app.connect("source-read", _outside_links)


# -- HTML ---------------------------------------------------------------------------------------
html_theme = "furo"
html_title = f"cellcoadd {version}"
html_static_path: list[str] = []
