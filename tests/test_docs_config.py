"""docs/conf.py builds offline: intersphinx uses only the inventories present on disk
(else nothing is fetched) unless CELLCOADD_DOCS_INTERSPHINX=online. The build itself
(`make docs`, warnings as errors) runs in CI."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"


def _conf(monkeypatch, online: bool):
    if online:
        monkeypatch.setenv("CELLCOADD_DOCS_INTERSPHINX", "online")
    else:
        monkeypatch.delenv("CELLCOADD_DOCS_INTERSPHINX", raising=False)
    spec = importlib.util.spec_from_file_location("docs_conf", DOCS / "conf.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_intersphinx_uses_local_inventories_only_when_offline(monkeypatch, tmp_path):
    conf = _conf(monkeypatch, online=False)
    conf.INVENTORIES = tmp_path
    assert conf._mapping() == {}  # no inventory on disk: no entry, nothing fetched
    (tmp_path / "numpy.inv").write_bytes(b"# Sphinx inventory version 2\n")
    assert conf._mapping() == {"numpy": (conf.INTERSPHINX["numpy"], str(tmp_path / "numpy.inv"))}
    assert {"numpy", "astropy", "galsim", "dask"} <= set(conf.INTERSPHINX)


def test_online_fetches_the_missing_inventories(monkeypatch, tmp_path):
    conf = _conf(monkeypatch, online=True)
    conf.INVENTORIES = tmp_path
    assert conf._mapping()["galsim"] == (conf.INTERSPHINX["galsim"], None)


def test_type_links_never_warn_offline(monkeypatch):
    """numpydoc's :ref:/:term: links warn (errors under -W) without their inventory:
    every alias in use is a class, data or function role, which falls back to text."""
    xref = pytest.importorskip("numpydoc.xref")
    conf = _conf(monkeypatch, online=False)
    merged = {**xref.DEFAULT_LINKS, **conf.numpydoc_xref_aliases}
    assert [k for k, v in merged.items() if v.startswith((":ref:", ":term:"))] == []


def test_links_to_markdown_outside_docs_become_file_links(monkeypatch):
    conf = _conf(monkeypatch, online=False)
    source = ["[README](../README.md), [part](../README.md#testing), [page](inputs.md#units)"]
    conf._outside_links(None, "architecture", source)
    expected = "[README](path:../README.md), [part](path:../README.md), [page](inputs.md#units)"
    assert source == [expected]
