"""Survey presets: ``bad_mask_bits = "des"`` / ``"lsst"`` in a configuration file,
``BuildConfig.for_survey``, errors that name the preset, ``cellcoadd init``, and the LSST
``PhotoCalib`` (afw archive) read as a zero point.

Files are written here with the survey's structure: DES ``SCI``/``MSK``/``WGT`` with the
real DECam CCD header (``tests/data/des``) on small planes, LSST ``ExposureF`` files
with ``MP_*`` planes and an afw archive holding a ``PhotoCalib`` catalog.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import fitsio
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import DES_PSF
from test_survey_readers import LSST_PLANES, PSF, des_header_cards, lsst_planes, write_lsst

from cellcoadd import BuildConfig
from cellcoadd.builder.inputs import check_mask_bits
from cellcoadd.cli.main import cli
from cellcoadd.errors import CellCoaddFormatError, ConfigError, InputError
from cellcoadd.io import (
    DES_BAD_MASK_BITS,
    DES_LAYOUT,
    DES_MASK_VALUES,
    LSST_BAD_MASK_BITS,
    LSST_LAYOUT,
    MefExposureFile,
    read_build_config,
    read_lsst_exposure,
    read_manifest,
    sources_from_manifest,
)
from cellcoadd.io.exposures.manifest_io import build_config_toml
from cellcoadd.model.units import NJY_ZERO_POINT

# -- presets in configurations ------------------------------------------------------------


@pytest.mark.parametrize(
    ("survey", "bits"), [("des", DES_BAD_MASK_BITS), ("lsst", LSST_BAD_MASK_BITS)]
)
def test_preset_in_a_config_file_and_for_survey(tmp_path, survey, bits):
    toml = tmp_path / "build.toml"
    toml.write_text(f'bad_mask_bits = "{survey}"\nn_noise = 2\n')
    config = read_build_config(toml)
    assert config.bad_mask_bits == bits and config.n_noise == 2
    assert BuildConfig.for_survey(survey, n_noise=2) == config
    as_json = tmp_path / "build.json"
    as_json.write_text(f'{{"bad_mask_bits": "{survey.upper()}"}}')
    assert read_build_config(as_json).bad_mask_bits == bits
    # the file `cellcoadd init` writes names the preset and reads back the same
    text = build_config_toml(config, preset=survey)
    assert f'bad_mask_bits = "{survey}"' in text
    assert read_build_config(_write(tmp_path / "again.toml", text)) == config
    # stored (and dumped) as the bit names: a coadd's file says which bits were bad
    assert BuildConfig.model_validate_json(config.model_dump_json()) == config


def test_unknown_preset_is_refused_with_the_choices(tmp_path):
    with pytest.raises(ConfigError, match=r"build.toml.*unknown mask-bit preset 'hsc'.*des"):
        read_build_config(_write(tmp_path / "build.toml", 'bad_mask_bits = "hsc"\n'))
    with pytest.raises(ValueError, match="lsst"):
        BuildConfig.for_survey("hsc")


def test_config_show_prints_values_as_given():
    shown = CliRunner().invoke(cli, ["config", "--show"])
    assert shown.exit_code == 0, shown.output
    assert "31.40006" not in shown.output
    assert "zero_point = 31.4 for nJy" in shown.output  # a comment: fixed for nJy


# -- errors that name the preset ----------------------------------------------------------


def write_small_des(path: Path, shape=(96, 64), magzero: float | None = 30.25) -> Path:
    """A DES ``immasked`` file: the real CCD's header cards on small planes."""
    rng = np.random.default_rng(3)
    image = rng.normal(0.0, 5.0, shape).astype(np.float32)
    mask = np.zeros(shape, dtype=np.int16)
    mask[5, 7] = DES_MASK_VALUES["BADPIX_CRAY"]
    weight = np.full(shape, 0.04, dtype=np.float32)
    cards = des_header_cards(magzero=magzero)
    with fitsio.FITS(path, "rw", clobber=True) as fits:
        fits.write(None)
        fits.write(image, extname="SCI", header=cards, compress="GZIP_2", qlevel=None)
        fits.write(mask, extname="MSK", header=cards, compress="RICE")
        fits.write(weight, extname="WGT", header=cards, compress="GZIP_2", qlevel=None)
    return path


def test_missing_bits_error_names_the_fitting_preset(tmp_path):
    path = write_small_des(tmp_path / "D00154912_r_c12_r2369p01_immasked.fits.fz")
    header = MefExposureFile(path, DES_LAYOUT, DES_PSF).header()
    with pytest.raises(InputError) as info:
        check_mask_bits([header], BuildConfig())
    message = str(info.value)
    assert "visit=154912, detector=12" in message
    assert "'des' preset" in message and 'for_survey("des")' not in message
    assert "BuildConfig.for_survey('des')" in message and "DES_BAD_MASK_BITS" in message
    check_mask_bits([header], BuildConfig.for_survey("des"))  # and the preset fits


def test_lsst_bits_suggest_the_lsst_preset(tmp_path):
    path = write_lsst(tmp_path / "calexp.fits")
    header = MefExposureFile(path, LSST_LAYOUT, PSF).header()
    with pytest.raises(InputError, match="'lsst' preset"):
        check_mask_bits([header], BuildConfig(bad_mask_bits=("BAD", "SPIKE")))
    check_mask_bits([header], BuildConfig.for_survey("lsst"))
    no_fit = {k: v for k, v in LSST_PLANES.items() if k != "CR"}
    odd = write_lsst(tmp_path / "odd.fits", planes_keywords=no_fit)
    with pytest.raises(InputError) as info:
        check_mask_bits([MefExposureFile(odd, LSST_LAYOUT, PSF).header()], BuildConfig())
    assert "preset" not in str(info.value)  # no preset fits: no advice to use one


# -- cellcoadd.io --------------------------------------------------------------------------


def test_io_is_an_attribute_of_the_package_and_import_stays_cheap():
    code = (
        "import sys, cellcoadd; "
        "heavy = [m for m in ('numba', 'galsim', 'matplotlib', 'dask') if m in sys.modules]; "
        "assert not heavy, heavy; "
        "assert 'io' in dir(cellcoadd); "
        "print(cellcoadd.io.DES_MASK_VALUES['BADPIX_CRAY'], cellcoadd.io.DES_LAYOUT.name)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["16", "des"]


# -- LSST PhotoCalib ----------------------------------------------------------------------

ARCHIVE_INDEX = [("id", "i4"), ("cat.archive", "i4"), ("row0", "i4"), ("nrows", "i4")]


def write_lsst_photocalib(path: Path, calibration_mean: float, *, object_id: int = 7) -> Path:
    """An ``ExposureF`` file without ``FLUXMAG0`` whose calibration is a ``PhotoCalib`` in
    its afw archive: index HDU (number ``AR_HDU``, 1-based), a PSF catalog, the
    ``PhotoCalib`` catalog (second row of its HDU, ``cat.archive`` counted from the index)."""
    write_lsst(path, lsst_planes(), calib="none")
    index = np.array(
        [(1, 1, 0, 1), (object_id, 2, 1, 1)],  # PSF_ID = 1; the PhotoCalib
        dtype=ARCHIVE_INDEX,
    )
    psf = np.zeros(1, dtype=[("sigma", "f8")])
    calib = np.array(
        [(0.5, 0.0, True), (calibration_mean, 0.01, True)],
        dtype=[("calibrationMean", "f8"), ("calibrationErr", "f8"), ("isConstant", "?")],
    )
    with fitsio.FITS(path) as fits:  # write_lsst's planes; its archive index replaced
        assert fits[4].get_extname() == "ARCHIVE_INDEX" and fits[0].read_header()["AR_HDU"] == 5
        hdus = [(fits[i].read(), fits[i].read_header()) for i in range(4)]
    hdus[0][1]["PHOTOCALIB_ID"] = object_id
    with fitsio.FITS(path, "rw", clobber=True) as fits:
        fits.write(None, header=hdus[0][1])
        for data, header in hdus[1:]:
            fits.write(data, header=header, extname=header["EXTNAME"])
        fits.write(index, extname="ARCHIVE_INDEX")
        fits.write(psf, extname="ARCHIVE_DATA")
        fits.write(calib, extname="ARCHIVE_DATA")
    return path


@pytest.mark.parametrize("zero_point", [27.85, NJY_ZERO_POINT])
def test_photocalib_is_read_as_the_zero_point(tmp_path, zero_point):
    mean = 10 ** (-0.4 * (zero_point - NJY_ZERO_POINT))  # nJy per count
    path = write_lsst_photocalib(tmp_path / "visit_image.fits", mean)
    assert "FLUXMAG0" not in fitsio.read_header(path, 0)
    exposure = read_lsst_exposure(path, PSF, zero_point=20.0)  # the file's calibration wins
    assert exposure.zero_point == pytest.approx(zero_point, abs=1e-12)
    # one count is calibrationMean nJy: flux in nJy = counts * mean
    assert 10 ** (-0.4 * (exposure.zero_point - NJY_ZERO_POINT)) == pytest.approx(mean)


def test_broken_photocalib_names_the_file_and_hdu(tmp_path):
    path = write_lsst_photocalib(tmp_path / "bad.fits", -1.0)
    with pytest.raises(CellCoaddFormatError, match=r"bad.fits: HDU 6 \(ARCHIVE_DATA\).*-1.0"):
        read_lsst_exposure(path, PSF)
    path = write_lsst_photocalib(tmp_path / "lost.fits", 1.0)
    with fitsio.FITS(path, "rw") as fits:
        fits[0].write_key("PHOTOCALIB_ID", 99)
    with pytest.raises(CellCoaddFormatError, match=r"lost.fits: HDU 4 .*PHOTOCALIB_ID=99"):
        read_lsst_exposure(path, PSF)
    with fitsio.FITS(path, "rw") as fits:
        fits[0].write_key("AR_HDU", 40)
    with pytest.raises(CellCoaddFormatError, match=r"lost.fits: HDU 0.*AR_HDU = 40"):
        read_lsst_exposure(path, PSF)


# -- cellcoadd init ------------------------------------------------------------------------


def test_init_writes_a_manifest_and_config_build_reads(tmp_path):
    (tmp_path / "ccds").mkdir()
    root = tmp_path / "ccds"
    names = ["D00154912_r_c12_r2369p01", "D00154913_r_c12_r2369p01", "D00154914_r_c12_r2369p01"]
    for stem in names:
        write_small_des(root / f"{stem}_immasked.fits.fz")
    for stem in names[:2]:
        (root / f"{stem}_psfexcat.psf").write_bytes(DES_PSF.read_bytes())
    (root / f"{names[0]}_bkg.fits.fz").write_bytes(b"")  # matched by name, never opened here
    (root / "notes.txt").write_text("not an exposure")
    result = CliRunner().invoke(cli, ["init", "--survey", "des", str(root)])
    assert result.exit_code == 0, result.output
    assert "2 of 3 exposures with a PSF file" in result.output
    assert f"no PSF model file for {names[2]}_immasked.fits.fz" in result.output
    manifest = read_manifest(root / "manifest.toml")
    assert [e.path for e in manifest.exposures] == [f"{n}_immasked.fits.fz" for n in names[:2]]
    assert all(e.layout == "des" for e in manifest.exposures)
    assert manifest.exposures[0].psf == f"{names[0]}_psfexcat.psf"
    assert manifest.exposures[0].background == f"{names[0]}_bkg.fits.fz"
    assert manifest.exposures[1].background is None
    assert f'# path = "{names[2]}_immasked.fits.fz"' in (root / "manifest.toml").read_text()
    assert read_build_config(root / "build.toml") == BuildConfig.for_survey("des")
    # the files it lists are read as the DES layout, with the header's zero point
    (root / f"{names[0]}_bkg.fits.fz").unlink()
    text = (root / "manifest.toml").read_text().replace(f'background = "{names[0]}_bkg', "# x")
    sources = sources_from_manifest(read_manifest(_write(root / "m2.toml", text)), root)
    assert [s.header().key for s in sources] == [(154912, 12), (154912, 12)]
    assert sources[0].header().zero_point == 30.25
    again = CliRunner().invoke(cli, ["init", "--survey", "des", str(root)])
    assert again.exit_code != 0 and "--overwrite" in again.output


def test_init_lsst_matches_piff_and_psfex_files_and_refuses_empty_dirs(tmp_path):
    for stem in ("calexp_2024031500123_R22_S11", "calexp_2024031500124_R22_S11"):
        write_lsst(tmp_path / f"{stem}.fits")
    (tmp_path / "calexp_2024031500123_R22_S11.piff").write_bytes(b"")
    (tmp_path / "calexp_2024031500124_R22_S11_psfexcat.psf").write_bytes(b"")
    result = CliRunner().invoke(cli, ["init", "--survey", "lsst", str(tmp_path)])
    assert result.exit_code == 0, result.output
    entries = read_manifest(tmp_path / "manifest.toml").exposures
    assert [(e.layout, e.psf) for e in entries] == [
        ("lsst", "calexp_2024031500123_R22_S11.piff"),
        ("lsst", "calexp_2024031500124_R22_S11_psfexcat.psf"),
    ]
    assert read_build_config(tmp_path / "build.toml").bad_mask_bits == LSST_BAD_MASK_BITS
    (tmp_path / "empty").mkdir()
    empty = CliRunner().invoke(cli, ["init", "--survey", "lsst", str(tmp_path / "empty")])
    assert empty.exit_code != 0 and "no LSST exposure files" in empty.output


def test_zero_point_helper_agrees_with_fluxmag0():
    from cellcoadd.io.exposures.lsst_photocalib import zero_point_from_calibration

    fluxmag0 = 10 ** (0.4 * 28.7)  # counts of a magnitude-0 source
    mean = 3631e9 / fluxmag0  # nJy per count
    assert zero_point_from_calibration(mean) == pytest.approx(2.5 * math.log10(fluxmag0))
    assert zero_point_from_calibration(0.0) is None


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path
