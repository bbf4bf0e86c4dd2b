"""Exposure files: lossless round trips, atomic writes and corruption detection."""

from __future__ import annotations

import json
import os
import shutil

import fitsio
import galsim
import numpy as np
import pytest
from astropy.wcs import WCS, Sip

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.geometry.box import Box
from cellcoadd.io.exposure_io import read_exposure, write_exposure
from cellcoadd.io.psf_codec import PsfCodecError, decode_psf, encode_psf
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.maskbits import MaskBits
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
        galsim.Add(galsim.Gaussian(sigma=0.4, flux=0.7), galsim.Exponential(scale_radius=0.3)),
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

    exposure = make_exposure(as_plain_function)
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
    psf = galsim.InterpolatedImage(moffat.drawImage(nx=65, ny=65, scale=0.05, method="no_pixel"))
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
