"""docs/survey-runs.md's walkthrough runs as written: every `$ ` line of each block, in
an empty folder (the DES one holding DES CCD files), and the files it names are there."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import DES_PSF
from test_presets import write_small_des

DOC = (Path(__file__).resolve().parents[1] / "docs" / "survey-runs.md").read_text()
BLOCKS = dict(re.findall(r"<!-- walkthrough: (\S+) -->\n```console\n(.*?)```", DOC, re.DOTALL))


def _lines(name: str) -> list[str]:
    return [line[2:] for line in BLOCKS[name].splitlines() if line.startswith("$ ")]


def _run(lines: list[str], work: Path) -> list[str]:
    """Run each line with bash in ``work``, the library's console script first on the
    PATH; their outputs."""
    path = f"{Path(sys.executable).parent}:{shutil.which('bash') and '/usr/bin:/bin'}"
    outputs = []
    for line in lines:
        done = subprocess.run(
            ["bash", "-c", line], cwd=work, capture_output=True, text=True, env={"PATH": path}
        )
        assert done.returncode == 0, f"{line}\n{done.stdout}\n{done.stderr}"
        outputs.append(done.stdout + done.stderr)
    return outputs


def test_the_blocks_are_found():
    assert set(BLOCKS) == {"simulated", "des"}
    assert [line.split()[1] for line in _lines("simulated")] == [
        "simulate", "config", "index", "index", "run", "info",
    ]  # fmt: skip
    assert [line.split()[1] for line in _lines("des")] == ["init", "index", "skymap", "run"]


def test_the_simulated_walkthrough_runs_as_written(tmp_path):
    outputs = _run(_lines("simulated"), tmp_path)
    out = tmp_path / "coadds"
    report = json.loads((out / "report.json").read_text())
    assert report["totals"]["done"] == 9 and report["totals"]["failed"] == 0
    for name in ("patch_1_1.fits", "report.json", "coverage.png"):
        assert (out / "i" / "tract_0" / name).is_file()
    assert "cells: 324 (" in outputs[4] and "input records" in outputs[4]
    assert "rejected because a CCD edge or gap crosses the cell" in outputs[4]  # as the doc says
    assert "coverage.png" in outputs[4]  # the warning points at the figure
    # the same command again builds nothing (the ledger)
    again = _run(_lines("simulated")[4:5], tmp_path)[0]
    assert "0 built, 9 up to date" in again


@pytest.mark.slow
def test_the_des_walkthrough_runs_as_written(tmp_path):
    ccds = tmp_path / "des-ccds"
    ccds.mkdir()
    write_small_des(ccds / "D00154912_Y_c12_r2369p01_immasked.fits.fz")
    shutil.copy(DES_PSF, ccds / "D00154912_Y_c12_r2369p01_psfexcat.psf")
    outputs = _run(_lines("des"), tmp_path)
    assert "1 of 1 exposures with a PSF file" in outputs[0]
    report = json.loads((tmp_path / "des-coadds" / "report.json").read_text())
    assert report["totals"]["failed"] == 0 and set(report["bands"]) == {"Y"}  # the header's FILTER
