"""The command's allocator settings: applied on glibc, never over the environment's."""

from __future__ import annotations

import sys

import pytest

from cellcoadd.cli.allocator import keep_freed_memory


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_applied_on_glibc_unless_the_environment_sets_both(monkeypatch):
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    assert keep_freed_memory() is True
    monkeypatch.setenv("MALLOC_MMAP_THRESHOLD_", "131072")
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "131072")
    assert keep_freed_memory() is False


def test_the_command_starts_with_them(monkeypatch, capsys):
    """`cellcoadd` (the console entry point) applies them before any command runs."""
    import cellcoadd.cli.allocator as allocator
    from cellcoadd.cli.main import main

    calls: list[int] = []
    monkeypatch.setattr(allocator, "keep_freed_memory", lambda: calls.append(1) or True)
    try:
        main(["--version"])
    except SystemExit as done:
        assert done.code in (0, None)
    assert calls == [1] and "cellcoadd" in capsys.readouterr().out
