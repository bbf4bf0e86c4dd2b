"""PSF models from survey files: a star drawn from the model equals the coadd PSF.

The acceptance test of survey PSFs: exposures of 2048 x 4096 pixels with a real DECam
TPV WCS (``tests/data/des``) or a rotated TAN-SIP WCS, dithered so that one cell
falls at very different places of the CCD in different exposures; a PSFEx model (and a
Piff model) whose FWHM varies by > 5% across the CCD; a star drawn at every cell centre
the way a survey user draws one (``DES_PSFEx.getPSF`` at the 1-based position,
``piff.PSF.draw``). The coadd PSF must equal the coadded star.
"""

from __future__ import annotations

from pathlib import Path

import galsim
import galsim.des
import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS
from conftest import DES_HEADER, DES_PSF
from survey_psf_factory import build_piff_model, write_psfex_file

from cellcoadd import BuildConfig, Exposure, SkyMap, SkyMapConfig, build_cell
from cellcoadd.errors import CellCoaddFormatError, ExposureError, PsfError
from cellcoadd.geometry.box import Box
from cellcoadd.io import read_piff, read_psfex
from cellcoadd.model.psf import CallablePsf, GalSimPsf, ImagePsf, PsfexPsf

NX, NY = 2048, 4096
# CCD-pixel shifts of the dithers: the same cell lands up to ~1500 px apart on the CCD
DITHERS = [(0.0, 0.0), (610.3, 1480.7), (-540.6, -1330.2), (420.9, -760.4)]
STAR_FLUX = 1.0e5
BUILD = BuildConfig(n_noise=1, psf_size=31)
SKY = SkyMapConfig(pixel_scale=0.2, cell_inner=60, cell_border=20, cells_per_patch=4)


def des_tpv_wcs(shift: tuple[float, float]) -> WCS:
    """The real DECam CCD's TPV WCS, its pointing moved by ``shift`` CCD pixels."""
    header = fits.getheader(DES_HEADER)
    header["NAXIS"], header["NAXIS1"], header["NAXIS2"] = 2, NX, NY
    header["CRPIX1"] += shift[0]
    header["CRPIX2"] += shift[1]
    return WCS(header)


def rotated_sip_wcs(shift: tuple[float, float], center: tuple[float, float]) -> WCS:
    """A TAN-SIP WCS rotated by 37 deg, 0.26"/px, with a few pixels of distortion."""
    angle = np.radians(37.0)
    scale = 0.26 / 3600.0
    header = fits.Header()
    header.update(
        NAXIS=2,
        NAXIS1=NX,
        NAXIS2=NY,
        CTYPE1="RA---TAN-SIP",
        CTYPE2="DEC--TAN-SIP",
        CRVAL1=center[0],
        CRVAL2=center[1],
        CRPIX1=NX / 2 + 0.5 + shift[0],
        CRPIX2=NY / 2 + 0.5 + shift[1],
        CD1_1=-scale * np.cos(angle),
        CD1_2=scale * np.sin(angle),
        CD2_1=scale * np.sin(angle),
        CD2_2=scale * np.cos(angle),
        A_ORDER=2,
        B_ORDER=2,
        A_2_0=2.0e-7,
        A_1_1=-1.5e-7,
        A_0_2=1.0e-7,
        B_2_0=-1.0e-7,
        B_1_1=2.0e-7,
        B_0_2=1.5e-7,
    )
    return WCS(header)


def _cells(center: tuple[float, float]):
    tract = SkyMap.from_centers([center], SKY)[0]
    mid = SKY.cells_per_tract // 2
    return [tract.cell(mid + dx, mid + dy) for dx, dy in ((0, 0), (1, 0), (0, 1))]


def _exposures(wcs_list, psf_model, draw_star, cells):
    exposures = []
    for visit, wcs in enumerate(wcs_list):
        image = np.zeros((NY, NX), dtype=np.float64)
        for cell in cells:
            x, y = wcs.all_world2pix([cell.center_sky[0]], [cell.center_sky[1]], 0)
            draw_star(image, float(x[0]), float(y[0]))
        exposures.append(
            Exposure(
                image=image,
                wcs=wcs,
                variance=1.0 + 0.5 * visit,  # unequal weights
                psf=psf_model,
                visit=visit,
                detector=12,
                band="r",
                zero_point=30.0,
            )
        )
    return exposures


def _check_star_is_psf(exposures, cells) -> list[tuple[float, float]]:
    """Coadd each cell; return (T ratio - 1, max residual / peak) per cell."""
    results = []
    for cell in cells:
        coadd = build_cell(cell, exposures, BUILD)
        assert coadd.n_used == len(exposures), [r.status for r in coadd.inputs]
        ny, nx = coadd.image.shape
        half = BUILD.psf_size // 2
        star = coadd.image[ny // 2 - half : ny // 2 + half + 1, nx // 2 - half : nx // 2 + half + 1]
        star = star.astype(np.float64) / star.sum()
        psf = coadd.psf
        t_star = galsim.hsm.FindAdaptiveMom(galsim.ImageD(star)).moments_sigma ** 2
        t_psf = galsim.hsm.FindAdaptiveMom(galsim.ImageD(psf)).moments_sigma ** 2
        results.append((t_star / t_psf - 1.0, float(np.abs(star - psf).max() / psf.max())))
    return results


def _stamp_box(x: float, y: float, half: int = 25) -> Box:
    ix, iy = round(x), round(y)
    return Box(x_start=ix - half, x_stop=ix + half + 1, y_start=iy - half, y_stop=iy + half + 1)


@pytest.fixture(scope="module")
def psfex_file(tmp_path_factory):
    info = write_psfex_file(tmp_path_factory.mktemp("psfex") / "ccd.psf")
    return info.path


def _psfex_star(path: Path):
    """Draw a star as a DES user does: DES_PSFEx at the 1-based position, FITS bounds."""
    psfex = galsim.des.DES_PSFEx(str(path))

    def draw(image: np.ndarray, x: float, y: float) -> None:
        box = _stamp_box(x, y)
        pos = galsim.PositionD(x + 1.0, y + 1.0)
        stamp = galsim.ImageD(
            galsim.BoundsI(box.x_start + 1, box.x_stop, box.y_start + 1, box.y_stop), scale=1.0
        )
        psfex.getPSF(pos).drawImage(stamp, center=pos, method="no_pixel")
        image[box.slices] += STAR_FLUX * stamp.array

    return draw


@pytest.mark.parametrize("layout", ["tpv", "sip"])
def test_psfex_star_equals_coadd_psf(psfex_file, layout):
    wcs_list = _layout_wcs_list(layout)
    center = wcs_list[0].all_pix2world([NX / 2], [NY / 2], 0)
    cells = _cells((float(center[0][0]), float(center[1][0])))
    exposures = _exposures(wcs_list, read_psfex(psfex_file), _psfex_star(psfex_file), cells)
    for t_error, residual in _check_star_is_psf(exposures, cells):
        assert abs(t_error) < 1e-3 and residual < 1e-3, (t_error, residual)


def test_the_check_sees_a_pixel_applied_twice(psfex_file):
    """The same build with the PSFEx profile taken as pre-pixel (the old behaviour of a
    bare callable) fails the acceptance check: the test can tell right from wrong."""
    wcs_list = [des_tpv_wcs(shift) for shift in DITHERS[:2]]
    center = wcs_list[0].all_pix2world([NX / 2], [NY / 2], 0)
    cells = _cells((float(center[0][0]), float(center[1][0])))[:1]
    psfex = galsim.des.DES_PSFEx(str(psfex_file), wcs=galsim.FitsWCS(str(DES_HEADER)))
    wrong = CallablePsf(
        lambda x, y: psfex.getPSF(galsim.PositionD(x + 1, y + 1)), includes_pixel=False
    )
    exposures = _exposures(wcs_list, wrong, _psfex_star(psfex_file), cells)
    ((t_error, _),) = _check_star_is_psf(exposures, cells)
    assert abs(t_error) > 1e-2
    right = CallablePsf(wrong.func, includes_pixel=True)
    exposures = _exposures(wcs_list, right, _psfex_star(psfex_file), cells)
    ((t_error, residual),) = _check_star_is_psf(exposures, cells)
    assert abs(t_error) < 2e-3 and residual < 5e-3  # the local Jacobian of another WCS


def test_real_des_psfex_model_draws_where_galsim_does():
    """The real DECam model, drawn by PsfexPsf at 0-based (x, y), equals GalSim's
    DES_PSFEx at the 1-based position divided by the sum of GalSim's drawing over the
    model's whole support (~0.5% from 1 with the phase: PsfexPsf draws unit flux), and
    its size varies over the CCD."""
    model = read_psfex(DES_PSF)
    psfex = galsim.des.DES_PSFEx(str(DES_PSF))
    sizes = []
    for x, y in [(10.3, 20.7), (1023.5, 2047.5), (2037.2, 4080.9)]:
        box = _stamp_box(x, y, 15)
        ours = model.draw(x, y, box, np.eye(2) * 0.263)
        whole = _stamp_box(x, y, 20)  # holds the model's support (~15 px)
        ref = galsim.ImageD(
            galsim.BoundsI(whole.x_start + 1, whole.x_stop, whole.y_start + 1, whole.y_stop),
            scale=1.0,
        )
        pos = galsim.PositionD(x + 1, y + 1)
        psfex.getPSF(pos).drawImage(ref, center=pos, method="no_pixel")
        total = ref.array.sum()
        assert abs(total - 1.0) < 1e-2
        inner = ref.array[box.y_start - whole.y_start : box.y_stop - whole.y_start,
                          box.x_start - whole.x_start : box.x_stop - whole.x_start]  # fmt: skip
        np.testing.assert_allclose(ours, inner / total, rtol=0, atol=1e-12)
        sizes.append(galsim.hsm.FindAdaptiveMom(galsim.ImageD(ours)).moments_sigma)
    assert max(sizes) / min(sizes) > 1.01


def _layout_wcs_list(layout: str) -> list[WCS]:
    if layout == "tpv":
        return [des_tpv_wcs(shift) for shift in DITHERS]
    return [rotated_sip_wcs(shift, (104.0, -55.0)) for shift in DITHERS]


@pytest.mark.parametrize("layout", ["tpv", "sip"])
def test_piff_star_equals_coadd_psf(tmp_path, layout):
    piff = pytest.importorskip("piff", reason="Piff is the optional extra cellcoadd[piff]")
    wcs_list = _layout_wcs_list(layout)
    # Piff is fitted with the first dither's WCS, as it would be on that exposure
    header = galsim.FitsHeader(wcs_list[0].to_header(relax=True))
    if layout == "tpv":
        header = galsim.FitsHeader(str(DES_HEADER))
    path = build_piff_model(tmp_path / "ccd.piff", wcs=galsim.FitsWCS(header=header)).path
    psf = piff.read(str(path))

    def draw_star(image: np.ndarray, x: float, y: float) -> None:
        box = _stamp_box(x, y)
        stamp = galsim.ImageD(
            galsim.BoundsI(box.x_start + 1, box.x_stop, box.y_start + 1, box.y_stop)
        )
        psf.draw(x + 1, y + 1, image=stamp, center=(x + 1, y + 1))
        image[box.slices] += STAR_FLUX * stamp.array

    center = wcs_list[0].all_pix2world([NX / 2], [NY / 2], 0)
    cells = _cells((float(center[0][0]), float(center[1][0])))
    exposures = _exposures(wcs_list, read_piff(path, trusted=True), draw_star, cells)
    for t_error, residual in _check_star_is_psf(exposures, cells):
        assert abs(t_error) < 1e-3 and residual < 1e-3, (t_error, residual)


def test_models_pickle_and_refuse_bad_input(psfex_file, tmp_path):
    import pickle

    model = read_psfex(psfex_file)
    box = _stamp_box(500.2, 900.7, 10)
    before = model.draw(500.2, 900.7, box, np.eye(2))
    back = pickle.loads(pickle.dumps(model))
    assert back == model
    np.testing.assert_array_equal(back.draw(500.2, 900.7, box, np.eye(2)), before)
    junk = tmp_path / "junk.psf"
    junk.write_bytes(b"not a PSFEx file")
    with pytest.raises(CellCoaddFormatError, match="junk.psf"):  # refused on reading
        read_psfex(junk)
    with pytest.raises(CellCoaddFormatError, match="no such PSF model file"):
        read_psfex(tmp_path / "missing.psf")
    with pytest.raises(PsfError, match=r"read_psfex\(path\)"):  # models never read files
        PsfexPsf(psfex_file)  # type: ignore[arg-type]
    with pytest.raises(PsfError, match="includes_pixel"):
        CallablePsf(lambda x, y: galsim.Gaussian(sigma=1.0), includes_pixel=None)  # type: ignore[arg-type]
    with pytest.raises(ExposureError, match="PsfModel, a GSObject"):
        Exposure(
            image=np.zeros((10, 10)),
            wcs=rotated_sip_wcs((0, 0), (10.0, 0.0)),
            variance=1.0,
            psf=42,  # type: ignore[arg-type]
            visit=1,
            detector=1,
            band="r",
            zero_point=30.0,
        )


def test_bare_forms_become_models():
    """A GSObject is a pre-pixel GalSimPsf, a galsim.Image an ImagePsf; a bare callable
    must say whether it includes the pixel."""
    from cellcoadd.model.psf import as_psf_model

    gaussian = galsim.Gaussian(sigma=0.4)
    assert isinstance(as_psf_model(gaussian), GalSimPsf)
    with pytest.raises(PsfError, match="include the pixel"):
        as_psf_model(lambda x, y: gaussian)
    stamp = gaussian.drawImage(nx=15, ny=15, scale=0.2, dtype=float)
    assert isinstance(as_psf_model(stamp), ImagePsf)
    jac = np.eye(2) * 0.2
    box = Box.from_shape((15, 15))
    drawn = as_psf_model(gaussian).draw(7.0, 7.0, box, jac)
    np.testing.assert_allclose(drawn, stamp.array, atol=1e-12)  # pixel added once
    interpolated = as_psf_model(stamp).draw(7.0, 7.0, box, jac)
    np.testing.assert_allclose(interpolated, stamp.array, atol=1e-6)  # not added again
