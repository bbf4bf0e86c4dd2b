"""Survey exposure files (LSST ``ExposureF``, DES ``SCI``/``MSK``/``WGT``) read as
exposure sources.

Files are written here from scratch with realistic headers: LSST with a rotated TAN-SIP
WCS in every plane's header, ``MP_*`` mask-plane keywords, Butler data-ID keywords and
``FLUXMAG0`` or ``BUNIT = 'nJy'``; DES with the real DECam TPV header of
``tests/data/des`` (2048 x 4096), DESDM ``BADPIX_*`` bits, a weight map, a
tile-compressed ``.fits.fz`` variant, a background file and the real PSFEx model.
"""

from __future__ import annotations

import pickle
import warnings
from pathlib import Path

import fitsio
import galsim
import galsim.des
import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS
from conftest import DES_DATA, DES_HEADER, DES_PSF

from cellcoadd import BuildConfig, SkyMap, SkyMapConfig, build_cell
from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.geometry.box import Box
from cellcoadd.io import (
    DES_BAD_MASK_BITS,
    DES_LAYOUT,
    LSST_LAYOUT,
    MefExposureFile,
    MefLayout,
    read_des_exposure,
    read_lsst_exposure,
    read_mef_exposure,
)
from cellcoadd.io.exposures.mef_layout import DES_MASK_VALUES
from cellcoadd.model.psf import GalSimPsf, PsfexPsf

DES_NX, DES_NY = 2048, 4096
LSST_NX, LSST_NY = 260, 300
LSST_PLANES = {
    "BAD": 0,
    "SAT": 1,
    "INTRP": 2,
    "CR": 3,
    "EDGE": 4,
    "DETECTED": 5,
    "DETECTED_NEGATIVE": 6,
    "SUSPECT": 7,
    "NO_DATA": 8,
    "CROSSTALK": 9,
    "NOT_DEBLENDED": 10,
    "UNMASKEDNAN": 11,
    "STREAK": 12,
}
PSF = GalSimPsf(galsim.Moffat(beta=3.5, fwhm=0.8))
STAR_FLUX = 1.0e5


def _need_des_files() -> None:
    """Fail (never skip) if the repository's DES files are missing: they are committed in
    ``tests/data/des``, so a missing file is a broken checkout, not an optional input."""
    missing = [p.name for p in (DES_HEADER, DES_PSF) if not p.is_file()]
    if missing:
        pytest.fail(f"{', '.join(missing)} missing from {DES_DATA}")


# -- LSST ---------------------------------------------------------------------------------


def _sip_cards(center=(150.1, 2.2), angle_deg=37.0) -> list[dict]:
    angle, scale = np.radians(angle_deg), 0.2 / 3600.0
    values = dict(
        CTYPE1="RA---TAN-SIP",
        CTYPE2="DEC--TAN-SIP",
        CRVAL1=center[0],
        CRVAL2=center[1],
        CRPIX1=LSST_NX / 2 + 10.25,
        CRPIX2=LSST_NY / 2 - 7.5,
        CD1_1=-scale * np.cos(angle),
        CD1_2=scale * np.sin(angle),
        CD2_1=scale * np.sin(angle),
        CD2_2=scale * np.cos(angle),
        A_ORDER=2,
        B_ORDER=2,
        A_2_0=2.0e-6,
        A_1_1=-1.5e-6,
        A_0_2=1.0e-6,
        B_2_0=-1.0e-6,
        B_1_1=2.0e-6,
        B_0_2=1.5e-6,
        # afw's alternate WCS "A": the parent-box origin XY0
        CTYPE1A="LINEAR",
        CTYPE2A="LINEAR",
        CRPIX1A=1.0,
        CRPIX2A=1.0,
        CRVAL1A=0.0,
        CRVAL2A=0.0,
        CUNIT1A="PIXEL",
        CUNIT2A="PIXEL",
    )
    return [{"name": k, "value": v} for k, v in values.items()]


def lsst_planes(seed: int = 1):
    rng = np.random.default_rng(seed)
    image = rng.normal(0.0, 30.0, (LSST_NY, LSST_NX)).astype(np.float32)
    mask = np.zeros((LSST_NY, LSST_NX), dtype=np.int32)
    mask[40:44, 50:60] |= 1 << LSST_PLANES["SAT"]
    mask[100, 120] |= 1 << LSST_PLANES["CR"]
    mask[:, :3] |= 1 << LSST_PLANES["EDGE"]
    mask[150:170, 150:170] |= 1 << LSST_PLANES["DETECTED"]
    variance = (900.0 + rng.uniform(0, 50, (LSST_NY, LSST_NX))).astype(np.float32)
    return image, mask, variance


def write_lsst(
    path: Path,
    planes=None,
    *,
    calib: str = "fluxmag0",
    with_variance: bool = True,
    planes_keywords: dict[str, int] | None = None,
    band_keyword: bool = True,
    compress: str | None = None,
) -> Path:
    image, mask, variance = planes if planes is not None else lsst_planes()
    primary = [
        {"name": "HIERARCH LSST BUTLER DATAID INSTRUMENT", "value": "LSSTCam"},
        {"name": "HIERARCH LSST BUTLER DATAID VISIT", "value": 2025061100123},
        {"name": "HIERARCH LSST BUTLER DATAID DETECTOR", "value": 94},
        {"name": "FILTER", "value": "r_57"},
        {"name": "EXPTIME", "value": 30.0},
        {"name": "AR_HDU", "value": 5},
        {"name": "PSF_ID", "value": 1},
    ]
    if band_keyword:
        primary.append({"name": "HIERARCH LSST BUTLER DATAID BAND", "value": "r"})
    if calib == "fluxmag0":
        primary.append({"name": "FLUXMAG0", "value": 10 ** (0.4 * 28.7)})
    wcs = _sip_cards()
    image_cards = [{"name": "EXTTYPE", "value": "IMAGE"}, *wcs]
    if calib == "njy":
        image_cards.append({"name": "BUNIT", "value": "nJy"})
    bits = LSST_PLANES if planes_keywords is None else planes_keywords
    mask_cards = [{"name": "EXTTYPE", "value": "MASK"}, *wcs]
    mask_cards += [{"name": f"MP_{name}", "value": bit} for name, bit in bits.items()]
    with fitsio.FITS(path, "rw", clobber=True) as fits:
        fits.write(None, header=primary)
        fits.write(image, extname="IMAGE", header=image_cards, compress=compress, qlevel=None)
        fits.write(mask, extname="MASK", header=mask_cards, compress=compress)
        if with_variance:
            cards = [{"name": "EXTTYPE", "value": "VARIANCE"}, *wcs]
            fits.write(variance, extname="VARIANCE", header=cards, compress=compress, qlevel=None)
        # the afw archive (PSF, photoCalib, ...) that cellcoadd does not read
        fits.write(np.zeros(3, dtype=[("id", "i8")]), extname="ARCHIVE_INDEX")
    return path


@pytest.fixture(scope="module")
def lsst_file(tmp_path_factory):
    return write_lsst(tmp_path_factory.mktemp("lsst") / "visit_image.fits")


def test_lsst_file_reads_planes_bits_identity_and_zero_point(lsst_file, tmp_path):
    image, mask, variance = lsst_planes()
    exposure = read_lsst_exposure(lsst_file, psf=PSF)
    np.testing.assert_array_equal(exposure.image, image)
    np.testing.assert_array_equal(exposure.mask, mask)
    np.testing.assert_array_equal(exposure.variance, variance)
    assert exposure.mask_bits.bits == LSST_PLANES
    sat = exposure.mask_bits.value("SAT")
    assert np.all(exposure.mask[40:44, 50:60] & sat) and exposure.mask[0, 10] & sat == 0
    assert exposure.mask[100, 120] & exposure.mask_bits.value("CR")
    assert exposure.key == (2025061100123, 94) and exposure.band == "r"
    assert exposure.zero_point == pytest.approx(28.7, abs=1e-12)
    assert exposure.origin == (0, 0)
    # nJy pixels: AB zero point 31.4; FILTER's first word when the band keyword is absent
    path = write_lsst(tmp_path / "njy.fits", calib="njy", band_keyword=False)
    exposure = read_lsst_exposure(path, psf=PSF)
    assert exposure.zero_point == pytest.approx(31.4, abs=1e-3) and exposure.band == "r"
    # no calibration in the header: the argument, else an error naming the file and HDUs
    path = write_lsst(tmp_path / "uncal.fits", calib="none")
    assert read_lsst_exposure(path, psf=PSF, zero_point=27.0).zero_point == 27.0
    with pytest.raises(CellCoaddFormatError, match=r"uncal\.fits.*zero point.*IMAGE"):
        read_lsst_exposure(path, psf=PSF)


def test_lsst_cutout_equals_slice_and_its_wcs_is_shifted(lsst_file):
    source = MefExposureFile(lsst_file, LSST_LAYOUT, PSF)
    full = source.load()
    header = source.header()
    assert header.shape == (LSST_NY, LSST_NX) and header.zero_point == full.zero_point
    box = Box(x_start=37, x_stop=211, y_start=58, y_stop=255)
    cut = source.load(box)
    assert cut.origin == (37, 58) and cut.shape == box.shape
    for name in ("image", "mask", "variance"):
        a, b = getattr(cut, name), getattr(full, name)[box.slices]
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
    _check_cutout_wcs(header.wcs, cut.wcs, box)
    # clipped to the detector
    edge = source.load(Box(x_start=200, x_stop=400, y_start=-5, y_stop=20))
    assert edge.origin == (200, 0) and edge.shape == (20, LSST_NX - 200)


def _check_cutout_wcs(full: WCS, cut: WCS, box: Box) -> None:
    rng = np.random.default_rng(3)
    x = rng.uniform(-20, box.nx + 20, 50)
    y = rng.uniform(-20, box.ny + 20, 50)
    ra_c, dec_c = cut.all_pix2world(x, y, 0)
    ra_f, dec_f = full.all_pix2world(x + box.x_start, y + box.y_start, 0)
    assert np.max(np.abs(ra_c - ra_f) * np.cos(np.radians(dec_f))) < 1e-10
    assert np.max(np.abs(dec_c - dec_f)) < 1e-10


def _forbid_pixel_reads(monkeypatch) -> None:
    def refuse(*args, **kwargs):
        raise AssertionError("pixels were read")

    monkeypatch.setattr(fitsio.hdu.ImageHDU, "read", refuse)
    monkeypatch.setattr(fitsio.hdu.ImageHDU, "_read_image_slice", refuse)
    monkeypatch.setattr(fitsio, "read", refuse)


def test_header_reads_no_pixels_and_sources_pickle(lsst_file, tmp_path, monkeypatch):
    fz = write_lsst(tmp_path / "visit_image.fits.fz", compress="GZIP_2")
    source = MefExposureFile(fz, LSST_LAYOUT, PSF)
    expected = MefExposureFile(lsst_file, LSST_LAYOUT, PSF).load()
    clone = pickle.loads(pickle.dumps(source))
    with monkeypatch.context() as patch:
        _forbid_pixel_reads(patch)
        header = clone.header()
        with pytest.raises(AssertionError, match="pixels were read"):
            clone.load()
    assert header.key == (2025061100123, 94) and header.band == "r"
    assert header.mask_bits.bits == LSST_PLANES
    loaded = clone.load()
    np.testing.assert_array_equal(loaded.image, expected.image)
    np.testing.assert_array_equal(loaded.mask, expected.mask)
    assert not any(hasattr(v, "close") for v in vars(source).values())


def test_psf_argument_forms(lsst_file):
    source = MefExposureFile(lsst_file, LSST_LAYOUT, DES_PSF)
    assert isinstance(source.psf, PsfexPsf)
    assert isinstance(read_lsst_exposure(lsst_file, psf=str(DES_PSF)).psf, PsfexPsf)
    with pytest.raises(CellCoaddFormatError, match="missing.psf"):
        MefExposureFile(lsst_file, LSST_LAYOUT, DES_PSF.parent / "missing.psf")


def test_errors_name_the_file_and_the_hdu(tmp_path):
    image, mask, variance = lsst_planes()
    with pytest.raises(CellCoaddFormatError, match=r"nothere\.fits: no such file"):
        read_lsst_exposure(tmp_path / "nothere.fits", psf=PSF)
    path = write_lsst(tmp_path / "novar.fits", with_variance=False)
    with pytest.raises(CellCoaddFormatError, match=r"novar\.fits: no variance HDU 'VARIANCE'"):
        MefExposureFile(path, LSST_LAYOUT, PSF).header()
    path = write_lsst(tmp_path / "shape.fits", (image, mask[:-1], variance))
    with pytest.raises(CellCoaddFormatError, match=r"shape\.fits: HDU 2 \(MASK\).*shape"):
        read_lsst_exposure(path, psf=PSF)
    bits = {k: v for k, v in LSST_PLANES.items() if k != "CR"}
    path = write_lsst(tmp_path / "bits.fits", planes_keywords=bits)
    with pytest.raises(CellCoaddFormatError, match=r"bits\.fits: HDU 2 \(MASK\): mask bits 0x8"):
        read_lsst_exposure(path, psf=PSF)
    path = write_lsst(tmp_path / "nomp.fits", planes_keywords={})
    with pytest.raises(CellCoaddFormatError, match=r"nomp\.fits: HDU 2 \(MASK\): no MP_"):
        read_lsst_exposure(path, psf=PSF)
    nan_image = image.copy()
    nan_image[5, 5] = np.nan
    path = write_lsst(tmp_path / "nan.fits", (nan_image, mask, variance))
    with pytest.raises(CellCoaddFormatError, match=r"nan\.fits: .*non-finite"):
        read_lsst_exposure(path, psf=PSF)
    with pytest.raises(ValueError, match="exactly one"):
        MefLayout(image_hdu=1, mask_hdu=2)


def test_layout_from_numbers_and_explicit_identity(lsst_file):
    layout = MefLayout(
        image_hdu=1,
        mask_hdu=2,
        variance_hdu=3,
        zero_point_keys=(),
        visit_keys=("NOPE",),
        band_keys=(),
        filter_key=None,
    )
    exposure = read_mef_exposure(
        lsst_file, layout, PSF, zero_point=30.0, visit=7, detector=8, band="i"
    )
    assert exposure.key == (7, 8) and exposure.band == "i" and exposure.zero_point == 30.0
    with pytest.raises(CellCoaddFormatError, match=r"no visit keyword \['NOPE'\]"):
        read_mef_exposure(lsst_file, layout, PSF, zero_point=30.0)


# -- DES ----------------------------------------------------------------------------------

_SKIP = ("SIMPLE", "BITPIX", "EXTEND", "XTENSION", "PCOUNT", "GCOUNT", "CHECKSUM", "DATASUM")


def des_header_cards(shift=(0.0, 0.0), magzero: float | None = None) -> list[dict]:
    cards = []
    for record in fitsio.read_header(DES_HEADER).records():
        name = record.get("name") or ""
        if (
            not name
            or name in _SKIP
            or name.startswith(("NAXIS", "Z"))
            or name in ("COMMENT", "HISTORY")
        ):
            continue
        value = record["value"]
        if name == "CRPIX1":
            value += shift[0]
        if name == "CRPIX2":
            value += shift[1]
        cards.append({"name": name, "value": value})
    if magzero is not None:
        cards.append({"name": "MAGZERO", "value": magzero})
    return cards


def des_tpv_wcs(shift=(0.0, 0.0)) -> WCS:
    """The real CCD's TPV WCS, as astropy reads it, its pointing moved by ``shift``."""
    header = fits.getheader(DES_HEADER)
    header["NAXIS"], header["NAXIS1"], header["NAXIS2"] = 2, DES_NX, DES_NY
    header["CRPIX1"] += shift[0]
    header["CRPIX2"] += shift[1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return WCS(header)


def des_planes(seed: int = 2):
    rng = np.random.default_rng(seed)
    image = rng.normal(0.0, 5.0, (DES_NY, DES_NX)).astype(np.float32)
    mask = np.zeros((DES_NY, DES_NX), dtype=np.int16)
    mask[10:20, 30:40] = DES_MASK_VALUES["BADPIX_SATURATE"]
    mask[3000, 1500] = DES_MASK_VALUES["BADPIX_CRAY"]
    mask[:, 2040:] |= DES_MASK_VALUES["BADPIX_EDGE"]
    mask[500:503, 700:710] = DES_MASK_VALUES["BADPIX_SUSPECT"]
    weight = np.full((DES_NY, DES_NX), 1.0 / 25.0, dtype=np.float32)
    weight[3900:3910, 100:120] = 0.0
    weight[10:20, 30:40] = 0.0
    return image, mask, weight


def write_des(path: Path, planes, *, shift=(0.0, 0.0), magzero=None, compress=None) -> Path:
    image, mask, weight = planes
    cards = des_header_cards(shift, magzero)
    with fitsio.FITS(path, "rw", clobber=True) as fits:
        if compress:
            fits.write(None)
        fits.write(image, extname="SCI", header=cards, compress=compress, qlevel=None)
        fits.write(mask, extname="MSK", header=cards, compress=compress and "RICE")
        fits.write(weight, extname="WGT", header=cards, compress=compress, qlevel=None)
    return path


def write_background(path: Path) -> tuple[Path, np.ndarray]:
    y, x = np.mgrid[0:DES_NY, 0:DES_NX]
    background = (100.0 + 0.25 * (x // 64) + 0.5 * (y // 128)).astype(np.float32)
    with fitsio.FITS(path, "rw", clobber=True) as fits:
        fits.write(None)
        fits.write(background, extname="SCI", compress="GZIP_2", qlevel=None)
    return path, background


@pytest.fixture(scope="module")
def des_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("des")
    planes = des_planes()
    plain = write_des(root / "D00154912_Y_c12_r1p1_immasked.fits", planes)
    bkg, background = write_background(root / "D00154912_Y_c12_r1p1_bkg.fits.fz")
    with_bkg = (planes[0] + background, planes[1], planes[2])
    fz = write_des(
        root / "D00154912_Y_c12_r1p1_immasked.fits.fz", with_bkg, magzero=30.5, compress="GZIP_2"
    )
    return {"plain": plain, "fz": fz, "bkg": bkg, "planes": planes, "background": background}


def test_des_file_reads_weight_bits_identity_zero_point(des_files):
    image, mask, weight = des_files["planes"]
    exposure = read_des_exposure(des_files["plain"], DES_PSF, zero_point=31.2)
    assert exposure.key == (154912, 12) and exposure.band == "Y"
    assert exposure.zero_point == 31.2 and isinstance(exposure.psf, PsfexPsf)
    np.testing.assert_array_equal(exposure.image, image)
    bits = exposure.mask_bits
    assert {name: 1 << bit for name, bit in bits.bits.items() if name != "ZERO_WEIGHT"} == (
        DES_MASK_VALUES
    )
    zero = bits.value("ZERO_WEIGHT")
    np.testing.assert_array_equal(exposure.mask & ~zero, mask)
    np.testing.assert_array_equal((exposure.mask & zero) != 0, weight <= 0)
    assert exposure.mask[3000, 1500] & bits.value("BADPIX_CRAY")
    good = weight > 0
    np.testing.assert_allclose(exposure.variance[good], 25.0, rtol=1e-6)
    assert np.all(np.isnan(exposure.variance[~good]))
    assert exposure.background_variance == pytest.approx(25.0, rel=1e-6)
    with pytest.raises(CellCoaddFormatError, match=r"immasked\.fits: no zero point.*SCI"):
        read_des_exposure(des_files["plain"], DES_PSF)


def test_des_compressed_with_background(des_files, monkeypatch):
    image, mask, _ = des_files["planes"]
    source = MefExposureFile(des_files["fz"], DES_LAYOUT, DES_PSF, background=des_files["bkg"])
    with monkeypatch.context() as patch:
        _forbid_pixel_reads(patch)
        header = source.header()
    assert header.zero_point == 30.5 and header.key == (154912, 12)
    full = read_des_exposure(des_files["fz"], DES_PSF, des_files["bkg"], zero_point=20.0)
    assert full.zero_point == 30.5  # the header's MAGZERO wins
    np.testing.assert_allclose(full.image, image, rtol=0, atol=1e-4)
    box = Box(x_start=1000, x_stop=1300, y_start=2900, y_stop=3100)
    cut = source.load(box)
    for name in ("image", "mask", "variance"):
        a, b = getattr(cut, name), getattr(full, name)[box.slices]
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
    _check_cutout_wcs(header.wcs, cut.wcs, box)
    _check_cutout_wcs(des_tpv_wcs(), cut.wcs, box)
    corner = source.load(Box(x_start=25, x_stop=45, y_start=5, y_stop=25))
    both = corner.mask_bits.mask_of(["BADPIX_SATURATE", "ZERO_WEIGHT"])
    assert np.all(corner.mask[5:15, 5:15] == both) and corner.mask[0, 0] == 0
    without = read_des_exposure(des_files["fz"], DES_PSF)
    np.testing.assert_allclose(without.image - full.image, des_files["background"], atol=1e-4)


# -- a build from survey files: a star drawn from the model is the coadd PSF ------------

SKY = SkyMapConfig(pixel_scale=0.2, cell_inner=60, cell_border=20, cells_per_patch=4)
BUILD = BuildConfig(n_noise=1, psf_size=31, bad_mask_bits=DES_BAD_MASK_BITS)
DITHERS = [(0.0, 0.0), (610.3, 1480.7)]


def _stamp_box(x: float, y: float, half: int = 25) -> Box:
    ix, iy = round(x), round(y)
    return Box(x_start=ix - half, x_stop=ix + half + 1, y_start=iy - half, y_stop=iy + half + 1)


def test_build_from_des_files_star_equals_coadd_psf(tmp_path):
    psfex = galsim.des.DES_PSFEx(str(DES_PSF))
    center = des_tpv_wcs().all_pix2world([DES_NX / 2], [DES_NY / 2], 0)
    tract = SkyMap.from_centers([(float(center[0][0]), float(center[1][0]))], SKY)[0]
    mid = SKY.cells_per_tract // 2
    cells = [tract.cell(mid, mid), tract.cell(mid + 1, mid)]
    sources = []
    for visit, shift in enumerate(DITHERS):
        wcs = des_tpv_wcs(shift)
        image, mask, weight = des_planes(seed=visit)
        image[:] = 0.0
        for cell in cells:
            x, y = wcs.all_world2pix([cell.center_sky[0]], [cell.center_sky[1]], 0)
            x, y = float(x[0]), float(y[0])
            box = _stamp_box(x, y)
            pos = galsim.PositionD(x + 1.0, y + 1.0)
            stamp = galsim.ImageF(
                galsim.BoundsI(box.x_start + 1, box.x_stop, box.y_start + 1, box.y_stop),
                scale=1.0,
            )
            psfex.getPSF(pos).drawImage(stamp, center=pos, method="no_pixel")
            image[box.slices] += STAR_FLUX * stamp.array
        path = write_des(tmp_path / f"D{visit:08d}_c12.fits", (image, mask, weight), shift=shift)
        sources.append(MefExposureFile(path, DES_LAYOUT, DES_PSF, zero_point=30.0, visit=visit))
    for cell in cells:
        # the sources themselves: build_cell loads each cut to the cell, one at a time
        coadd = build_cell(cell, sources, BUILD)
        assert coadd.n_used == len(sources), [r.status for r in coadd.inputs]
        ny, nx = coadd.image.shape
        half = BUILD.psf_size // 2
        star = coadd.image[ny // 2 - half : ny // 2 + half + 1, nx // 2 - half : nx // 2 + half + 1]
        star = star.astype(np.float64) / star.sum()
        residual = float(np.abs(star - coadd.psf).max() / coadd.psf.max())
        assert residual < 1e-3, residual
