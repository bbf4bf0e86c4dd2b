"""Hostile inputs, round 3: each finding of the issue, tried as it was found.

Files are written by the tests themselves in survey shapes (LSST ``visit_image`` with a
TAN-SIP WCS, DES ``SCI``/``MSK``/``WGT`` with the real CCD's TPV header, PSFEx ``.psf``
tables, Piff files, TOML/JSON/CSV manifests). Every read that could hang runs in a thread
with a deadline.
"""

from __future__ import annotations

import concurrent.futures
import gzip
import json
import os
import shutil
from pathlib import Path

import fitsio
import galsim
import numpy as np
import pytest
from survey_psf_factory import write_psfex_file
from test_survey_readers import LSST_NX, LSST_NY, lsst_planes, write_lsst

from cellcoadd.errors import CellCoaddFormatError, PsfError
from cellcoadd.io import (
    read_build_config,
    read_exposure,
    read_lsst_exposure,
    read_manifest,
    read_piff,
    read_psf_file,
    read_psfex,
    sources_from_manifest,
    write_exposure,
)
from cellcoadd.io._files.path_gate import gate_read, gate_write
from cellcoadd.model.psf import GalSimPsf, PiffPsf, PsfexPsf

DEADLINE = 20.0  # seconds: a read that blocks (FIFO) fails the test instead of hanging it


def _within_deadline(function, *args, **kwargs):
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=1)
    future = pool.submit(function, *args, **kwargs)
    try:
        return future.result(timeout=DEADLINE)
    finally:
        pool.shutdown(wait=False)


def _refused(function, *args, match: str | None = None, **kwargs) -> CellCoaddFormatError:
    with pytest.raises(CellCoaddFormatError) as info:
        _within_deadline(function, *args, **kwargs)
    if match is not None:
        assert match in str(info.value), str(info.value)
    return info.value


@pytest.fixture(scope="module")
def psfex_path(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("psfex")
    return write_psfex_file(root / "ccd3.psf", nx=LSST_NX, ny=LSST_NY, pixel_scale=0.2).path


@pytest.fixture(scope="module")
def lsst_file(tmp_path_factory) -> Path:
    return write_lsst(tmp_path_factory.mktemp("lsst") / "visit_image.fits")


def _piff_like(path: Path, marker: Path) -> Path:
    """A file shaped like a Piff model whose 'WCS' is a pickle that would create
    ``marker`` when loaded (the attack of the issue)."""
    import pickle

    class Payload:
        def __reduce__(self):
            return (Path.touch, (marker,))

    blob = np.frombuffer(pickle.dumps(Payload()), dtype=np.uint8)
    with fitsio.FITS(path, "rw", clobber=True) as fits:
        fits.write(None)
        table = np.zeros(1, dtype=[("type", "S10"), ("piff_version", "S5")])
        table["type"], table["piff_version"] = b"Simple", b"1.7.0"
        fits.write(table, extname="psf", header={"PIFF_VERSION": "1.7.0"})
        wcs = np.zeros(1, dtype=[("chipnums", "i8"), ("wcs_str_0000", "u1", blob.size)])
        wcs["wcs_str_0000"][0] = blob
        fits.write(wcs, extname="psf_wcs")
    return path


# -- 1. code execution ---------------------------------------------------------------------


@pytest.mark.parametrize("name", ["model.piff", "model.fits", "model.psf", "model"])
def test_a_piff_file_is_never_unpickled_without_trust(tmp_path, name):
    """Issue 28.1: any manifest psf not ending in .psf was read as Piff, and Piff unpickles
    its WCS. Now the kind comes from the content, and Piff needs ``trusted=True``."""
    marker = tmp_path / "pwned"
    path = _piff_like(tmp_path / name, marker)
    error = _refused(read_psf_file, path, match="pickled")
    assert name in str(error)
    _refused(read_piff, path, match="trusted=True")
    assert not marker.exists()


def test_a_manifest_piff_psf_needs_trust_psf(tmp_path, lsst_file):
    marker = tmp_path / "pwned"
    _piff_like(tmp_path / "calexp.psf_model", marker)
    shutil.copy(lsst_file, tmp_path / "calexp.fits")
    entry = {"path": "calexp.fits", "layout": "lsst", "psf": "calexp.psf_model"}
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"exposures": [entry]}))
    with pytest.raises(CellCoaddFormatError, match="pickled") as info:
        sources_from_manifest(read_manifest(manifest), tmp_path)
    assert "calexp.psf_model" in str(info.value)
    assert not marker.exists()
    assert read_manifest(manifest).exposures[0].trust_psf is False


def test_psf_files_are_recognised_by_content(tmp_path, psfex_path):
    """A PSFEx table named ``.piff`` is PSFEx; junk named ``.psf`` is refused on reading."""
    renamed = tmp_path / "not_a.piff"
    shutil.copy(psfex_path, renamed)
    model = read_psf_file(renamed)
    assert isinstance(model, PsfexPsf) and model == read_psfex(psfex_path)
    junk = tmp_path / "junk.psf"
    junk.write_bytes(os.urandom(5000))
    _refused(read_psf_file, junk, match="not a FITS file")
    image_only = tmp_path / "image.psf"
    fitsio.write(image_only, np.zeros((5, 5)), clobber=True)
    _refused(read_psf_file, image_only, match="not a PSF model file")


def test_model_classes_never_read_files(psfex_path):
    with pytest.raises(PsfError, match="read_psfex"):
        PsfexPsf(psfex_path)  # type: ignore[arg-type]
    with pytest.raises(PsfError, match="read_piff"):
        PiffPsf(str(psfex_path))


def test_trusted_piff_still_reads(tmp_path):
    pytest.importorskip("piff")
    from survey_psf_factory import build_piff_model

    path = build_piff_model(tmp_path / "m.bin", nx=80, ny=60, nstars_side=(3, 3)).path
    model = read_psf_file(path, trusted=True)
    assert isinstance(model, PiffPsf)
    drawn = model.draw(40.0, 30.0, galsim_box(40, 30), np.eye(2) * 0.263)
    assert abs(drawn.sum() - 1.0) < 0.02


def galsim_box(x: int, y: int, half: int = 12):
    from cellcoadd.geometry.box import Box

    return Box(x_start=x - half, x_stop=x + half + 1, y_start=y - half, y_stop=y + half + 1)


# -- 2. one gate for every path --------------------------------------------------------------


def _exposure():
    from exposure_factory import make_exposure

    return make_exposure((150.0, 2.0), shape=(60, 60), psf=galsim.Gaussian(sigma=0.4))


def test_plus_n_suffix_never_reads_another_file(tmp_path, lsst_file):
    """Issue 28.2: ``e.fits+1`` read ``e.fits`` (CFITSIO's HDU suffix)."""
    write_exposure(_exposure(), tmp_path / "e.fits")
    shutil.copy(tmp_path / "e.fits", tmp_path / "e.fits+1")
    _refused(read_exposure, tmp_path / "e.fits+1", match="'+N' suffix")
    shutil.copy(lsst_file, tmp_path / "v.fits")
    shutil.copy(lsst_file, tmp_path / "v.fits+0")
    psf = GalSimPsf(galsim.Gaussian(sigma=0.4))
    _refused(read_lsst_exposure, tmp_path / "v.fits+0", psf, match="'+N' suffix")
    with pytest.raises(CellCoaddFormatError, match="'\\+N' suffix"):
        write_exposure(_exposure(), tmp_path / "new.fits+2")
    assert not (tmp_path / "new.fits+2").exists()


def test_plus_n_suffix_is_refused_by_the_build_command(tmp_path):
    from click.testing import CliRunner

    from cellcoadd.cli.build import build as build_command

    write_exposure(_exposure(), tmp_path / "e.fits")
    shutil.copy(tmp_path / "e.fits", tmp_path / "e.fits+1")
    result = CliRunner().invoke(
        build_command,
        [str(tmp_path / "e.fits+1"), "--tract", "0", "--patch", "0,0"]
        + ["--out", str(tmp_path / "p.fits")],
    )
    message = result.output + str(result.exception)  # `cellcoadd` prints it in one line
    assert result.exit_code != 0 and "+N" in message and "e.fits+1" in message, message
    assert not (tmp_path / "p.fits").exists()


def test_bang_prefix_reads_the_named_cell_coadds_file(tmp_path, monkeypatch):
    """Issue 28.2: the Rubin cell_coadds reader read ``!d/y.fits`` as ``d/y.fits``."""
    from coadd_factory import make_patch

    from cellcoadd.io import api

    monkeypatch.chdir(tmp_path)
    (tmp_path / "d").mkdir()
    (tmp_path / "!d").mkdir()
    first, second = make_patch(band="r", seed=1), make_patch(band="i", seed=2)
    api.write(first, "d/y.fits", layout="cell_coadds")
    api.write(second, "!d/y.fits", layout="cell_coadds")
    assert api.read("!d/y.fits").metadata.band == "i"
    assert api.read("d/y.fits").metadata.band == "r"


@pytest.mark.parametrize("what", ["manifest", "config", "psf", "exposure", "coadd"])
def test_symlink_to_dev_zero_is_refused_unread(tmp_path, what):
    """Issue 28.2: a symlink to /dev/zero was read whole (3 memory blow-ups)."""
    if not os.path.exists("/dev/zero"):
        pytest.skip("no /dev/zero")
    name = {"manifest": "m.toml", "config": "c.toml", "psf": "p.psf"}.get(what, "x.fits")
    link = tmp_path / name
    link.symlink_to("/dev/zero")
    reader = {
        "manifest": read_manifest,
        "config": read_build_config,
        "psf": read_psf_file,
        "exposure": read_exposure,
        "coadd": _coadd_read,
    }[what]
    error = _refused_any(reader, link)
    assert "character device" in str(error) and name in str(error)


def _coadd_read(path):
    from cellcoadd.io import api

    return api.read(path)


def _refused_any(reader, path):
    with pytest.raises(Exception) as info:  # ConfigError wraps nothing: format errors only
        _within_deadline(reader, path)
    assert isinstance(info.value, CellCoaddFormatError), repr(info.value)
    return info.value


@pytest.mark.parametrize("what", ["manifest", "config", "psf", "exposure", "coadd"])
def test_fifo_is_refused_without_blocking(tmp_path, what):
    """Issue 28.2: a FIFO as a manifest hung the reader (2 hangs)."""
    name = {"manifest": "m.json", "config": "c.json", "psf": "p.psf"}.get(what, "x.fits")
    fifo = tmp_path / name
    os.mkfifo(fifo)
    reader = {
        "manifest": read_manifest,
        "config": read_build_config,
        "psf": read_psf_file,
        "exposure": read_exposure,
        "coadd": _coadd_read,
    }[what]
    error = _refused_any(reader, fifo)
    assert "FIFO" in str(error)


def test_writers_refuse_a_fifo_or_device_target(tmp_path):
    fifo = tmp_path / "e.fits"
    os.mkfifo(fifo)
    with pytest.raises(CellCoaddFormatError, match="FIFO"):
        _within_deadline(write_exposure, _exposure(), fifo, overwrite=True)
    link = tmp_path / "z.fits"
    link.symlink_to("/dev/null")
    with pytest.raises(CellCoaddFormatError, match="character device"):
        _within_deadline(write_exposure, _exposure(), link, overwrite=True)
    assert os.path.exists("/dev/null") and not os.path.isfile("/dev/null")


@pytest.mark.parametrize(
    "name",
    ["e.fits[1]", "e.fits(t.fits)", "mem://e.fits", "https://x/e.fits", "e.fits+12", "e.fits "],
)
def test_cfitsio_syntax_is_refused_by_the_gate(tmp_path, monkeypatch, name):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(CellCoaddFormatError):
        gate_read(name, fits=True)
    with pytest.raises(CellCoaddFormatError):
        gate_write(name, fits=True)


def test_symlinks_are_resolved_and_the_target_checked(tmp_path):
    write_exposure(_exposure(), tmp_path / "e.fits")
    shutil.copy(tmp_path / "e.fits", tmp_path / "x.fits[1]")
    (tmp_path / "plain.fits").symlink_to(tmp_path / "x.fits[1]")
    # the link's own name is harmless, its target's is not: refused
    _refused(read_exposure, tmp_path / "plain.fits", match="resolved to")
    # a chain of links through a CFITSIO-like name ends at e.fits: that file is read
    (tmp_path / "e.fits+1").symlink_to(tmp_path / "e.fits")
    (tmp_path / "chain.fits").symlink_to(tmp_path / "e.fits+1")
    assert gate_read(tmp_path / "chain.fits", fits=True) == os.path.realpath(tmp_path / "e.fits")
    (tmp_path / "ok.fits").symlink_to(tmp_path / "e.fits")
    assert read_exposure(tmp_path / "ok.fits").visit == _exposure().visit
    assert gate_read(tmp_path / "ok.fits") == os.path.realpath(tmp_path / "e.fits")


def test_gzip_psf_file_is_not_inflated(tmp_path, psfex_path):
    packed = tmp_path / "bomb.psf"
    packed.write_bytes(gzip.compress(b"\0" * (20 << 20)))
    _refused(read_psf_file, packed, match="not a FITS file")


# -- 3. truncation of cell_coadds files -------------------------------------------------------


@pytest.fixture(scope="module")
def cell_coadds_bytes(tmp_path_factory) -> bytes:
    from coadd_factory import make_patch

    from cellcoadd.io import api

    path = tmp_path_factory.mktemp("rubin") / "patch.fits"
    api.write(make_patch(seed=3), path, layout="cell_coadds")
    return path.read_bytes()


def _hdu_starts(path: Path) -> list[int]:
    with fitsio.FITS(str(path)) as fits:
        return [int(hdu.get_offsets()["header_start"]) for hdu in fits]


@pytest.mark.parametrize("hdu", [2, 3, 4, 5, 6, 7, 8, 9])
def test_cell_coadds_cut_at_an_hdu_boundary_is_refused(tmp_path, cell_coadds_bytes, hdu):
    """Issue 28.3: cut at the start of HDU 5 or 6, the file read as another patch."""
    from cellcoadd.io import api

    whole = tmp_path / "whole.fits"
    whole.write_bytes(cell_coadds_bytes)
    starts = _hdu_starts(whole)
    cut = tmp_path / "cut.fits"
    cut.write_bytes(cell_coadds_bytes[: starts[hdu]])
    error = _refused(api.read, cut, match="CCNHDU")
    assert f"the file has {hdu}" in str(error) and "cut.fits" in str(error)


def test_cell_coadds_random_truncation_is_always_refused(tmp_path, cell_coadds_bytes):
    from cellcoadd.io import api

    rng = np.random.default_rng(28)
    whole = tmp_path / "whole.fits"
    whole.write_bytes(cell_coadds_bytes)
    starts = _hdu_starts(whole)
    offsets = [*rng.integers(1, len(cell_coadds_bytes), 40), *starts[1:]]
    for offset in offsets:
        cut = tmp_path / f"cut{offset}.fits"
        cut.write_bytes(cell_coadds_bytes[:offset])
        _refused(api.read, cut)


# -- 4. and 10. PSF normalisation and conventions ---------------------------------------------


def _tiny_build(psfs):
    """Build the tiny patch from exposures made with ``psfs`` (one per exposure)."""
    import dataclasses

    from coadd_factory import TINY_BUILD, tiny_exposures, tiny_patch

    from cellcoadd import build_patch

    patch = tiny_patch()
    exposures = tiny_exposures(patch, n=len(psfs))
    exposures = [dataclasses.replace(e, psf=p) for e, p in zip(exposures, psfs, strict=True)]
    return build_patch(patch, exposures, TINY_BUILD, seed=1, progress=False)


def test_a_profile_of_flux_half_is_refused_at_construction():
    """Issue 28.4: a GalSim PSF of flux 0.5 moved the coadd PSF by 10% of its peak."""
    from cellcoadd.errors import ExposureError

    with pytest.raises(PsfError, match="flux 0.5"):
        GalSimPsf(galsim.Gaussian(sigma=0.4, flux=0.5))
    with pytest.raises(ExposureError, match="flux 1e-300"):
        import dataclasses

        dataclasses.replace(_exposure(), psf=galsim.Gaussian(sigma=0.4, flux=1e-300))


def test_an_image_psf_summing_to_half_is_refused():
    from cellcoadd.model.psf import ImagePsf

    stamp = galsim.Gaussian(sigma=0.4).drawImage(nx=25, ny=25, scale=0.2).array
    ImagePsf(stamp)  # sums to 1 within 1%
    with pytest.raises(PsfError, match="flux 0.5"):
        ImagePsf(0.5 * stamp / stamp.sum())


def test_a_callable_of_the_wrong_flux_is_rejected_bad_psf():
    """A callable's profiles are checked at each position: the input is rejected, named."""
    good = GalSimPsf(galsim.Moffat(beta=3.5, fwhm=0.8))
    half = GalSimPsf(lambda x, y: galsim.Moffat(beta=3.5, fwhm=0.8, flux=0.5))
    built = _tiny_build([good, half])
    for cell in built.values():
        status = {r.visit: r.status for r in cell.inputs}
        assert status.get(1) in (None, "bad_psf"), status
        assert any(s == "bad_psf" for s in status.values()) or 1 not in status
    assert any(r.status == "bad_psf" for c in built.values() for r in c.inputs)


def test_a_bare_callable_must_state_the_pixel():
    """Issue 28.10: a bare callable returning a PSFEx profile was taken as pre-pixel."""
    import dataclasses

    from cellcoadd.errors import ExposureError

    with pytest.raises(ExposureError, match="include the pixel"):
        dataclasses.replace(_exposure(), psf=lambda x, y: galsim.Gaussian(sigma=0.4))


def test_a_profile_in_pixels_taken_as_arcsec_is_rejected_bad_psf():
    """Issue 28.10: a profile returned in pixel units (5 px FWHM read as 5 arcsec)."""
    good = GalSimPsf(galsim.Moffat(beta=3.5, fwhm=0.8))
    in_pixels = GalSimPsf(lambda x, y: galsim.Moffat(beta=3.5, fwhm=0.8 / 0.2))
    built = _tiny_build([good, in_pixels])
    statuses = [r.status for c in built.values() for r in c.inputs if r.visit == 1]
    assert statuses and all(s == "bad_psf" for s in statuses), statuses


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("PSF_SAMP", 0.0, "PSF_SAMP"),
        ("POLSCAL1", 0.0, "POLSCAL"),
        ("PSFAXIS1", 4, "PSFAXIS3/2/1"),
        ("POLDEG1", 40, "POLDEG1"),
        ("PSF_SAMP", "0.5", "not a number"),
    ],
)
def test_broken_psfex_keywords_are_refused_on_reading(tmp_path, psfex_path, key, value, message):
    """Issue 28.6: PSF_SAMP = 0 or POLSCAL1 = 0 failed the whole patch (ZeroDivisionError)."""
    from astropy.io import fits

    with fits.open(psfex_path) as hdus:
        hdus[1].header[key] = value
        hdus.writeto(tmp_path / "bad.psf")
    error = _refused(read_psfex, tmp_path / "bad.psf", match=message)
    assert "bad.psf" in str(error)


@pytest.mark.parametrize("damage", ["random", "empty", "truncated", "nan", "gzip"])
def test_broken_psfex_files_are_refused_on_reading(tmp_path, psfex_path, damage):
    """Issue 28.6: broken PSF files were read as bytes, then every cell said bad_psf."""
    from astropy.io import fits

    data = psfex_path.read_bytes()
    bad = tmp_path / "bad.psf"
    if damage == "random":
        bad.write_bytes(np.random.default_rng(6).bytes(len(data)))
    elif damage == "empty":
        bad.write_bytes(b"")
    elif damage == "truncated":
        bad.write_bytes(data[: len(data) - 1000])
    elif damage == "gzip":
        bad.write_bytes(gzip.compress(data))
    else:
        with fits.open(psfex_path) as hdus:
            hdus[1].data["PSF_MASK"][0][0, 3, 3] = np.nan
            hdus.writeto(bad)
    _refused(read_psf_file, bad, match="bad.psf")


def test_a_manifest_with_a_broken_psf_fails_before_the_build(tmp_path, lsst_file):
    shutil.copy(lsst_file, tmp_path / "calexp.fits")
    (tmp_path / "calexp.psf").write_bytes(b"SIMPLE  =" + os.urandom(3000))
    (tmp_path / "m.toml").write_text(
        '[[exposures]]\npath = "calexp.fits"\nlayout = "lsst"\npsf = "calexp.psf"\n'
    )
    with pytest.raises(CellCoaddFormatError, match="calexp.psf"):
        sources_from_manifest(read_manifest(tmp_path / "m.toml"), tmp_path)


# -- 5. memory on survey readers ----------------------------------------------------------------


def _forge_cards(data: bytes, values: dict[str, int]) -> bytes:
    """``data`` with every header card ``KEY = ...`` of ``values`` rewritten in place."""
    out = bytearray(data)
    for key, value in values.items():
        start = 0
        prefix = f"{key:<8}= ".encode()
        while (found := out.find(prefix, start)) >= 0:
            if found % 80 == 0:
                out[found : found + 80] = f"{key:<8}= {value:>20}".ljust(80).encode()
            start = found + 80
    return bytes(out)


def _small_compressed_lsst(tmp_path: Path) -> Path:
    """An LSST-shaped tile-compressed file whose planes are one 64 x 64 tile each."""
    from test_survey_readers import LSST_PLANES, _sip_cards

    path = tmp_path / "small.fits.fz"
    wcs = _sip_cards()
    mask_cards = [*wcs, *({"name": f"MP_{k}", "value": v} for k, v in LSST_PLANES.items())]
    primary = [
        {"name": "HIERARCH LSST BUTLER DATAID VISIT", "value": 2025061100123},
        {"name": "HIERARCH LSST BUTLER DATAID DETECTOR", "value": 94},
        {"name": "HIERARCH LSST BUTLER DATAID BAND", "value": "r"},
    ]
    with fitsio.FITS(path, "rw", clobber=True) as fits:
        fits.write(None, header=primary)
        for name, dtype, cards in (
            ("IMAGE", np.float32, wcs),
            ("MASK", np.int32, mask_cards),
            ("VARIANCE", np.float32, wcs),
        ):
            plane = np.ones((64, 64), dtype=dtype)
            fits.write(
                plane,
                extname=name,
                header=cards,
                compress="GZIP_2",
                tile_dims=(64, 64),
                qlevel=None,
            )
    return path


@pytest.mark.parametrize(
    ("size", "message"), [(16000, "more than the"), (4000, "stores")], ids=["huge", "ratio"]
)
def test_declared_planes_are_bounded_before_cfitsio_allocates(tmp_path, size, message):
    """Issue 28.5: a 17 MB .fz declaring 16000 x 16000 planes reached 5.7 GB."""
    import resource

    small = _small_compressed_lsst(tmp_path)
    forged = tmp_path / "forged.fits.fz"
    cards = {"ZNAXIS1": size, "ZNAXIS2": size, "ZTILE1": size, "ZTILE2": size}  # one tile
    forged.write_bytes(_forge_cards(small.read_bytes(), cards))
    psf = GalSimPsf(galsim.Gaussian(sigma=0.4))
    read_lsst_exposure(small, psf, zero_point=30.0)  # the file as written reads
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    error = _refused(read_lsst_exposure, forged, psf, zero_point=30.0, match=message)
    assert "forged.fits.fz" in str(error) and "HDU" in str(error)
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert grown_mb < 200, grown_mb


def test_gzip_stream_named_fz_is_refused_before_cfitsio(tmp_path, lsst_file):
    """Issue 28.5: a 1.5 MB gzip named .fits.fz took 1.74 GB and 85 s (CFITSIO inflated it)."""
    packed = tmp_path / "visit.fits.fz"
    packed.write_bytes(gzip.compress(b"\0" * (64 << 20)))
    psf = GalSimPsf(galsim.Gaussian(sigma=0.4))
    _refused(read_lsst_exposure, packed, psf, match="not a FITS file")


def test_gzip_fits_is_read_within_its_inflation_bound(tmp_path, lsst_file, monkeypatch):
    """A gzip-compressed exposure file is read (CFITSIO inflates it in memory), but only
    after its stream was inflated once, bounded, and found to hold a FITS file."""
    from cellcoadd.io.exposures import mef_file

    packed = tmp_path / "visit.fits.gz"
    packed.write_bytes(gzip.compress(lsst_file.read_bytes()))
    psf = GalSimPsf(galsim.Gaussian(sigma=0.4))
    plain, unpacked = read_lsst_exposure(lsst_file, psf), read_lsst_exposure(packed, psf)
    np.testing.assert_array_equal(plain.image, unpacked.image)
    monkeypatch.setattr(mef_file, "MAX_GZIP_BYTES", lsst_file.stat().st_size // 2)
    _refused(read_lsst_exposure, packed, psf, match="inflates beyond")
    cut = tmp_path / "cut.fits.gz"
    cut.write_bytes(packed.read_bytes()[: packed.stat().st_size // 2])
    _refused(read_lsst_exposure, cut, psf, match="damaged gzip stream")


# -- 7. strict header values --------------------------------------------------------------------


def _with_primary_key(source: Path, target: Path, key: str, value) -> Path:
    shutil.copy(source, target)
    with fitsio.FITS(str(target), "rw") as fits:
        fits[0].write_key(key, value)
    return target


def test_a_zero_point_keyword_that_is_not_a_number_is_refused(tmp_path, lsst_file):
    """Issue 28.7: MAGZERO = '31.2' (a string) was ignored and zero_point= used silently."""
    from cellcoadd.io import LSST_LAYOUT, ZeroPointKey, read_mef_exposure

    psf = GalSimPsf(galsim.Gaussian(sigma=0.4))
    layout = LSST_LAYOUT.model_copy(update={"zero_point_keys": (ZeroPointKey(keyword="MAGZERO"),)})
    path = _with_primary_key(lsst_file, tmp_path / "magzero.fits", "MAGZERO", "31.2")
    error = _refused(read_mef_exposure, path, layout, psf, zero_point=30.0, match="MAGZERO")
    assert "'31.2'" in str(error) and "HDU 0" in str(error)
    path = _with_primary_key(lsst_file, tmp_path / "fluxmag0.fits", "FLUXMAG0", -5.0)
    _refused(read_lsst_exposure, path, psf, zero_point=30.0, match="FLUXMAG0")
    # a number reads; no keyword at all still takes zero_point=
    path = _with_primary_key(lsst_file, tmp_path / "ok.fits", "MAGZERO", 31.2)
    assert read_mef_exposure(path, layout, psf, zero_point=30.0).zero_point == 31.2


def test_an_undefined_high_mask_bit_in_an_int64_mask_is_refused(tmp_path):
    """Issue 28.7: bit 40 of an int64 mask was dropped by the cast to int32."""
    image, mask, variance = lsst_planes()
    wide = mask.astype(np.int64)
    wide[7, 9] |= np.int64(1) << 40
    path = write_lsst(tmp_path / "wide.fits", (image, wide, variance))
    psf = GalSimPsf(galsim.Gaussian(sigma=0.4))
    error = _refused(read_lsst_exposure, path, psf, match="have no name")
    assert "0x10000000000" in str(error) and "MASK" in str(error)
    narrow = write_lsst(tmp_path / "narrow.fits", (image, mask.astype(np.int64), variance))
    np.testing.assert_array_equal(read_lsst_exposure(narrow, psf).mask, mask)


# -- 8. manifests and configurations ----------------------------------------------------------


def _deep(kind: str, depth: int) -> str:
    if kind == "json":
        return '{"exposures": ' + "[" * depth + "]" * depth + "}"
    return "exposures = " + "[" * depth + "]" * depth + "\n"


@pytest.mark.parametrize("kind", ["json", "toml"])
@pytest.mark.parametrize("reader", [read_manifest, read_build_config], ids=["manifest", "config"])
@pytest.mark.parametrize("depth", [100_000, 40])
def test_deep_nesting_is_refused_naming_the_file(tmp_path, kind, reader, depth):
    """Issue 28.8: 100,000-deep nesting raised a RecursionError without the file's name."""
    path = tmp_path / f"deep.{kind}"
    path.write_text(_deep(kind, depth))
    error = _refused(reader, path, match="nested")
    assert f"deep.{kind}" in str(error)


def test_duplicate_keys_are_refused(tmp_path):
    """Issue 28.8: duplicate keys in JSON or CSV manifests: the last silently won."""
    entry = '{"path": "a.fits", "visit": 1, "visit": 2}'
    (tmp_path / "m.json").write_text('{"exposures": [' + entry + "]}")
    _refused(read_manifest, tmp_path / "m.json", match="key visit twice")
    (tmp_path / "t.json").write_text('{"exposures": [], "exposures": [{"path": "a.fits"}]}')
    _refused(read_manifest, tmp_path / "t.json", match="key exposures twice")
    (tmp_path / "c.json").write_text('{"n_noise": 1, "n_noise": 3}')
    _refused(read_build_config, tmp_path / "c.json", match="key n_noise twice")
    (tmp_path / "m.csv").write_text("path,visit,visit\na.fits,1,2\n")
    _refused(read_manifest, tmp_path / "m.csv", match="['visit'] twice")
    (tmp_path / "m.toml").write_text('[[exposures]]\npath = "a.fits"\npath = "b.fits"\n')
    _refused(read_manifest, tmp_path / "m.toml", match="m.toml")


# -- 9. --out never one of the inputs -------------------------------------------------------------


@pytest.mark.parametrize("how", ["same", "relative", "symlink", "hardlink", "manifest"])
def test_build_out_equal_to_an_input_is_refused(tmp_path, monkeypatch, how):
    """Issue 28.9: --out equal to an input exposure replaced it with the coadd, exit 0."""
    from click.testing import CliRunner

    from cellcoadd.cli.build import build as build_command

    monkeypatch.chdir(tmp_path)
    write_exposure(_exposure(), tmp_path / "e.fits")
    before = (tmp_path / "e.fits").read_bytes()
    out = {"same": str(tmp_path / "e.fits"), "relative": "./e.fits", "manifest": "m.toml"}
    if how == "symlink":
        (tmp_path / "link.fits").symlink_to(tmp_path / "e.fits")
    if how == "hardlink":
        os.link(tmp_path / "e.fits", tmp_path / "hard.fits")
    target = out.get(how, {"symlink": "link.fits", "hardlink": "hard.fits"}.get(how))
    args = ["e.fits"]
    if how == "manifest":
        (tmp_path / "m.toml").write_text('[[exposures]]\npath = "e.fits"\n')
        args, target = ["--manifest", "m.toml"], "e.fits"
    result = CliRunner().invoke(
        build_command, [*args, "--tract", "0", "--patch", "0,0", "--out", target, "--overwrite"]
    )
    assert result.exit_code != 0 and "is the input file" in result.output, result.output
    assert (tmp_path / "e.fits").read_bytes() == before


# -- 11. band mismatch --------------------------------------------------------------------------


def test_a_band_mismatch_is_an_input_error_naming_the_exposures():
    """Issue 28.11: a band mismatch was refused as a plain ValueError."""
    import dataclasses

    from coadd_factory import TINY_BUILD, tiny_exposures, tiny_patch

    from cellcoadd import build_patch
    from cellcoadd.errors import InputError

    patch = tiny_patch()
    first, second = tiny_exposures(patch, n=2)
    with pytest.raises(InputError, match="several bands") as info:
        build_patch(patch, [first, dataclasses.replace(second, band="i")], TINY_BUILD)
    assert f"visit={second.visit}" in str(info.value) and "'i'" in str(info.value)


@pytest.mark.parametrize("order", [100_000, 5000, -3, "2"])
def test_a_huge_sip_order_is_refused_before_astropy_allocates(tmp_path, lsst_file, order):
    """Found by the header fuzz: A_ORDER = 100000 made astropy allocate 75 GB."""
    path = tmp_path / "sip.fits"
    shutil.copy(lsst_file, path)
    with fitsio.FITS(str(path), "rw") as fits:
        fits[1].write_key("A_ORDER", order)
    psf = GalSimPsf(galsim.Gaussian(sigma=0.4))
    _refused(read_lsst_exposure, path, psf, match="A_ORDER")


def test_a_trusted_manifest_piff_psf_reads(tmp_path, lsst_file):
    pytest.importorskip("piff")
    from survey_psf_factory import build_piff_model

    build_piff_model(tmp_path / "calexp.piff", nx=LSST_NX, ny=LSST_NY, nstars_side=(3, 3))
    shutil.copy(lsst_file, tmp_path / "calexp.fits")
    entry = '[[exposures]]\npath = "calexp.fits"\nlayout = "lsst"\npsf = "calexp.piff"\n'
    (tmp_path / "m.toml").write_text(entry + "trust_psf = true\n")
    (source,) = sources_from_manifest(read_manifest(tmp_path / "m.toml"), tmp_path)
    assert isinstance(source.psf, PiffPsf)


# Round 4: init, writers, the ledger and run options ------------------------------------------
# `cellcoadd init` and every file a writer creates in place (ledger, lock, index) never
# follow a symbolic link; sky map sizes are bounded before work; a bad ledger row fails
# (or rebuilds) only its patch; a directory in a patch's place fails only that patch.


def _outside(tmp_path: Path, text: str = "precious\n") -> Path:
    """A file outside the folder under test, which nothing may create or change."""
    (tmp_path / "elsewhere").mkdir(exist_ok=True)
    target = tmp_path / "elsewhere" / "precious.txt"
    target.write_text(text)
    return target


def _init(root: Path, *extra: str):
    from click.testing import CliRunner

    from cellcoadd.cli.main import cli

    return _within_deadline(
        CliRunner().invoke, cli, ["init", "--survey", "lsst", str(root), *extra]
    )


@pytest.fixture
def init_dir(tmp_path, lsst_file) -> Path:
    root = tmp_path / "visits"
    root.mkdir()
    shutil.copy(lsst_file, root / "calexp_2024031500123_R22_S11.fits")
    (root / "calexp_2024031500123_R22_S11_psfexcat.psf").write_bytes(b"")
    return root


def test_init_never_writes_through_a_link(tmp_path, init_dir):
    target = tmp_path / "elsewhere" / "created.toml"
    (init_dir / "manifest.toml").symlink_to(target)  # dangling: init once created its target
    for extra in ((), ("--overwrite",)):
        result = _init(init_dir, *extra)
        assert result.exit_code == 1, result.output
        assert "manifest.toml: refused: a symbolic link" in result.output
        assert not target.exists() and not target.parent.exists()
    (init_dir / "manifest.toml").unlink()
    precious = _outside(tmp_path)
    (init_dir / "build.toml").symlink_to(precious)  # with --overwrite it was overwritten
    result = _init(init_dir, "--overwrite")
    assert result.exit_code == 1 and "build.toml: refused: a symbolic link" in result.output
    assert precious.read_text() == "precious\n" and (init_dir / "build.toml").is_symlink()
    assert not (init_dir / "manifest.toml").exists()  # refused before anything is written


def test_init_refuses_a_fifo_without_blocking_and_writes_atomically(init_dir):
    os.mkfifo(init_dir / "manifest.toml")
    result = _init(init_dir, "--overwrite")  # blocked forever before
    assert result.exit_code == 1 and "manifest.toml: refused: a FIFO" in result.output
    os.unlink(init_dir / "manifest.toml")
    (init_dir / "build.toml").mkdir()
    result = _init(init_dir, "--overwrite")
    assert result.exit_code == 1 and "build.toml: refused: a directory" in result.output
    (init_dir / "build.toml").rmdir()
    assert _init(init_dir).exit_code == 0
    first = (init_dir / "manifest.toml").read_bytes()
    inode = (init_dir / "manifest.toml").stat().st_ino
    assert _init(init_dir).exit_code == 1  # exists, no --overwrite
    assert _init(init_dir, "--overwrite").exit_code == 0
    # replaced by a rename (a new inode), same content, no temporary file left
    assert (init_dir / "manifest.toml").stat().st_ino != inode
    assert (init_dir / "manifest.toml").read_bytes() == first
    assert not [p for p in init_dir.iterdir() if ".tmp-" in p.name]


def test_gate_create_and_open_nofollow_never_follow_a_link(tmp_path):
    from cellcoadd.io._files.path_gate import gate_create, open_nofollow

    dangling = tmp_path / "db.sqlite"
    dangling.symlink_to(tmp_path / "elsewhere" / "new.sqlite")
    for call in (gate_create, open_nofollow):
        with pytest.raises(CellCoaddFormatError, match=r"db\.sqlite: refused: a symbolic link"):
            call(dangling, what="index")
    assert not (tmp_path / "elsewhere").exists()
    os.mkfifo(tmp_path / "fifo")
    with pytest.raises(CellCoaddFormatError, match="FIFO"):
        gate_create(tmp_path / "fifo")
    with pytest.raises(CellCoaddFormatError, match="FIFO"):
        _within_deadline(open_nofollow, tmp_path / "fifo")
    (tmp_path / "ok.sqlite-journal").symlink_to(_outside(tmp_path))
    with pytest.raises(CellCoaddFormatError, match=r"ok\.sqlite-journal: refused: a symbolic"):
        gate_create(tmp_path / "ok.sqlite", companions=("-journal",))
    assert gate_create(tmp_path / "new.sqlite") == str(tmp_path / "new.sqlite")
    descriptor = open_nofollow(tmp_path / "new.lock")
    os.close(descriptor)
    assert (tmp_path / "new.lock").is_file()


@pytest.fixture(scope="module")
def survey_dir(tmp_path_factory) -> Path:
    """A small indexed field (one band, 2 x 2 patches), its sky map and configuration,
    and a complete run in ``reference``."""
    from run_factory import BUILD, skymap, write_field

    from cellcoadd.io.exposures.index import ExposureIndex, absolute_entry
    from cellcoadd.model.manifest import ManifestEntry
    from cellcoadd.pipelines.survey import run_tract

    root = tmp_path_factory.mktemp("survey")
    paths = write_field(root / "inputs", n_visits=1, patches_per_tract=2)
    with ExposureIndex(root / "inputs.sqlite") as index:
        index.update([absolute_entry(ManifestEntry(path=str(p)), ".") for p in paths])
    (root / "skymap.json").write_text(skymap(2).to_json())
    (root / "build.json").write_text(BUILD.model_dump_json())
    result = run_tract(
        root / "inputs.sqlite", skymap(2), 0, root / "reference", config=BUILD,
        progress=False, figure=False,
    )  # fmt: skip
    assert len(result.built) == 4 and result.ok
    return root


def _run(root: Path, out: Path, *extra: str, skymap: Path | None = None):
    from click.testing import CliRunner

    from cellcoadd.cli.main import cli

    args = [
        "run", "--index", str(root / "inputs.sqlite"), "--skymap",
        str(skymap or root / "skymap.json"), "--out-dir", str(out), "--config",
        str(root / "build.json"), "-q", "--no-figure", *extra,
    ]  # fmt: skip
    return _within_deadline(CliRunner().invoke, cli, args)


def _said(result) -> str:
    """What a command printed, and the error it ended with."""
    return result.output + ("" if result.exception is None else str(result.exception))


def _sha(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_run_lock_ledger_and_index_never_follow_a_link(tmp_path, survey_dir):
    from cellcoadd.io.exposures.index import ExposureIndex

    precious = _outside(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / ".run.lock").symlink_to(precious)  # its target was truncated to 0 bytes
    result = _run(survey_dir, out)
    assert result.exit_code == 1 and ".run.lock: refused: a symbolic link" in _said(result)
    assert precious.read_text() == "precious\n"
    (out / ".run.lock").unlink()
    (out / "ledger.sqlite").symlink_to(tmp_path / "elsewhere" / "ledger.sqlite")
    result = _run(survey_dir, out)
    assert result.exit_code == 1 and "ledger.sqlite: refused: a symbolic link" in _said(result)
    assert not (tmp_path / "elsewhere" / "ledger.sqlite").exists()
    assert not list(out.glob("*/tract_*/patch_*"))  # refused before any work
    (tmp_path / "db.sqlite").symlink_to(tmp_path / "elsewhere" / "index.sqlite")
    with pytest.raises(CellCoaddFormatError, match="refused: a symbolic link"):
        ExposureIndex(tmp_path / "db.sqlite")
    assert not (tmp_path / "elsewhere" / "index.sqlite").exists()


def test_foreign_sqlite_files_are_refused_unmodified(tmp_path, survey_dir):
    import sqlite3

    from click.testing import CliRunner

    from cellcoadd.cli.main import cli

    foreign = tmp_path / "foreign.sqlite"
    with sqlite3.connect(foreign) as db:
        db.execute("CREATE TABLE notes (text TEXT)")
    db.close()
    ledger = survey_dir / "reference" / "ledger.sqlite"
    exposure = next((survey_dir / "inputs").glob("*.fits"))
    for db_path in (foreign, ledger):
        before = _sha(db_path)
        result = CliRunner().invoke(cli, ["index", str(exposure), "--db", str(db_path)])
        said = _said(result)
        assert result.exit_code != 0 and f"{db_path}: not a" in said, said
        assert "exposure index" in said and "left unmodified" in said
        assert _sha(db_path) == before  # 'ledger.sqlite' was modified, then failed on 'nside'
    # an index named ledger.sqlite in the output folder is not taken as the ledger
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(survey_dir / "inputs.sqlite", out / "ledger.sqlite")
    before = _sha(out / "ledger.sqlite")
    result = _run(survey_dir, out)
    assert result.exit_code == 1 and "not a run ledger" in _said(result), _said(result)
    assert _sha(out / "ledger.sqlite") == before and not list(out.glob("*/tract_*"))


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (("--retries", "-1"), "-1 is not in the range 0<=x<=100"),
        (("--seed", "18446744073709551616"), "is not in the range 0<=x<=9223372036854775807"),
        (("--seed", "-1"), "-1 is not in the range 0<=x<=9223372036854775807"),
    ],
)
def test_run_options_are_click_ranges_checked_before_work(tmp_path, survey_dir, extra, message):
    result = _run(survey_dir, tmp_path / "out", *extra)
    assert result.exit_code == 2 and message in result.output, result.output
    assert not (tmp_path / "out").exists()


def test_an_unknown_band_is_refused_naming_the_bands(tmp_path, survey_dir):
    result = _run(survey_dir, tmp_path / "out", "--band", "nope")  # exited 0, 0 planned
    assert result.exit_code == 1
    assert "band(s) ['nope'] have no usable input" in str(result.exception)
    assert "its bands are ['r']" in str(result.exception)
    assert not list((tmp_path / "out").glob("*/tract_*"))


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        (
            "cells_per_patch",
            10000,
            "cells_per_patch = 10000 cells is outside the allowed range [1, 200]",
        ),
        (
            "pixel_scale",
            1e-9,
            "pixel_scale = 1e-09 arcsec/pixel is outside the allowed range [0.001, 60]",
        ),
        ("cell_inner", 100000, "cell_inner = 100000 pixels is outside the allowed range [1, 4096]"),
        ("pixel_scale", "1e-9", "pixel_scale = 1e-09 arcsec/pixel is outside"),
    ],
)
def test_sky_map_sizes_are_bounded_before_work(tmp_path, survey_dir, field, value, message):
    import re

    from cellcoadd.geometry import SkyMap, SkyMapConfig
    from cellcoadd.geometry.skymap import LSST_SKYMAPS

    spec = json.loads((survey_dir / "skymap.json").read_text())
    spec["config"][field] = value  # MemoryError in the patch; "Polygon has degenerate corner."
    (tmp_path / "bad.json").write_text(json.dumps(spec))
    result = _run(survey_dir, tmp_path / "out", skymap=tmp_path / "bad.json")
    assert result.exit_code == 1 and message in _said(result), _said(result)
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match=re.escape(message)):
        SkyMapConfig(**{field: value})
    # the surveys' own sizes, and a patch the size of a DES tile, are inside the bounds
    for name in LSST_SKYMAPS:
        assert SkyMap.named(name).config.patch_outer <= 3400
    des = SkyMapConfig(pixel_scale=0.263, cell_inner=200, cell_border=50, cells_per_patch=50)
    assert des.patch_inner == 10000
    with pytest.raises(ValueError, match="a patch of 202100 pixels on a side"):
        SkyMapConfig(cells_per_patch=200, cell_inner=1000, cell_border=50)


def _copy_run(survey_dir: Path, tmp_path: Path) -> Path:
    out = tmp_path / "out"
    shutil.copytree(survey_dir / "reference", out)
    return out


def test_a_bad_ledger_row_rebuilds_only_its_patch(tmp_path, survey_dir):
    import sqlite3

    from cellcoadd.pipelines.survey.ledger import Ledger

    out = _copy_run(survey_dir, tmp_path)
    with sqlite3.connect(out / "ledger.sqlite") as db:  # "Expecting value: line 1 column 4"
        db.execute("UPDATE patches SET record = 'r {' WHERE px = 0 AND py = 1")
        record = db.execute("SELECT record FROM patches WHERE px = 1 AND py = 1").fetchone()[0]
        other = record.replace('"px":1,"py":1', '"px":0,"py":0')
        db.execute("UPDATE patches SET record = ? WHERE px = 1 AND py = 1", (other,))
        db.execute(  # a row whose key is not a patch: named, never rebuilt
            "INSERT INTO patches VALUES (?, 0, 'x', 0, 'done', CAST(? AS BLOB), 0)",
            (b"\xff\xfe", b"\x00\xff"),
        )
    db.close()
    with Ledger(out) as ledger:
        records = ledger.records()
        assert {k.patch for k in records} == {(0, 0), (1, 0)}
        said = "\n".join(ledger.unreadable.values())
    assert f"{out / 'ledger.sqlite'}: row " in said
    assert "r tract 0 patch 0,1: its record is not a patch record" in said
    assert "r tract 0 patch 1,1: its record is of r tract 0 patch 0,0" in said
    assert "its key is not a band and three integers" in said
    result = _run(survey_dir, out, "--tract", "0")
    assert result.exit_code == 0, _said(result)
    assert "2 built, 2 up to date, 0 failed" in result.output
    # the run says which row it could not read, with the ledger's path
    assert f"r tract 0 patch 0,1: unreadable ledger row: {out / 'ledger.sqlite'}: row" in (
        result.output
    )
    for name in ("patch_0_1.fits", "patch_1_1.fits"):  # the same bytes as before
        assert _sha(out / "r/tract_0" / name) == _sha(survey_dir / "reference/r/tract_0" / name)
    with Ledger(out) as ledger:
        assert len(ledger.records()) == 4 and len(ledger.unreadable) == 1


def test_verify_with_a_directory_as_a_patch_fails_only_that_patch(tmp_path, survey_dir):
    out = _copy_run(survey_dir, tmp_path)
    patch = out / "r/tract_0/patch_1_1.fits"
    patch.unlink()
    patch.mkdir()
    (patch / "keep").write_text("mine")
    result = _run(survey_dir, out, "--verify")  # aborted the run with [Errno 21]
    assert result.exit_code == 1
    text = str(result.exception)
    assert "1 patch failed" in text and f"{patch}: refused: a directory" in text, text
    assert (patch / "keep").read_text() == "mine"
    report = json.loads((out / "report.json").read_text())
    assert len(report["this_run"]["failed"]) == 1 and report["this_run"]["up_to_date"] == 3


def test_side_files_replace_a_link_never_write_through_it(tmp_path, survey_dir):
    from click.testing import CliRunner

    from cellcoadd.cli.main import cli
    from cellcoadd.plots import style

    precious = _outside(tmp_path)
    out = _copy_run(survey_dir, tmp_path)
    (out / "report.json").unlink()
    (out / "report.json").symlink_to(precious)
    assert _run(survey_dir, out).exit_code == 0
    assert (
        not (out / "report.json").is_symlink() and "this_run" in (out / "report.json").read_text()
    )
    (tmp_path / "schemas").mkdir()
    (tmp_path / "schemas" / "SkyMapConfig.v1.json").symlink_to(precious)
    result = CliRunner().invoke(cli, ["schemas", "--out", str(tmp_path / "schemas")])
    assert result.exit_code == 0, result.output
    assert not (tmp_path / "schemas" / "SkyMapConfig.v1.json").is_symlink()
    (tmp_path / "figure.png").symlink_to(precious)
    style.save(style.figure(2, 2), tmp_path / "figure.png")
    assert (tmp_path / "figure.png").read_bytes().startswith(b"\x89PNG")
    assert precious.read_text() == "precious\n"


# Round 4: the exposure index and `cellcoadd index` ---------------------------------------
# Bounds checked before work (nside, pixels per footprint, the planes a gzip stream or a
# tile-compressed HDU declares); one bad file or row fails only itself (degenerate
# footprints, duplicate identities, undecodable columns); `cellcoadd index` says so.


def _index_entries(paths, **fields):
    from cellcoadd.io.exposures.index import absolute_entry
    from cellcoadd.model.manifest import ManifestEntry

    return [absolute_entry(ManifestEntry(path=str(p), **fields), ".") for p in paths]


def _index_cli(*args: str):
    from click.testing import CliRunner

    from cellcoadd.cli.main import cli

    return _within_deadline(CliRunner().invoke, cli, ["index", *args])


def _index_said(result) -> str:
    """What `cellcoadd index` printed, and the error it ended with."""
    return result.output + ("" if result.exception is None else str(result.exception))


@pytest.fixture(scope="module")
def field_files(tmp_path_factory) -> list[Path]:
    from run_factory import write_field

    return write_field(tmp_path_factory.mktemp("field") / "inputs", n_visits=1)


def test_nside_is_bounded_before_any_file_is_touched(tmp_path, field_files):
    """Issue 39: --nside 67108864 on one exposure: 337 MB of database after 120 s."""
    import sqlite3

    from cellcoadd.errors import CellCoaddRangeError
    from cellcoadd.geometry.footprint import MAX_NSIDE
    from cellcoadd.io.exposures.index import ExposureIndex

    db = tmp_path / "inputs.sqlite"
    result = _index_cli(str(field_files[0]), "--db", str(db), "--nside", "67108864")
    assert result.exit_code == 2 and f"1<=x<={MAX_NSIDE}" in result.output, result.output
    result = _index_cli(str(field_files[0]), "--db", str(db), "--nside", "1000")
    said = _index_said(result)
    assert result.exit_code == 1 and "power of 2 from 1 to 65536" in said, said
    with pytest.raises(CellCoaddRangeError, match="67108864 is not a power of 2 from 1 to"):
        ExposureIndex(db, nside=67108864)
    assert not db.exists()
    # an index file that says so itself is refused on opening
    with ExposureIndex(db) as index:
        index.update(_index_entries(field_files[:1]))
    with sqlite3.connect(db) as raw:
        raw.execute("UPDATE meta SET value = '67108864' WHERE key = 'nside'")
    raw.close()
    for readonly in (True, False):
        with pytest.raises(CellCoaddFormatError, match=r"inputs\.sqlite.*67108864"):
            ExposureIndex(db, readonly=readonly)


def test_a_footprint_over_the_pixel_bound_is_a_bad_file_before_listing(tmp_path, field_files):
    """A footprint tens of degrees wide (a WCS of the wrong scale) would list millions of
    HEALPix pixels: refused from its size alone, the other files indexed."""
    from exposure_factory import make_exposure

    from cellcoadd.errors import GeometryError
    from cellcoadd.geometry.footprint import MAX_FOOTPRINT_PIXELS, healpix_pixels
    from cellcoadd.io.exposures.index import ExposureIndex

    wide = tmp_path / "wide.fits"
    write_exposure(make_exposure((10.0, -30.0), shape=(60, 60), pixel_scale=3000.0), wide)
    with ExposureIndex(tmp_path / "inputs.sqlite") as index:
        update = index.update(_index_entries([field_files[0], wide]))
        assert update.added == [str(field_files[0])]
        ((path, reason),) = update.bad
        assert path == str(wide) and f"more than the {MAX_FOOTPRINT_PIXELS}" in reason, reason
        assert "nside 512" in reason and index.stats()["ok"] == 1
    whole_sky = np.array([[0.0, -80.0], [120.0, -80.0], [240.0, -80.0]])
    with pytest.raises(GeometryError, match="HEALPix pixels at nside 65536"):
        healpix_pixels(65536, whole_sky)  # refused at once: 3e10 pixels not listed


@pytest.mark.parametrize("workers", [1, 2])
def test_a_degenerate_footprint_is_one_bad_file(tmp_path, field_files, workers):
    """Issue 39: an exposure at 1e-7 arcsec/px aborted the whole update with 'Polygon has
    degenerate corner.' and lost the good file of the same update."""
    from exposure_factory import make_exposure

    from cellcoadd.io.exposures.index import ExposureIndex

    tiny = tmp_path / "tiny.fits"
    write_exposure(make_exposure((10.0, -30.0), shape=(50, 50), pixel_scale=1e-7), tiny)
    with ExposureIndex(tmp_path / "inputs.sqlite") as index:
        update = index.update(_index_entries([tiny, *field_files[:2]]), workers=workers)
        assert sorted(update.added) == sorted(map(str, field_files[:2]))
        ((path, reason),) = update.bad
        assert path == str(tiny) and "degenerate footprint" in reason, reason
        assert "the WCS gives 9.99e-08 arcsec/pixel" in reason, reason
        assert index.stats()["ok"] == 2


def _gzip_declaring(path: Path, naxis1: int, naxis2: int, zeros_mb: int) -> Path:
    """A gzip stream of a FITS primary HDU declaring an ``naxis1 x naxis2`` float32 image,
    then ``zeros_mb`` MiB of zeros (a few hundred kB on disk)."""
    cards = [
        "SIMPLE  =                    T", "BITPIX  =                  -32",
        "NAXIS   =                    2", f"NAXIS1  = {naxis1:>20}", f"NAXIS2  = {naxis2:>20}",
        "END",
    ]  # fmt: skip
    with gzip.open(path, "wb", compresslevel=1) as stream:
        stream.write(b"".join(f"{card:<80}".encode() for card in cards).ljust(2880))
        for _ in range(zeros_mb):
            stream.write(bytes(1 << 20))
    return path


def test_a_gzip_stream_declaring_a_huge_plane_is_refused_from_its_header(
    tmp_path, psfex_path, lsst_file
):
    """Issue 39: a 1.6 MB gzip .fits.fz declaring 20000 x 20000 cost 1.5 GB and 20 s per
    describing process before the refusal: the header is checked as it leaves the stream,
    before the rest is inflated (by us, or by CFITSIO into memory)."""
    import resource

    from cellcoadd.io.exposures.index import ExposureIndex

    forged = _gzip_declaring(tmp_path / "visit.fits.fz", 20000, 20000, zeros_mb=256)
    assert forged.stat().st_size < 2 << 20
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    psf = GalSimPsf(galsim.Gaussian(sigma=0.4))
    error = _refused(read_lsst_exposure, forged, psf, zero_point=30.0, match="20000 x 20000")
    assert "visit.fits.fz" in str(error) and "HDU 0" in str(error)
    assert "(400000000 pixels), more than the 67108864 accepted" in str(error)
    # behind the 5 HDUs of a real file too: each header is read where the last data ends
    cards = [
        "XTENSION= 'IMAGE   '", "BITPIX  =                  -32",
        "NAXIS   =                    2", "NAXIS1  =                20000",
        "NAXIS2  =                20000", "PCOUNT  =                    0",
        "GCOUNT  =                    1", "END",
    ]  # fmt: skip
    extension = b"".join(f"{card:<80}".encode() for card in cards).ljust(2880)
    appended = tmp_path / "appended.fits.gz"
    appended.write_bytes(gzip.compress(lsst_file.read_bytes() + extension + bytes(1 << 20)))
    _refused(read_lsst_exposure, appended, psf, zero_point=30.0, match="HDU 5 declares a 20000")
    good = tmp_path / "good.fits"
    shutil.copy(lsst_file, good)
    with ExposureIndex(tmp_path / "inputs.sqlite") as index:
        entries = _index_entries([forged, good], layout="lsst", psf=str(psfex_path))
        update = index.update([e.model_copy(update={"zero_point": 30.0}) for e in entries])
        assert update.added == [str(good)]
        ((path, reason),) = update.bad
        assert path == str(forged) and "declares a 20000 x 20000 image" in reason, reason
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert grown_mb < 128, grown_mb  # inflating the stream whole: > 256 MB


def test_a_tile_compressed_plane_over_the_bound_is_refused_in_cellcoadd_files(
    tmp_path, field_files
):
    """The same bound for cellcoadd's own exposure files: a tile-compressed IMAGE
    declaring 20000 x 20000 (1000:1 of zeros passes the ratio check) is refused from its
    header, by the reader and by the index (where only headers are read)."""
    from cellcoadd.io.exposures.index import ExposureIndex

    small = tmp_path / "small.fits.fz"
    with fitsio.FITS(str(field_files[0])) as source, fitsio.FITS(str(small), "rw") as out:
        for hdu in source:
            name = hdu.get_extname()
            data, header = hdu.read(), hdu.read_header()
            if name == "IMAGE":
                plane = np.zeros((64, 64), dtype=np.float32)
                out.write(plane, extname=name, compress="GZIP_2", tile_dims=(64, 64), qlevel=None)
            elif hdu.get_exttype() == "IMAGE_HDU":
                out.write(data, header=header, extname=name or None)
            else:
                out.write(data, header=header, extname=name)
    forged = tmp_path / "forged.fits.fz"
    sizes = {"ZNAXIS1": 20000, "ZNAXIS2": 20000, "ZTILE1": 20000, "ZTILE2": 20000}
    forged.write_bytes(_forge_cards(small.read_bytes(), sizes))
    error = _refused(read_exposure, forged, match="declares a 20000 x 20000 image")
    assert "forged.fits.fz" in str(error) and "HDU IMAGE" in str(error)
    with ExposureIndex(tmp_path / "inputs.sqlite") as index:
        ((path, reason),) = index.update(_index_entries([forged])).bad
    assert path == str(forged) and "HDU IMAGE declares a 20000 x 20000 image" in reason, reason


def _forge_row(db: Path, path: str, **columns) -> int:
    """Set ``columns`` of the row of ``path`` and recompute its checksum (and header
    SHA-256) so that they agree: a row damaged consistently. Returns the row id."""
    import sqlite3

    from cellcoadd.io._files.stamps import json_sha256
    from cellcoadd.io.exposures.index import CHECKED_FIELDS, row_checksum

    with sqlite3.connect(db) as raw:
        raw.row_factory = sqlite3.Row
        for name, value in columns.items():
            raw.execute(f"UPDATE exposures SET {name} = ? WHERE path = ?", (value, path))
            if name == "header":
                sha = json_sha256(value)
                raw.execute("UPDATE exposures SET header_sha256 = ? WHERE path = ?", (sha, path))
        row = raw.execute("SELECT * FROM exposures WHERE path = ?", (path,)).fetchone()
        values = {name: row[name] for name in CHECKED_FIELDS}
        raw.execute(
            "UPDATE exposures SET checksum = ? WHERE id = ?", (row_checksum(values), row["id"])
        )
    raw.close()
    return int(row["id"])


@pytest.mark.parametrize("column", ["corners", "files", "entry", "header"])
def test_non_json_in_an_index_row_fails_only_that_row_naming_it(tmp_path, field_files, column):
    """Issue 39: non-JSON in an index row gave 'Expecting value: line 1 column 4', naming
    no file or row. Even with its checksum made to agree, the row's error names the index,
    the row, the file and the column; the other rows read."""
    from run_factory import skymap

    from cellcoadd.errors import IndexRowError
    from cellcoadd.io.exposures.index import ExposureIndex

    db = tmp_path / "inputs.sqlite"
    with ExposureIndex(db) as index:
        index.update(_index_entries(field_files))
    damaged = str(field_files[0])
    row_id = _forge_row(db, damaged, **{column: '{"a": 1'})
    tract = skymap()[0]
    corners = np.column_stack(tract.pixel_to_sky(*_tract_box_corners(tract)))
    with ExposureIndex(db, readonly=True) as index:
        rows = index.query(corners)
        assert len(rows) == len(field_files)
        full = index.by_ids([row.id for row in rows])
    for row in full:
        attempts = [
            lambda row=row: row.corners,
            lambda row=row: row.files,
            lambda row=row: row.entry,
            row.header,
        ]
        if row.path != damaged:
            for attempt in attempts:
                attempt()
            continue
        with pytest.raises(IndexRowError) as info:
            for attempt in attempts:
                attempt()
        message = str(info.value)
        assert info.value.row == row_id and info.value.fields == (column,)
        assert f"row {row_id}" in message and str(db) in message and damaged in message
        assert f"its {column} column is unusable" in message, message
    # indexing again reads the file again (a column that must decode to say whether the
    # file changed: always; a consistent checksum hides the others but from --checksum)
    with ExposureIndex(db) as index:
        deep = column in ("corners", "header")
        update = index.update(_index_entries(field_files), checksum=deep)
        assert damaged in update.updated and not update.bad
        assert deep or update.updated == [damaged]
        for row in index.by_ids([row.id for row in index.query(corners)]):
            assert row.header().visit == 0 and row.corners.shape == (4, 2) and row.entry


def _tract_box_corners(tract):
    box = tract.bbox
    x = np.array([box.x_start, box.x_stop, box.x_stop, box.x_start]) - 0.5
    y = np.array([box.y_start, box.y_start, box.y_stop, box.y_stop]) - 0.5
    return x, y


def test_a_forged_header_row_fails_only_the_patches_using_it(tmp_path, field_files):
    """Issue 39: non-JSON in an index row aborted the whole run. With the row's checksum
    made to agree, the patches using it fail naming the row; the others are built."""
    from run_factory import BUILD, skymap

    from cellcoadd.io.exposures.index import ExposureIndex
    from cellcoadd.pipelines.survey import run_tract

    db = tmp_path / "inputs.sqlite"
    with ExposureIndex(db) as index:
        index.update(_index_entries(field_files))
    row_id = _forge_row(db, str(field_files[0]), header="[1, 2")  # detector 0, patch (0, 0)
    result = _within_deadline(
        run_tract, db, skymap(), 0, tmp_path / "out", config=BUILD, progress=False,
        figure=False, retries=0,
    )  # fmt: skip
    assert result.failed and result.built and not result.plan_failed
    for key, why in result.failed.items():
        assert f"row {row_id}" in why and "header column" in why, why
        assert max(key.px, key.py) <= 1, key  # only patches detector 0 touches
    assert len(result.failed) + len(result.built) == len(result.planned)


def test_a_second_file_of_one_visit_and_detector_is_refused(tmp_path, field_files):
    """Issue 39: the index accepted two files of the same (visit, detector), and the run
    then retried each patch using them in vain."""
    from cellcoadd.io.exposures.index import ExposureIndex

    copy = tmp_path / "copy-of-det0.fits"
    shutil.copy(field_files[0], copy)
    db = tmp_path / "inputs.sqlite"
    with ExposureIndex(db) as index:
        first = index.update(_index_entries([field_files[0], copy, field_files[1]]))
        assert first.added == [str(field_files[0]), str(field_files[1])]
        ((path, reason),) = first.bad
        assert path == str(copy) and "(visit=0, detector=0)" in reason, reason
        assert f"already indexed from {field_files[0]}" in reason
        again = index.update(_index_entries([copy]))  # in a later update too
        assert [p for p, _ in again.bad] == [str(copy)]
        assert index.stats()["ok"] == 2
    result = _index_cli(str(copy), "--db", str(db), "-q")
    assert result.exit_code == 1 and str(field_files[0]) in result.output, result.output


def test_index_command_exits_non_zero_on_bad_files_and_lists_them_when_quiet(tmp_path, field_files):
    """Issue 39: `cellcoadd index` exited 0 when every file was bad, and -q hid the list."""
    db = str(tmp_path / "inputs.sqlite")
    bad = []
    for name in ("empty.fits", "text.fits"):
        bad.append(tmp_path / name)
        bad[-1].write_bytes(b"" if name == "empty.fits" else b"not FITS\n" * 400)
    result = _index_cli(*map(str, bad), "--db", db, "-q")
    assert result.exit_code == 1, result.output
    lines = [line for line in result.output.splitlines() if line.startswith("bad: ")]
    assert len(lines) == 2 and all(any(str(p) in line for line in lines) for p in bad), lines
    assert "2 files are bad" in _index_said(result)
    result = _index_cli(str(field_files[0]), *map(str, bad), "--db", db, "-q", "--allow-bad")
    assert result.exit_code == 0 and "1 added" in result.output, result.output
    assert sum(line.startswith("bad: ") for line in result.output.splitlines()) == 2
    result = _index_cli(str(field_files[0]), "--db", db)  # only good files: success
    assert result.exit_code == 0 and "1 unchanged" in result.output, result.output
    help_text = _index_cli("--help").output
    assert "exits with status 1" in help_text and "--allow-bad" in help_text


def test_a_missing_zero_point_names_the_manifest_field(tmp_path, psfex_path):
    """Issue 43.4: the index's error said 'pass zero_point=', a Python keyword, to a user
    who writes manifest.toml."""
    from cellcoadd.io.exposures.index import ExposureIndex

    small = _small_compressed_lsst(tmp_path)  # no FLUXMAG0, no BUNIT
    with ExposureIndex(tmp_path / "inputs.sqlite") as index:
        entries = _index_entries([small], layout="lsst", psf=str(psfex_path))
        ((path, reason),) = index.update(entries).bad
    assert path == str(small) and "no zero point" in reason, reason
    assert "set `zero_point = ...` in the file's manifest entry (manifest.toml)" in reason
    assert "pass zero_point=" not in reason
