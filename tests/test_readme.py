"""The README names every command of the command line and every make target it shows."""

from __future__ import annotations

import re
from pathlib import Path

from cellcoadd.cli.main import COMMANDS

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def test_readme_lists_every_command():
    sentence = README[README.index("From the command line:") :].split("(each with")[0]
    listed = set(re.findall(r"`(?:cellcoadd )?([a-z-]+)`", sentence))
    assert listed == set(COMMANDS), (set(COMMANDS) - listed, listed - set(COMMANDS))


def test_readme_make_targets_exist():
    targets = set(re.findall(r"^([a-z-]+):", (ROOT / "Makefile").read_text(), re.MULTILINE))
    shown = set(re.findall(r"^make ([a-z-]+)", README, re.MULTILINE))
    assert shown and shown <= targets, shown - targets


def test_the_compile_time_is_said_alike_everywhere():
    """README, tutorial and `cellcoadd demo` give the one measured compile time."""
    from cellcoadd.pipelines.warmup import COMPILE_TIME

    tutorial = (ROOT / "docs" / "tutorial.md").read_text()
    for text in (README, tutorial):
        assert COMPILE_TIME in " ".join(text.split()), COMPILE_TIME
    assert "10-40 s" not in README + tutorial
