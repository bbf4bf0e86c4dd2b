"""Every `Examples:` line of every command's --help runs (with small sizes, in a
temporary folder holding the files the examples name).

Sizes are shrunk (visits, objects, trials...) so the whole set takes seconds; the
commands, options and file names are the examples' own. Skipped, with the reason:
the `<command> --help` placeholder, the DES manifest build on a dask scheduler (needs
survey files and a running scheduler) and `show ... --cell 41,17` (needs a full-size
LSST patch of 22 x 22 cells).
"""

from __future__ import annotations

import glob
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from cellcoadd.cli.main import cli

SKIP = {
    "cellcoadd <command> --help": "a placeholder",
    "--scheduler tcp://": "needs DES survey files and a running dask scheduler",
    "--cell 41,17": "needs a full-size LSST patch (22 x 22 cells)",
}

#: option -> small value replacing the example's
SHRINK = {
    "--visits": "1",
    "--objects": "2",
    "--n-objects": "2",
    "--trials": "20",
    "--n-cells": "40",
    "--workers": "1",
}
#: command -> options appended (the last occurrence of an option wins)
EXTRA = {
    "demo": ["--visits", "1", "--workers", "1", "--quiet"],
    "simulate": ["--visits", "1", "--objects", "2", "--quiet"],
    "validate-shear": ["--n-objects", "2", "--bfd-templates", "4", "--quiet"],
    "analyze rejection": ["--n-cells", "40", "--n-visits", "4"],
    "analyze snr-loss": ["--trials", "20"],
}


def _commands(group: click.Group, prefix: list[str]):
    for name in group.list_commands(None):  # type: ignore[arg-type]
        command = group.get_command(None, name)  # type: ignore[arg-type]
        yield [*prefix, name], command
        if isinstance(command, click.Group):
            yield from _commands(command, [*prefix, name])


def _examples() -> list[tuple[str, list[str]]]:
    """(command name, its example lines) for the group and every command."""
    found = []
    for path, _ in [([], cli), *_commands(cli, [])]:
        text = CliRunner().invoke(cli, [*path, "--help"]).output
        block = re.search(r"Examples:\n((?:  .*\n)+)", text)
        assert block, f"cellcoadd {' '.join(path)} --help has no examples"
        lines = block.group(1).replace("\\\n", " ").splitlines()
        found.append((" ".join(path) or "cellcoadd", [" ".join(x.split()) for x in lines]))
    return found


EXAMPLES = _examples()


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    """The files the examples name: simulations, coadds, a catalog, a sky map."""
    root = tmp_path_factory.mktemp("library")
    runner = CliRunner()

    def run(*args: str) -> None:
        result = runner.invoke(cli, list(args), catch_exceptions=False)
        assert result.exit_code == 0, result.output

    run("simulate", "--out", str(root / "sim"), "--visits", "1", "--patch", "0,0", "-q")
    run("simulate", "--out", str(root / "sim11"), "--visits", "1", "-q")
    files = sorted(glob.glob(str(root / "sim11" / "visit*-det*.fits")))
    (root / "demo-output").mkdir()
    run(
        "build", *files, "--skymap", str(root / "sim11" / "skymap.json"), "--tract", "0",
        "--patch", "1,1", "--out", str(root / "demo-output" / "coadd.h5"), "--n-noise", "3", "-q",
    )  # fmt: skip
    run("convert", str(root / "demo-output" / "coadd.h5"), str(root / "patch.fits"))
    shutil.copy(root / "sim11" / "truth.fits", root / "demo-output" / "truth.fits")
    shutil.copy(root / "sim11" / "truth.fits", root / "cat.fits")
    run("skymap", "--center", "150.1,2.2", "--cells-per-patch", "4", "--out", str(root / "sk.json"))
    return root


def _prepare(command: str, library: Path, work: Path) -> None:
    links = {
        "build": ["sim"],
        "index": ["sim"],
        "run": ["sim"],
        "info": ["patch.fits"],
        "show": ["demo-output"],
        "trim": ["demo-output", "cat.fits", "patch.fits"],
        "convert": ["patch.fits"],
        "schemas": [],
    }.get(command, [])
    for name in links:
        if (library / name).is_dir():
            shutil.copytree(library / name, work / name)
        else:
            shutil.copy(library / name, work / name)
    if command == "info":
        shutil.copy(library / "demo-output" / "coadd.h5", work / "patch.h5")
    if command == "locate":
        shutil.copy(library / "sk.json", work / "skymap.json")
    if command == "init":  # a DES CCD (the real header) and an LSST visit image
        from conftest import DES_PSF
        from test_presets import write_lsst, write_small_des

        (work / "des-ccds").mkdir()
        write_small_des(work / "des-ccds" / "D00154912_r_c12_r2369p01_immasked.fits.fz")
        shutil.copy(DES_PSF, work / "des-ccds" / "D00154912_r_c12_r2369p01_psfexcat.psf")
        (work / "visit_images").mkdir()
        write_lsst(work / "visit_images" / "visit_image_2025061100123_94.fits")
    (work / "docs" / "images").mkdir(parents=True)


def _run_one(command: str, line: str, work: Path) -> bool:
    """Run one example line; True when every part of it succeeded."""
    line = line.replace("/tmp/", f"{work}/tmp/")
    for part in line.split("&&"):
        words = shlex.split(part)
        redirect = None
        if ">" in words:
            words, redirect = words[: words.index(">")], words[words.index(">") + 1]
        if words[0] != "cellcoadd":  # e.g. diff: a real program
            if subprocess.run(words, cwd=work, capture_output=True).returncode:
                return False
            continue
        args = []
        for word in words[1:]:
            args.extend(sorted(glob.glob(str(work / word))) if "*" in word else [word])
        for index, word in enumerate(args[:-1]):
            if word in SHRINK:
                args[index + 1] = SHRINK[word]
        args += EXTRA.get(command, []) if "--help" not in args else []
        result = CliRunner().invoke(cli, args)
        if result.exit_code != 0:
            print(f"{line}\n{result.output}\n{result.exception!r}")
            return False
        if redirect:
            (work / redirect).write_text(result.output)
    return True


#: examples known to be wrong (their owners to fix; the test fails once they work, so
#: that the entry is removed): `visit*.fits` also matches sim/visits.fits, the table of
#: visits, where `visit*-det*.fits` names the exposures only; the last convert example
#: writes patch.h5, which its first example created, without --overwrite
KNOWN_BROKEN = {}

#: running the demo takes tens of seconds; tests/test_demo.py runs it in the default suite
SLOW = {"cellcoadd", "demo"}

COMMANDS = [
    pytest.param(command, lines, id=command, marks=[pytest.mark.slow] if command in SLOW else [])
    for command, lines in EXAMPLES
]


@pytest.mark.parametrize(("command", "lines"), COMMANDS)
def test_help_examples_run(command, lines, library, tmp_path, monkeypatch):
    """The examples of one command, in order, in one folder (they may build on each
    other: `config --show > build.toml`, then `config --check build.toml`)."""
    work = tmp_path / "work"
    (work / "tmp").mkdir(parents=True)
    _prepare(command.split()[0], library, work)
    monkeypatch.chdir(work)
    failed, stale = [], []
    for line in lines:
        if any(marker in line for marker in SKIP):
            continue
        broken = any(line.startswith(marker) for marker in KNOWN_BROKEN)
        ok = _run_one(command, line, work)
        if broken and ok:
            stale.append(line)
        elif not broken and not ok:
            failed.append(line)
    assert not failed, f"help examples fail: {failed}"
    assert not stale, f"these examples work now, remove them from KNOWN_BROKEN: {stale}"
