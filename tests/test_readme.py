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
