"""What `cellcoadd run` and `cellcoadd build` tell their user: the run's summary in the
build's words (cells, empty cells, input records by reason), the builds' warnings as one
clean line each (from the workers too), and failures in one error line."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from run_factory import BUILD, skymap, write_field

from cellcoadd.cli.main import one_line
from cellcoadd.io.exposures.index import ExposureIndex, absolute_entry
from cellcoadd.model.manifest import ManifestEntry


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """Two visits over the run factory's tract, indexed; BUILD's 15-pixel PSF stamp loses
    flux, so every build warns."""
    root = tmp_path_factory.mktemp("summary")
    paths = write_field(root / "inputs", n_visits=2)
    with ExposureIndex(root / "inputs.sqlite") as index:
        index.update([absolute_entry(ManifestEntry(path=str(p)), ".") for p in paths])
    (root / "skymap.json").write_text(skymap().to_json())
    (root / "build.json").write_text(BUILD.model_dump_json())
    return root


def _cellcoadd(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "cellcoadd", *args], capture_output=True, text=True, check=False
    )


def _no_raw_warnings(stderr: str) -> None:
    """No line of Python's own warning format: a source path and line, or the code."""
    assert "warnings.warn" not in stderr and ".py:" not in stderr, stderr


def test_run_summarises_cells_records_and_warnings_like_build(inputs, tmp_path):
    out = tmp_path / "out"
    done = _cellcoadd(
        "run", "--index", str(inputs / "inputs.sqlite"), "--skymap", str(inputs / "skymap.json"),
        "--config", str(inputs / "build.json"), "--out-dir", str(out), "--patch", "0,0",
        "--patch", "1,0", "-q", "--no-figure",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    report = json.loads((out / "report.json").read_text())
    totals = report["totals"]
    rejected = ", ".join(f"{k} {n}" for k, n in sorted(totals["rejected_records"].items()))
    assert rejected  # edges reject many records of this field
    assert (
        f"cells: {totals['cells']} ({totals['empty_cells']} empty; inner cells "
        f"{totals['inner_cells']}, {totals['empty_inner_cells']} empty); input records (one "
        f"per cell and overlapping exposure): used {totals['input_records_used']}, "
        f"rejected: {rejected}"
    ) in done.stdout
    # most records lost to CCD edges: the build's warning, said by the run too
    assert "rejected because a CCD edge or gap crosses the cell" in done.stderr
    # each patch's build warned in its process; the run says it once, counting the patches
    psf_lines = [line for line in done.stderr.splitlines() if "PsfStampWarning" in line]
    assert len(psf_lines) == 1, done.stderr
    assert psf_lines[0].startswith("warning: r tract 0 patch 0,0: PsfStampWarning: ")
    assert psf_lines[0].endswith("(and 1 more patches: see report.json)")
    _no_raw_warnings(done.stderr)
    patches = json.loads((out / "r" / "tract_0" / "report.json").read_text())["patches"]
    said = [p["warnings"] for p in patches]
    assert len(said) == 2 and all(w and w[0].startswith("PsfStampWarning: ") for w in said)


def test_build_warnings_are_one_clean_line(inputs, tmp_path):
    files = sorted(str(p) for p in (inputs / "inputs").glob("*.fits"))
    done = _cellcoadd(
        "build", *files, "--skymap", str(inputs / "skymap.json"), "--tract", "0", "--patch",
        "0,0", "--config", str(inputs / "build.json"), "--out", str(tmp_path / "p.fits"), "-q",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    lines = [line for line in done.stderr.splitlines() if "PsfStampWarning" in line]
    assert len(lines) == 1 and lines[0].startswith("warning: PsfStampWarning: "), done.stderr
    assert "psf_size" in lines[0]  # what to do
    _no_raw_warnings(done.stderr)


def test_a_line_announcing_a_list_runs_into_it():
    assert one_line("2 patches failed:\n  a: x\n  b: y\n") == "2 patches failed: a: x; b: y"
    assert one_line("bad value\nFor further information visit x\n  at row 3") == (
        "bad value; at row 3"
    )


def test_index_lists_a_bad_file_once_on_one_line(inputs, tmp_path):
    bad = tmp_path / "cut.fits"
    good = sorted((inputs / "inputs").glob("*.fits"))[0]
    bad.write_bytes(good.read_bytes()[:5000])
    done = _cellcoadd("index", str(bad), str(good), "--db", str(tmp_path / "i.sqlite"), "-q")
    assert done.returncode == 1  # a bad file: non-zero, unless --allow-bad
    lines = [line for line in done.stderr.splitlines() if str(bad) in line]
    assert len(lines) == 1 and lines[0].count(str(bad)) == 1, done.stderr
    assert lines[0].startswith(f"bad: {bad}: ") and "Error:" not in lines[0]
