"""Whole-survey runs: two bands and two tracts into one output directory, equal to runs of
one band and one tract; a moved directory resumes; nothing stale is kept (changed input
files, altered index rows, missing footprint pixels); trust only from the run; files the
index found bad named in the report; kill -9 of a multi-band run resumes byte-identical."""

from __future__ import annotations

import filecmp
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
from run_factory import BUILD, survey_skymap, write_survey

from cellcoadd.errors import ConfigError, IndexRowError
from cellcoadd.io.exposures.index import ExposureIndex, FileStamp, absolute_entry
from cellcoadd.model.manifest import ManifestEntry
from cellcoadd.pipelines.survey import PatchKey, run_survey, run_tract
from cellcoadd.pipelines.survey.ledger import Ledger

REPO = Path(__file__).resolve().parents[1]


def _index(db: Path, paths, **entry) -> None:
    with ExposureIndex(db) as index:
        entries = [absolute_entry(ManifestEntry(path=str(p), **entry), ".") for p in paths]
        update = index.update(entries)
        assert not update.bad, update.bad


def _run(root: Path, out: Path, **options):
    options = {"config": BUILD, "progress": False, "figure": False, **options}
    return run_survey(root / "inputs.sqlite", survey_skymap(), out, **options)


def _patch_files(out: Path) -> list[str]:
    return sorted(str(p.relative_to(out)) for p in out.glob("*/tract_*/patch_*.fits"))


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    """Files in bands g and r over two tracts, their index, and the whole survey run."""
    root = tmp_path_factory.mktemp("survey")
    paths = write_survey(root / "inputs")
    _index(root / "inputs.sqlite", paths)
    result = run_survey(
        root / "inputs.sqlite", survey_skymap(), root / "all", config=BUILD, progress=False
    )
    assert result.ok and len(result.built) == 16, result.summary()
    return root


def _copy(survey: Path, tmp_path: Path) -> Path:
    """A private copy of the inputs and their index (for tests that change them)."""
    shutil.copytree(survey / "inputs", tmp_path / "inputs")
    _index(tmp_path / "inputs.sqlite", sorted((tmp_path / "inputs").glob("*.fits")))
    return tmp_path


def test_two_bands_and_two_tracts_in_one_directory_equal_single_runs(survey, tmp_path):
    out = survey / "all"
    files = _patch_files(out)
    assert files == [
        f"{band}/tract_{t}/patch_{x}_{y}.fits"
        for band in "gr" for t in (0, 1) for x in (0, 1) for y in (0, 1)
    ]  # fmt: skip
    # one band and one tract at a time, each into its own directory: the same bytes
    for band in "gr":
        for tract in (0, 1):
            single = tmp_path / f"{band}{tract}"
            result = run_tract(
                survey / "inputs.sqlite", survey_skymap(), tract, single, band=band,
                config=BUILD, progress=False, figure=False,
            )  # fmt: skip
            assert result.ok and len(result.built) == 4
            for name in _patch_files(single):
                assert filecmp.cmp(single / name, out / name, shallow=False), name
    report = json.loads((out / "report.json").read_text())
    assert set(report["bands"]) == {"g", "r"} and report["totals"]["done"] == 16
    assert set(report["tracts"]) == {"g/0", "g/1", "r/0", "r/1"}
    for entry in report["tracts"].values():
        tract_report = json.loads((out / entry["report"]).read_text())
        assert entry["done"] == 4 == len(tract_report["patches"])
    assert (out / "g" / "tract_1" / "coverage.png").read_bytes()[:4] == b"\x89PNG"
    # narrowing by band, tract and region: only those patches are planned
    again = _run(survey, out, bands=["g"], tracts=[1])
    assert {(k.band, k.tract) for k in again.planned} == {("g", 1)} and not again.built
    tract = survey_skymap()[1]
    inner = tract.patch(1, 0).inner_bbox
    ra, dec = tract.pixel_to_sky(
        (inner.x_start + inner.x_stop - 1) / 2, (inner.y_start + inner.y_stop - 1) / 2
    )
    box = (float(ra[0]) - 1e-4, float(ra[0]) + 1e-4, float(dec[0]) - 1e-4, float(dec[0]) + 1e-4)
    region = _run(survey, out, region=box)
    assert set(region.planned) == {PatchKey(b, 1, 1, 0) for b in "gr"}
    assert len(region.up_to_date) == 2


def test_a_moved_directory_resumes_and_rebuilds_a_deleted_file(survey, tmp_path):
    moved = tmp_path / "elsewhere" / "coadds"
    shutil.copytree(survey / "all", moved)
    cwd = os.getcwd()
    os.chdir(tmp_path)  # another working directory too
    try:
        result = _run(survey, moved)
        assert len(result.up_to_date) == 16 and not result.built
        (moved / "r" / "tract_1" / "patch_0_1.fits").unlink()
        result = _run(survey, moved, verify=True)
    finally:
        os.chdir(cwd)
    assert result.built == [PatchKey("r", 1, 0, 1)] and len(result.up_to_date) == 15
    assert filecmp.cmp(
        moved / "r/tract_1/patch_0_1.fits", survey / "all/r/tract_1/patch_0_1.fits", False
    )


def test_an_input_changed_or_deleted_without_indexing_is_never_up_to_date(survey, tmp_path):
    root = _copy(survey, tmp_path)
    out = tmp_path / "out"
    assert _run(root, out, bands=["g"], tracts=[0]).ok
    changed = root / "inputs" / "g-visit0-det0.fits"
    stamp = FileStamp.of(str(changed))
    os.utime(changed, ns=(stamp.mtime_ns + 10**9,) * 2)
    again = _run(root, out, bands=["g"], tracts=[0])
    assert not again.up_to_date or PatchKey("g", 0, 0, 0) not in again.up_to_date
    assert PatchKey("g", 0, 0, 0) in again.failed
    assert all("g-visit0-det0.fits" in why for why in again.failed.values())
    assert not (out / "g/tract_0/patch_0_0.fits").exists()  # never a stale file beside it
    # deleted: the same, naming the file as vanished
    changed.unlink()
    gone = _run(root, out, bands=["g"], tracts=[0])
    assert PatchKey("g", 0, 0, 0) in gone.failed
    assert "vanished" in gone.failed[PatchKey("g", 0, 0, 0)]


def _altered(db: Path, path: str, sql: str, *values) -> None:
    with sqlite3.connect(db) as connection:
        connection.execute(sql + " WHERE path = ?", (*values, path))


@pytest.mark.parametrize(
    "column, sql, field",
    [
        ("zero_point", "UPDATE exposures SET zero_point = zero_point + 0.5", "zero_point"),
        ("visit", "UPDATE exposures SET visit = visit + 1000", "visit"),
        ("valid_box", "UPDATE exposures SET valid_box = '[1, 109, 0, 110]'", "valid_box"),
        ("corners", "UPDATE exposures SET corners = replace(corners, '-30.', '-31.')", "corners"),
        (
            "header",
            "UPDATE exposures SET header = replace(header, '\"zero_point\":30.0', "
            "'\"zero_point\":30.5')",
            "header.zero_point",
        ),  # fmt: skip
        (
            "wcs",
            "UPDATE exposures SET header = replace(header, '\"pc\":[[-5.', '\"pc\":[[-5.0001')",
            "header.wcs",
        ),  # fmt: skip
    ],
)
def test_an_altered_index_row_is_refused_naming_the_field(survey, tmp_path, column, sql, field):
    root = _copy(survey, tmp_path)
    target = str(root / "inputs" / "g-visit0-det0.fits")
    _altered(root / "inputs.sqlite", target, sql)
    result = _run(root, tmp_path / "out", bands=["g"], tracts=[0], patches=[(0, 0)])
    assert not result.ok and not result.built  # never "up to date", never other bytes
    why = next(iter({**result.failed, **result.plan_failed}.values()))
    assert "IndexRowError" in why and "g-visit0-det0.fits" in why and field in why, why


def test_missing_footprint_pixels_are_refused_naming_the_file(survey, tmp_path):
    root = _copy(survey, tmp_path)
    with sqlite3.connect(root / "inputs.sqlite") as db:
        (row,) = db.execute(
            "SELECT id FROM exposures WHERE path LIKE '%g-visit1-det2.fits'"
        ).fetchone()
        db.execute("DELETE FROM footprint WHERE exposure = ?", (row,))
    with pytest.raises(IndexRowError, match=r"g-visit1-det2\.fits \(row \d+: 0 of \d+ pixels"):
        _run(root, tmp_path / "out")


def test_trust_comes_from_the_run_never_from_the_index(survey, tmp_path):
    """An index row that says ``trust_psf = true`` for a file with a pickled (Piff) PSF:
    the run refuses to load it unless the run itself is given trust_psf."""
    pytest.importorskip("piff")
    from survey_psf_factory import build_piff_model

    from cellcoadd.io import read_piff
    from cellcoadd.io.exposures.exposure_io import read_exposure, write_exposure
    from cellcoadd.model.exposure import Exposure

    root = _copy(survey, tmp_path)
    path = root / "inputs" / "g-visit0-det0.fits"
    plain = read_exposure(path)
    model = build_piff_model(
        tmp_path / "ccd.piff", nx=110, ny=110, pixel_scale=0.2, fwhm_range=(0.8, 0.9),
        nstars_side=(3, 3), chipnum=0,
    )  # fmt: skip
    piff_psf = read_piff(model.path, trusted=True, chipnum=0, origin=0)
    exposure = Exposure(
        image=plain.image, wcs=plain.wcs, variance=plain.variance, psf=piff_psf,
        visit=plain.visit, detector=plain.detector, band=plain.band,
        zero_point=plain.zero_point, valid_box=plain.valid_box,
    )  # fmt: skip
    write_exposure(exposure, path, overwrite=True)
    _index(root / "inputs.sqlite", [path], trust_psf=True)  # the row says "trusted"
    with ExposureIndex(root / "inputs.sqlite", readonly=True) as index:
        (row,) = [r for r in index.query(_tract_corners(0)) if r.path == str(path)]
        assert '"trust_psf":true' in row.entry_json and row.entry.trust_psf is False
    refused = _run(root, tmp_path / "refused", bands=["g"], tracts=[0], patches=[(0, 0)])
    assert "pickled" in refused.failed[PatchKey("g", 0, 0, 0)]
    trusted = _run(
        root, tmp_path / "trusted", bands=["g"], tracts=[0], patches=[(0, 0)], trust_psf=True
    )
    assert trusted.ok and trusted.built == [PatchKey("g", 0, 0, 0)]


def _tract_corners(tract_id: int):
    import numpy as np

    tract = survey_skymap()[tract_id]
    ra, dec = tract.pixel_to_sky(np.array([0.0, 160, 160, 0]), np.array([0.0, 0, 160, 160]))
    return np.column_stack([ra, dec])


def test_a_file_the_index_found_bad_is_named_by_the_run(survey, tmp_path):
    root = _copy(survey, tmp_path)
    broken = root / "inputs" / "g-visit1-det5.fits"
    with ExposureIndex(root / "inputs.sqlite") as index:
        broken.write_bytes(b"not a FITS file")
        update = index.update([absolute_entry(ManifestEntry(path=str(broken)), ".")])
        assert [path for path, _ in update.bad] == [str(broken)]
    out = tmp_path / "out"
    result = _run(root, out, bands=["g"])
    assert [item.path for item in result.bad_inputs] == [str(broken)]
    report = json.loads((out / "report.json").read_text())
    assert [item["path"] for item in report["bad_inputs"]] == [str(broken)]
    assert report["bad_inputs"][0]["reason"]


def test_an_output_directory_of_another_layout_or_sky_map_is_refused(survey, tmp_path):
    from cellcoadd import SkyMap

    older = tmp_path / "older"
    (older / "tract_0").mkdir(parents=True)
    with pytest.raises(ConfigError, match="older layout"):
        _run(survey, older)
    other = SkyMap.from_centers([(10.0, 10.0)], survey_skymap().config)
    out = tmp_path / "out"
    assert _run(survey, out, bands=["r"], tracts=[0], patches=[(0, 0)]).ok
    with pytest.raises(ConfigError, match="another sky map"):
        run_survey(survey / "inputs.sqlite", other, out, config=BUILD, progress=False)


def test_kill_9_of_a_multi_band_run_then_resume_gives_identical_bytes(survey, tmp_path):
    out = tmp_path / "out"
    (tmp_path / "skymap.json").write_text(survey_skymap().to_json())
    (tmp_path / "build.json").write_text(BUILD.model_dump_json())
    args = [
        sys.executable, "-m", "cellcoadd", "run", "--index", str(survey / "inputs.sqlite"),
        "--skymap", str(tmp_path / "skymap.json"), "--out-dir", str(out),
        "--config", str(tmp_path / "build.json"), "-q", "--no-figure",
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    first = subprocess.Popen(args, env=env, start_new_session=True, stdout=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while _done(out) < 3 and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert first.poll() is None
    os.killpg(first.pid, signal.SIGKILL)
    first.wait()
    done_before = _done(out)
    assert 3 <= done_before < 16
    second = subprocess.run(args, env=env, capture_output=True, text=True, timeout=600)
    assert second.returncode == 0, second.stdout + second.stderr
    assert f"{16 - done_before} built, {done_before} up to date, 0 failed" in second.stdout
    assert _patch_files(out) == _patch_files(survey / "all")
    for name in _patch_files(out):
        assert filecmp.cmp(out / name, survey / "all" / name, shallow=False), name
    with Ledger(out) as ledger:
        assert {r.state.value for r in ledger.records().values()} == {"done"}


def _done(out: Path) -> int:
    try:
        with sqlite3.connect(out / "ledger.sqlite", timeout=5) as db:
            return db.execute("SELECT COUNT(*) FROM patches WHERE state = 'done'").fetchone()[0]
    except sqlite3.Error:
        return 0
