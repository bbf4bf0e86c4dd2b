"""Exposure files: lossless round trips, atomic writes and corruption detection."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys

import fitsio
import galsim
import galsim.des
import numpy as np
import pytest
from astropy.wcs import WCS, Sip
from survey_psf_factory import build_piff_model, write_psfex_file

from cellcoadd.errors import CellCoaddFormatError, PsfCodecError
from cellcoadd.geometry.box import Box
from cellcoadd.io import read_piff, read_psfex
from cellcoadd.io.exposures.exposure_io import read_exposure, write_exposure
from cellcoadd.io.exposures.psf_codec import decode_psf, encode_psf
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.psf import CallablePsf, GalSimPsf, ImagePsf, PiffPsf, PsfexPsf
from cellcoadd.model.psf_profiles import GridPsf, VaryingPsf

SHAPE = (60, 80)


def sip_wcs() -> WCS:
    """A rotated TAN-SIP WCS with awkward full-precision values."""
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"]
    wcs.wcs.crval = [359.123456789012345, -30.987654321098765]
    wcs.wcs.crpix = [-212.3456789123457, 611.9876543210987]
    theta = 0.3
    scale = 0.27 / 3600.0 * (1.0 + 1.234567891e-3)
    wcs.wcs.cd = scale * np.array([[-np.cos(theta), np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    a = np.zeros((4, 4))
    b = np.zeros((4, 4))
    a[3, 0] = a[1, 2] = b[2, 1] = b[0, 3] = 1.234567890123e-9
    a[2, 0] = 3.3333333333333e-7
    wcs.sip = Sip(a, b, None, None, wcs.wcs.crpix)
    wcs.wcs.set()
    return wcs


def make_exposure(psf, *, variance_array: bool = False, dtype=np.float32) -> Exposure:
    rng = np.random.default_rng(3)
    image = rng.normal(size=SHAPE).astype(dtype)
    image[0, 0] = -0.0
    image[5, 7] = np.nan
    bits = MaskBits(bits={**MaskBits().bits, "Extra_Bit": 12})
    mask = np.zeros(SHAPE, dtype=np.int32)
    mask[5, 7] = bits.value("BAD")
    mask[10:12, :] = bits.value("Extra_Bit") | bits.value("CR")
    variance = rng.uniform(80, 90, SHAPE) if variance_array else 81.12345678901234
    return Exposure(
        image=image,
        wcs=sip_wcs(),
        variance=variance,
        psf=psf,
        visit=123456,
        detector=42,
        band="y\u00b2 ",
        zero_point=30.123456789012345,
        mask=mask,
        mask_bits=bits,
        valid_box=Box(x_start=2, x_stop=77, y_start=3, y_stop=58),
    )


def varying_psf() -> VaryingPsf:
    base = galsim.Moffat(beta=3.5, fwhm=0.93).shear(g1=0.011, g2=-0.02)
    return VaryingPsf(
        base=base,
        x0=-150.5,
        y0=900.25,
        radius=877.0,
        dilation=((2, 0, 0.0487), (0, 2, 0.0487)),
        g1=((2, 0, 0.01), (0, 2, -0.01)),
        g2=((1, 1, 0.02),),
    )


def bits_of(array: np.ndarray) -> np.ndarray:
    """The raw bits, with every NaN mapped to one value (cfitsio canonicalises NaNs)."""
    bits = array.view(f"u{array.dtype.itemsize}").copy()
    bits[np.isnan(array)] = 0
    return bits


def draw(profile: galsim.GSObject) -> np.ndarray:
    return profile.drawImage(nx=25, ny=25, scale=0.27, method="auto").array


def assert_same_exposure(a: Exposure, b: Exposure) -> None:
    assert a.image.dtype == b.image.dtype
    np.testing.assert_array_equal(bits_of(a.image), bits_of(b.image))
    np.testing.assert_array_equal(a.mask, b.mask)
    assert b.mask.dtype == np.int32
    if isinstance(a.variance, float):
        assert b.variance == a.variance and isinstance(b.variance, float)
    else:
        np.testing.assert_array_equal(bits_of(a.variance), bits_of(b.variance))
    assert (a.visit, a.detector, a.band, a.zero_point) == (
        b.visit,
        b.detector,
        b.band,
        b.zero_point,
    )
    assert a.valid_box == b.valid_box
    assert a.mask_bits == b.mask_bits
    # the WCS maps identically, SIP included, both ways
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-300, 400, (2, 2000))
    ra_a, dec_a = a.wcs.all_pix2world(x, y, 0)
    ra_b, dec_b = b.wcs.all_pix2world(x, y, 0)
    scale = 0.27 / 3600.0
    assert np.max(np.abs(ra_a - ra_b) * np.cos(np.radians(dec_a))) / scale < 1e-9
    assert np.max(np.abs(dec_a - dec_b)) / scale < 1e-9
    xb, yb = b.wcs.all_world2pix(ra_a, dec_a, 0, tolerance=1e-12)
    xa, ya = a.wcs.all_world2pix(ra_a, dec_a, 0, tolerance=1e-12)
    assert np.max(np.abs(xa - xb)) < 1e-9 and np.max(np.abs(ya - yb)) < 1e-9
    assert b.wcs.sip is not None


@pytest.mark.parametrize("variance_array", [False, True])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_round_trip_profile_psf(tmp_path, variance_array, dtype):
    psf = galsim.Moffat(beta=3.5, fwhm=0.95).shear(g1=0.003, g2=0.01).shift(0.01, -0.02)
    exposure = make_exposure(psf, variance_array=variance_array, dtype=dtype)
    path = write_exposure(exposure, tmp_path / "e.fits")
    back = read_exposure(path)
    assert_same_exposure(exposure, back)
    assert back.psf == psf
    np.testing.assert_array_equal(draw(back.psf), draw(psf))
    assert os.listdir(tmp_path) == ["e.fits"]  # no temporary file left behind


@pytest.mark.parametrize(
    "psf",
    [
        galsim.Gaussian(sigma=0.4, gsparams=galsim.GSParams(folding_threshold=1e-3)),
        galsim.Kolmogorov(fwhm=0.7).shear(e1=0.05, e2=0.0).dilate(1.07),
        galsim.Convolve(galsim.Kolmogorov(fwhm=0.6), galsim.Airy(lam_over_diam=0.1)),
        galsim.Add(
            galsim.Gaussian(sigma=0.4, flux=0.7), galsim.Exponential(scale_radius=0.3, flux=0.3)
        ),
    ],
)
def test_round_trip_other_profiles(tmp_path, psf):
    back = read_exposure(write_exposure(make_exposure(psf), tmp_path / "e.fits"))
    assert back.psf == psf
    np.testing.assert_array_equal(draw(back.psf), draw(psf))


def test_round_trip_varying_psf_is_exact(tmp_path):
    psf = varying_psf()
    back = read_exposure(write_exposure(make_exposure(psf), tmp_path / "e.fits"))
    assert isinstance(back.psf, VaryingPsf) and back.psf == psf
    for x, y in [(0.0, 0.0), (40.3, 17.9), (79.0, 59.0)]:
        np.testing.assert_array_equal(draw(back.psf(x, y)), draw(psf(x, y)))


def test_callable_psf_becomes_an_accurate_grid(tmp_path):
    psf = varying_psf()

    def as_plain_function(x: float, y: float) -> galsim.GSObject:
        return psf(x, y)

    exposure = make_exposure(GalSimPsf(as_plain_function))
    back = read_exposure(write_exposure(exposure, tmp_path / "e.fits"))
    assert isinstance(back.psf, GridPsf) and callable(back.psf)
    for x, y in [(0.0, 0.0), (40.0, 29.5), (79.0, 59.0), (13.7, 44.1)]:
        truth, grid = draw(psf(x, y)), draw(back.psf(x, y))
        assert np.max(np.abs(grid - truth)) < 2e-3 * truth.max()
        assert abs(grid.sum() - truth.sum()) < 5e-3
    # a grid read back is written again unchanged
    again = read_exposure(write_exposure(back, tmp_path / "f.fits"))
    np.testing.assert_array_equal(again.psf.stamps, back.psf.stamps)
    np.testing.assert_array_equal(again.psf.x_nodes, back.psf.x_nodes)


def test_image_psf_round_trip(tmp_path):
    stamp = galsim.Moffat(beta=3.5, fwhm=0.9).drawImage(nx=25, ny=25, scale=0.27)
    back = read_exposure(write_exposure(make_exposure(stamp), tmp_path / "e.fits"))
    assert isinstance(back.psf, galsim.Image)
    np.testing.assert_array_equal(bits_of(back.psf.array), bits_of(stamp.array))
    assert back.psf.scale == stamp.scale


def test_unlisted_profile_is_sampled(tmp_path):
    moffat = galsim.Moffat(beta=3.5, fwhm=0.9)
    stamp = moffat.drawImage(nx=65, ny=65, scale=0.05, method="no_pixel")
    psf = galsim.InterpolatedImage(stamp, flux=1.0)  # a PSF has unit flux
    back = read_exposure(write_exposure(make_exposure(psf), tmp_path / "e.fits"))
    assert isinstance(back.psf, galsim.GSObject)
    assert np.max(np.abs(draw(back.psf) - draw(psf))) < 2e-3 * draw(psf).max()


def test_codec_refuses_unlisted_types_and_fields():
    with pytest.raises(PsfCodecError):
        decode_psf({"type": "__import__", "name": "os"})
    with pytest.raises(PsfCodecError):
        decode_psf({"type": "Gaussian", "sigma": 0.4, "flux": 1.0, "extra": "os.system"})
    with pytest.raises(PsfCodecError):
        decode_psf({"type": "Gaussian", "sigma": "0.4", "flux": 1.0})
    with pytest.raises(PsfCodecError):
        decode_psf({"type": "Gaussian", "sigma": float("nan"), "flux": 1.0})
    with pytest.raises(PsfCodecError):
        encode_psf(galsim.InterpolatedImage(galsim.Image(np.ones((5, 5)), scale=0.2)))


def test_refuses_to_overwrite(tmp_path):
    exposure = make_exposure(galsim.Gaussian(sigma=0.4))
    path = write_exposure(exposure, tmp_path / "e.fits")
    before = path.read_bytes()
    with pytest.raises(FileExistsError):
        write_exposure(make_exposure(galsim.Gaussian(sigma=0.5)), path)
    assert path.read_bytes() == before
    write_exposure(make_exposure(galsim.Gaussian(sigma=0.5)), path, overwrite=True)
    assert read_exposure(path).psf == galsim.Gaussian(sigma=0.5)


def test_failed_write_leaves_previous_file_intact(tmp_path, monkeypatch):
    path = write_exposure(make_exposure(galsim.Gaussian(sigma=0.4)), tmp_path / "e.fits")
    before = path.read_bytes()
    original = fitsio.FITS.write
    calls = []

    def failing_write(self, data, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise OSError("disk full")
        return original(self, data, *args, **kwargs)

    monkeypatch.setattr(fitsio.FITS, "write", failing_write)
    with pytest.raises(OSError, match="disk full"):
        write_exposure(make_exposure(galsim.Gaussian(sigma=0.5)), path, overwrite=True)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["e.fits"]


# -- malformed files -------------------------------------------------------------------
@pytest.fixture(scope="module")
def good_file(tmp_path_factory):
    directory = tmp_path_factory.mktemp("good")
    return write_exposure(make_exposure(varying_psf(), variance_array=True), directory / "e.fits")


def expect_format_error(path) -> CellCoaddFormatError:
    with pytest.raises(CellCoaddFormatError) as info:
        read_exposure(path)
    assert info.value.path == os.fspath(path)
    return info.value


def test_not_fits_empty_and_missing(tmp_path):
    text = tmp_path / "notes.fits"
    text.write_text("SIMPLE = not really a FITS file\n" * 100)
    expect_format_error(text)
    empty = tmp_path / "empty.fits"
    empty.write_bytes(b"")
    expect_format_error(empty)
    expect_format_error(tmp_path / "absent.fits")


def test_truncated_files(good_file, tmp_path):
    data = good_file.read_bytes()
    rng = np.random.default_rng(5)
    offsets = [2880, len(data) - 2880, len(data) - 1, *rng.integers(1, len(data), 12)]
    for offset in offsets:
        path = tmp_path / f"cut{offset}.fits"
        path.write_bytes(data[:offset])
        expect_format_error(path)


def test_flipped_bytes_are_caught(good_file, tmp_path):
    data = bytearray(good_file.read_bytes())
    rng = np.random.default_rng(11)
    path = tmp_path / "flipped.fits"
    for offset in rng.integers(0, len(data), 60):
        corrupted = bytearray(data)
        corrupted[offset] ^= 1 << int(rng.integers(0, 8))
        path.write_bytes(bytes(corrupted))
        expect_format_error(path)


def rewrite_without(source, target, drop: str | None = None, edit=None) -> None:
    """Copy an exposure file HDU by HDU, optionally dropping one or editing headers.

    The copy has fresh CHECKSUM/DATASUM cards and no DATACRC (like files written before
    it existed), so only the edit itself can make it unreadable."""
    with fitsio.FITS(os.fspath(source)) as src, fitsio.FITS(os.fspath(target), "rw") as dst:
        for hdu in src:
            name = hdu.get_extname()
            if name == drop:
                continue
            header = [
                r
                for r in hdu.read_header().records()
                if r["name"] not in ("CHECKSUM", "DATASUM", "DATACRC")
            ]
            data = hdu.read()
            if edit is not None:
                data, header = edit(name, data, header)
            dst.write(data, header=header, extname=name)
            dst[-1].write_checksum()


@pytest.mark.parametrize("hdu", ["MASK", "META", "VARIANCE"])
def test_missing_hdu(good_file, tmp_path, hdu):
    target = tmp_path / "missing.fits"
    rewrite_without(good_file, target, drop=hdu)
    assert hdu in expect_format_error(target).problem


def test_keyword_disagreeing_with_metadata(good_file, tmp_path):
    def bump_visit(name, data, header):
        if name == "IMAGE":
            header = [dict(r, value=7) if r["name"] == "VISIT" else r for r in header]
        return data, header

    target = tmp_path / "visit.fits"
    rewrite_without(good_file, target, edit=bump_visit)
    assert "VISIT" in expect_format_error(target).problem


def test_unknown_major_version_and_bad_metadata(good_file, tmp_path):
    def edit_meta(change):
        def edit(name, data, header):
            if name == "META":
                meta = json.loads(data.tobytes())
                change(meta)
                data = np.frombuffer(json.dumps(meta).encode(), np.uint8)
            return data, header

        return edit

    cases = {
        "version": lambda m: m.update(format_version="2.0"),
        "psf": lambda m: m["psf"]["profile"].update(type="exec"),
        "box": lambda m: m.update(valid_box=[0, 1]),
        "band": lambda m: m.update(band=3),
    }
    for label, change in cases.items():
        target = tmp_path / f"{label}.fits"
        rewrite_without(good_file, target, edit=edit_meta(change))
        expect_format_error(target)
    # a minor version bump still reads
    target = tmp_path / "minor.fits"
    rewrite_without(good_file, target, edit=edit_meta(lambda m: m.update(format_version="1.7")))
    assert read_exposure(target).visit == 123456


def test_missing_checksums_are_refused(good_file, tmp_path):
    target = tmp_path / "nochecksum.fits"
    shutil.copy(good_file, target)
    with fitsio.FITS(os.fspath(target), "rw") as fits_file:
        fits_file["MASK"].delete_key("CHECKSUM")
        fits_file["MASK"].delete_key("DATASUM")
    assert "checksum" in expect_format_error(target).problem


# -- PSF models (cellcoadd.model.psf): every kind is stored -------------------------------
def _model_box(x: float, y: float, half: int = 12) -> Box:
    ix, iy = round(x), round(y)
    return Box(x_start=ix - half, x_stop=ix + half + 1, y_start=iy - half, y_stop=iy + half + 1)


PSF_POSITIONS = [(0.0, 0.0), (39.5, 29.5), (79.0, 59.0), (13.7, 44.1), (40.3, 17.9)]


def psf_meta(path) -> tuple[str, dict]:
    """PSFKIND keyword and META psf description of an exposure file."""
    with fitsio.FITS(os.fspath(path)) as fits_file:
        kind = fits_file["IMAGE"].read_header()["PSFKIND"]
        meta = json.loads(fits_file["META"].read().tobytes())
    return kind, meta["psf"]


@pytest.fixture(scope="module")
def small_psfex(tmp_path_factory):
    """A PSFEx file whose FWHM varies by 20% over the 80 x 60 test exposure."""
    directory = tmp_path_factory.mktemp("psfex")
    return write_psfex_file(
        directory / "ccd12.psf", nx=SHAPE[1], ny=SHAPE[0], fwhm_range=(0.8, 1.0), pixel_scale=0.27
    ).path


def test_psfex_model_is_stored_whole(tmp_path, small_psfex):
    model = read_psfex(small_psfex)
    exposure = make_exposure(model)
    path = write_exposure(exposure, tmp_path / "e.fits")
    kind, desc = psf_meta(path)
    assert kind == "PSFEX"
    assert desc["sha256"] == hashlib.sha256(small_psfex.read_bytes()).hexdigest()
    assert desc["file_name"] == "ccd12.psf"
    back = read_exposure(path)
    assert_same_exposure(exposure, back)
    assert isinstance(back.psf, PsfexPsf) and back.psf == model
    assert back.psf.data == small_psfex.read_bytes() and back.psf.source == "ccd12.psf"
    for x, y in PSF_POSITIONS:
        box = _model_box(x, y)
        np.testing.assert_array_equal(back.draw_psf(x, y, box), exposure.draw_psf(x, y, box))
    # written again, the file is the same
    again = write_exposure(back, tmp_path / "f.fits")
    assert again.read_bytes() == path.read_bytes()


def test_tampered_psfex_copy_is_refused(tmp_path, small_psfex):
    path = write_exposure(make_exposure(read_psfex(small_psfex)), tmp_path / "e.fits")

    def tamper(name, data, header):
        if name == "PSF":
            data = data.copy()
            data[len(data) // 2] ^= 4
        return data, header

    target = tmp_path / "tampered.fits"
    rewrite_without(path, target, edit=tamper)  # fresh checksums: only the SHA-256 can tell
    problem = expect_format_error(target).problem
    assert "HDU PSF" in problem and "ccd12.psf" in problem and "SHA-256" in problem


@pytest.fixture(scope="module")
def small_piff(tmp_path_factory):
    directory = tmp_path_factory.mktemp("piff")
    return build_piff_model(
        directory / "ccd7.piff",
        nx=SHAPE[1],
        ny=SHAPE[0],
        pixel_scale=0.27,
        fwhm_range=(0.8, 1.0),
        nstars_side=(3, 3),
        chipnum=7,
    ).path


def test_piff_model_is_stored_whole(tmp_path, small_piff):
    model = read_piff(small_piff, trusted=True, chipnum=7, origin=0)
    exposure = make_exposure(model)
    path = write_exposure(exposure, tmp_path / "e.fits")
    kind, desc = psf_meta(path)
    assert kind == "PIFF"
    assert (desc["chipnum"], desc["origin"], desc["file_name"]) == (7, 0, "ccd7.piff")
    back = read_exposure(path, trust_psf=True)
    assert isinstance(back.psf, PiffPsf) and back.psf == model
    assert (back.psf.chipnum, back.psf.origin) == (7, 0)
    assert back.psf.data == small_piff.read_bytes()
    for x, y in PSF_POSITIONS:
        box = _model_box(x, y)
        np.testing.assert_array_equal(back.draw_psf(x, y, box), exposure.draw_psf(x, y, box))


def test_piff_exposure_needs_trust_and_piff(tmp_path, small_piff, monkeypatch):
    """A stored Piff model (pickled objects) is loaded only when the reader trusts the
    file, and then needs Piff: both refusals name the file, before any build."""
    path = write_exposure(make_exposure(read_piff(small_piff, trusted=True)), tmp_path / "e.fits")
    with pytest.raises(CellCoaddFormatError, match="pickled") as info:
        read_exposure(path)
    assert "e.fits" in str(info.value) and "ccd7.piff" in str(info.value)
    assert isinstance(read_exposure(path, trust_psf=True).psf, PiffPsf)
    monkeypatch.setitem(sys.modules, "piff", None)  # import piff -> ImportError
    with pytest.raises(CellCoaddFormatError, match=r"cellcoadd\[piff\]"):
        read_exposure(path, trust_psf=True)


def _unlisted_profile() -> galsim.GSObject:
    moffat = galsim.Moffat(beta=3.5, fwhm=0.9)
    stamp = moffat.drawImage(nx=65, ny=65, scale=0.05, method="no_pixel")
    return galsim.InterpolatedImage(stamp, flux=1.0)


def _plain_function(x: float, y: float) -> galsim.GSObject:
    return varying_psf()(x, y)


@pytest.mark.parametrize(
    ("bare", "wrapped"),
    [
        (galsim.Gaussian(sigma=0.4), GalSimPsf(galsim.Gaussian(sigma=0.4))),
        (_unlisted_profile(), GalSimPsf(_unlisted_profile())),
        (varying_psf(), GalSimPsf(varying_psf())),
        (GalSimPsf(_plain_function), CallablePsf(_plain_function, includes_pixel=False)),
        (varying_psf(), CallablePsf(varying_psf(), includes_pixel=False)),
        (
            galsim.Moffat(beta=3.5, fwhm=0.9).drawImage(nx=25, ny=25, scale=0.27),
            ImagePsf(galsim.Moffat(beta=3.5, fwhm=0.9).drawImage(nx=25, ny=25, scale=0.27)),
        ),
    ],
    ids=["profile", "sampled", "varying", "callable-no-pixel", "callable-varying", "image"],
)
def test_wrapped_forms_are_stored_like_bare_forms(tmp_path, bare, wrapped):
    path_bare = write_exposure(make_exposure(bare), tmp_path / "bare.fits")
    path_wrapped = write_exposure(make_exposure(wrapped), tmp_path / "wrapped.fits")
    assert path_wrapped.read_bytes() == path_bare.read_bytes()


def test_callable_including_the_pixel_keeps_its_flag(tmp_path, small_psfex):
    """A profile that includes the pixel (here PSFEx's, through a WCS) is sampled without
    adding a pixel and read back as a model that draws without adding one: the pixel is in
    the PSF exactly once. Measured: residual <= 7.6e-4 of the peak, |T / T_true - 1| <=
    4.4e-4 (bilinear interpolation between grid nodes of a PSF whose FWHM varies by 20%
    over 100 px; less at the nodes), the sum 0.1% - 0.3% low (stamp truncation: the coadd
    PSF is normalised after averaging). With the pixel applied twice T would be 3-5%
    larger."""
    gwcs = galsim.GSFitsWCS(header=galsim.FitsHeader(sip_wcs().to_header(relax=True)))
    psfex = galsim.des.DES_PSFEx(str(small_psfex), wcs=gwcs)
    model = CallablePsf(
        lambda x, y: psfex.getPSF(galsim.PositionD(x + 1, y + 1)), includes_pixel=True
    )
    exposure = make_exposure(model)
    path = write_exposure(exposure, tmp_path / "e.fits")
    kind, desc = psf_meta(path)
    assert kind == "PIXGRID" and desc["includes_pixel"] is True
    back = read_exposure(path)
    assert isinstance(back.psf, CallablePsf) and back.psf.includes_pixel
    assert isinstance(back.psf.func, GridPsf)
    twice = CallablePsf(back.psf.func, includes_pixel=False)

    def size(stamp: np.ndarray) -> float:
        return galsim.hsm.FindAdaptiveMom(galsim.ImageD(stamp)).moments_sigma ** 2

    for x, y in [*PSF_POSITIONS, (10.0, 7.5)]:
        box = _model_box(x, y)
        truth, stored = exposure.draw_psf(x, y, box), back.draw_psf(x, y, box)
        assert np.max(np.abs(stored - truth)) < 1e-3 * truth.max()
        assert abs(size(stored) / size(truth) - 1) < 1e-3
        assert abs(stored.sum() / truth.sum() - 1) < 5e-3
        wrong = twice.draw(x, y, box, exposure.local_jacobian(x, y))
        assert size(wrong) / size(truth) - 1 > 2e-2
    # a pixel grid read back is written again unchanged
    again = write_exposure(back, tmp_path / "f.fits")
    assert again.read_bytes() == path.read_bytes()


def test_unstorable_psf_model_is_refused(tmp_path):
    from cellcoadd.errors import ExposureError
    from cellcoadd.model.psf import PsfModel

    class Custom(PsfModel):
        includes_pixel = True

        def draw(self, x, y, box, jacobian, center=None):
            return np.ones(box.shape)

    with pytest.raises(ExposureError, match="cannot be stored"):
        write_exposure(make_exposure(Custom()), tmp_path / "e.fits")
    assert not (tmp_path / "e.fits").exists()


# -- end to end: exposure files with survey PSF models -> build_cell ----------------------
E2E_NX, E2E_NY = 1024, 2048
# CCD-pixel shifts of the dithers: one cell lands up to ~1400 px apart on the CCD
E2E_DITHERS = [(0.0, 0.0), (300.3, 740.7), (-270.6, -665.2), (210.9, -380.4)]
E2E_CENTER = (104.0, -55.0)
E2E_STAR_FLUX = 1.0e5


def e2e_wcs(shift: tuple[float, float]) -> WCS:
    """A TAN-SIP WCS rotated by 37 deg, 0.26"/px, with a few pixels of distortion."""
    angle = np.radians(37.0)
    scale = 0.26 / 3600.0
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"]
    wcs.wcs.crval = list(E2E_CENTER)
    wcs.wcs.crpix = [E2E_NX / 2 + 0.5 + shift[0], E2E_NY / 2 + 0.5 + shift[1]]
    wcs.wcs.cd = scale * np.array([[-np.cos(angle), np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    a = np.zeros((3, 3))
    b = np.zeros((3, 3))
    a[2, 0], a[1, 1], a[0, 2] = 2.0e-7, -1.5e-7, 1.0e-7
    b[2, 0], b[1, 1], b[0, 2] = -1.0e-7, 2.0e-7, 1.5e-7
    wcs.sip = Sip(a, b, None, None, wcs.wcs.crpix)
    wcs.wcs.set()
    return wcs


def _e2e_cells():
    from cellcoadd import SkyMap, SkyMapConfig

    config = SkyMapConfig(pixel_scale=0.2, cell_inner=60, cell_border=20, cells_per_patch=4)
    wcs = e2e_wcs((0.0, 0.0))
    ra, dec = wcs.all_pix2world([E2E_NX / 2], [E2E_NY / 2], 0)
    tract = SkyMap.from_centers([(float(ra[0]), float(dec[0]))], config)[0]
    mid = config.cells_per_tract // 2
    return [tract.cell(mid + dx, mid + dy) for dx, dy in ((0, 0), (1, 0), (0, 1))]


def _e2e_build(tmp_path, psf_model, draw_star) -> list[tuple[float, float]]:
    """Write 4 dithered exposures with stars at the cell centres, read them back, coadd
    each cell from the files and from memory; return (T ratio - 1, residual / peak)."""
    from cellcoadd import BuildConfig, build_cell

    config = BuildConfig(n_noise=1, psf_size=31)
    cells = _e2e_cells()
    exposures, paths = [], []
    for visit, shift in enumerate(E2E_DITHERS):
        wcs = e2e_wcs(shift)
        image = np.zeros((E2E_NY, E2E_NX), dtype=np.float32)
        for cell in cells:
            x, y = wcs.all_world2pix([cell.center_sky[0]], [cell.center_sky[1]], 0)
            box = _model_box(float(x[0]), float(y[0]), 25)
            image[box.slices] += E2E_STAR_FLUX * draw_star(float(x[0]), float(y[0]), box)
        exposure = Exposure(
            image=image,
            wcs=wcs,
            variance=1.0 + 0.5 * visit,  # unequal weights
            psf=psf_model,
            visit=visit,
            detector=12,
            band="r",
            zero_point=30.0,
        )
        exposures.append(exposure)
        paths.append(write_exposure(exposure, tmp_path / f"visit{visit}.fits"))
    from_files = [read_exposure(path, trust_psf=True) for path in paths]
    assert all(type(e.psf) is type(psf_model) and e.psf == psf_model for e in from_files)
    results = []
    for cell in cells:
        coadd = build_cell(cell, from_files, config)
        assert coadd.n_used == len(E2E_DITHERS), [r.status for r in coadd.inputs]
        in_memory = build_cell(cell, exposures, config)
        np.testing.assert_array_equal(coadd.psf, in_memory.psf)
        np.testing.assert_array_equal(coadd.image, in_memory.image)
        ny, nx = coadd.image.shape
        half = config.psf_size // 2
        star = coadd.image[ny // 2 - half : ny // 2 + half + 1, nx // 2 - half : nx // 2 + half + 1]
        star = star.astype(np.float64) / star.sum()
        t_star = galsim.hsm.FindAdaptiveMom(galsim.ImageD(star)).moments_sigma ** 2
        t_psf = galsim.hsm.FindAdaptiveMom(galsim.ImageD(coadd.psf)).moments_sigma ** 2
        residual = float(np.abs(star - coadd.psf).max() / coadd.psf.max())
        results.append((t_star / t_psf - 1.0, residual))
    return results


def test_psfex_exposure_files_build_the_star_as_the_coadd_psf(tmp_path):
    info = write_psfex_file(tmp_path / "ccd.psf", nx=E2E_NX, ny=E2E_NY, fwhm_range=(0.85, 1.0))
    psfex = galsim.des.DES_PSFEx(str(info.path))

    def draw_star(x: float, y: float, box: Box) -> np.ndarray:
        # as a DES user does: DES_PSFEx at the 1-based position, FITS bounds
        pos = galsim.PositionD(x + 1.0, y + 1.0)
        stamp = galsim.ImageD(
            galsim.BoundsI(box.x_start + 1, box.x_stop, box.y_start + 1, box.y_stop), scale=1.0
        )
        psfex.getPSF(pos).drawImage(stamp, center=pos, method="no_pixel")
        return stamp.array

    for t_error, residual in _e2e_build(tmp_path, read_psfex(info.path), draw_star):
        assert abs(t_error) < 1e-3 and residual < 1e-3, (t_error, residual)


def test_piff_exposure_files_build_the_star_as_the_coadd_psf(tmp_path):
    import piff

    wcs = galsim.GSFitsWCS(header=galsim.FitsHeader(e2e_wcs((0.0, 0.0)).to_header(relax=True)))
    info = build_piff_model(
        tmp_path / "ccd.piff", nx=E2E_NX, ny=E2E_NY, fwhm_range=(0.85, 1.0), wcs=wcs
    )
    psf = piff.read(str(info.path))

    def draw_star(x: float, y: float, box: Box) -> np.ndarray:
        stamp = galsim.ImageD(
            galsim.BoundsI(box.x_start + 1, box.x_stop, box.y_start + 1, box.y_stop)
        )
        psf.draw(x + 1, y + 1, image=stamp, center=(x + 1, y + 1))
        return stamp.array

    for t_error, residual in _e2e_build(tmp_path, read_piff(info.path, trusted=True), draw_star):
        assert abs(t_error) < 1e-3 and residual < 1e-3, (t_error, residual)
