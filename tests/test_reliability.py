"""Hostile inputs: malformed exposures refused when they are built, and bad inputs
rejected cell by cell without changing the coadd (see docs/reliability.md).

Faults while writing are in ``test_write_faults.py``, failing workers and byte-identical
files across executors in ``test_executors.py``.
"""

from __future__ import annotations

import dataclasses
import os

import galsim
import numpy as np
import pytest
from astropy.wcs import WCS
from coadd_factory import TINY_BUILD, tiny_exposures, tiny_patch
from exposure_factory import make_exposure, make_wcs

import cellcoadd.builder.exposure_frame as frame_module
import cellcoadd.builder.select as select_module
from cellcoadd import Box, Exposure, ExposureError, build_patch
from cellcoadd.io.exposures.exposure_io import write_exposure
from cellcoadd.model.psf import GalSimPsf


@pytest.fixture(scope="module")
def tiny():
    """The tiny patch, two good exposures and their serial build."""
    patch = tiny_patch()
    good = tiny_exposures(patch, 2)
    return patch, good, build_patch(patch, good, TINY_BUILD, seed=1, progress=False)


# --------------------------------------------------------------- exposures refused up front


def _kwargs() -> dict:
    shape = (30, 40)
    return dict(
        image=np.zeros(shape),
        wcs=make_wcs((30.0, -10.0), shape, 0.26),
        variance=1.0,
        psf=galsim.Gaussian(sigma=0.4),
        visit=5,
        detector=2,
        band="r",
        zero_point=30.0,
    )


def _wcs(**changes) -> WCS:
    wcs = make_wcs((30.0, -10.0), (30, 40), 0.26)
    for name, value in changes.items():
        setattr(wcs.wcs, name, value)
    return wcs


def _other_wcs(ctypes: list[str]) -> WCS:
    wcs = WCS(naxis=len(ctypes))
    wcs.wcs.ctype = ctypes
    wcs.wcs.crval = [30.0, -10.0, 1e9][: len(ctypes)]
    wcs.wcs.cdelt = [-7e-5, 7e-5, 1e6][: len(ctypes)]
    return wcs


_NAN_PIXEL = np.zeros((30, 40))
_NAN_PIXEL[4, 7] = np.nan
REFUSED = {
    "unmasked NaN pixel": dict(image=_NAN_PIXEL),
    "unmasked inf pixel": dict(image=np.where(_NAN_PIXEL != _NAN_PIXEL, -np.inf, 0.0)),
    "complex image": dict(image=np.zeros((30, 40), complex)),
    "mask with unknown bits": dict(mask=np.full((30, 40), 1 << 20, np.int32)),
    "mask bit beyond int32": dict(mask=np.full((30, 40), 1 << 40, np.int64)),
    "float mask": dict(mask=np.zeros((30, 40))),
    "linear WCS": dict(wcs=_other_wcs(["X", "Y"])),
    "galactic WCS": dict(wcs=_other_wcs(["GLON-TAN", "GLAT-TAN"])),
    "WCS with a spectral axis": dict(wcs=_other_wcs(["RA---TAN", "DEC--TAN", "FREQ"])),
    "singular WCS": dict(wcs=_wcs(cd=np.zeros((2, 2)))),
    "non-finite WCS": dict(wcs=_wcs(crval=[np.nan, -10.0])),
    "even image PSF": dict(psf=galsim.Image(np.ones((4, 4)))),
    "non-finite image PSF": dict(psf=galsim.Image(np.full((5, 5), np.nan))),
    "zero image PSF": dict(psf=galsim.Image(np.zeros((5, 5)))),
    "array as PSF": dict(psf=np.ones((5, 5))),
    "huge zero point": dict(zero_point=1e6),
    "tiny zero point": dict(zero_point=-1e6),
    "NaN zero point": dict(zero_point=float("nan")),
    "text zero point": dict(zero_point="30"),
    "fractional visit": dict(visit=1.5),
    "control character in band": dict(band="r\n"),
    "empty band": dict(band=""),
    "variance of another shape": dict(variance=np.ones((3, 3))),
    "text variance": dict(variance="high"),
    "valid box outside the image": dict(valid_box=Box(x_start=0, x_stop=50, y_start=0, y_stop=9)),
}


@pytest.mark.parametrize("case", REFUSED)
def test_malformed_exposures_are_refused_at_construction(case):
    with pytest.raises(ExposureError, match=r"exposure \(visit=\S+, detector=2\): "):
        Exposure(**{**_kwargs(), **REFUSED[case]})


# ------------------------------------------------------------ inputs rejected, cell by cell


def _raising(x: float, y: float) -> galsim.GSObject:
    raise RuntimeError("PSF model unavailable here")


def _returns_even_image(x: float, y: float) -> galsim.Image:
    return galsim.Image(np.ones((4, 4)))


def _returns_nan_flux(x: float, y: float) -> galsim.GSObject:
    return galsim.Gaussian(sigma=0.4).withFlux(float("nan"))


def _returns_zero_flux(x: float, y: float) -> galsim.GSObject:
    return galsim.Gaussian(sigma=0.4, flux=0.0)


def _returns_nan_image(x: float, y: float) -> galsim.GSObject:
    return galsim.InterpolatedImage(galsim.Image(np.full((9, 9), np.nan), scale=0.2))


def _returns_huge(x: float, y: float) -> galsim.GSObject:
    return galsim.Gaussian(sigma=1e5)


def _bad_inputs(good: Exposure) -> dict[int, tuple[str, Exposure]]:
    """Valid exposures over the whole patch that every cell must reject: visit -> (reason,
    exposure)."""
    shape = good.shape
    grid = np.zeros(shape, bool)
    grid[::4, ::4] = True
    intrp = good.mask_bits.value("INTRP")  # a bit the build does not treat as bad
    variants = {
        "bad_weight": [
            dict(variance=0.0),
            dict(variance=-1.0),
            dict(variance=np.where(grid, 0.0, 1.0)),
            dict(variance=np.where(grid, np.nan, 1.0)),
            dict(zero_point=99.0),  # noise scaled below float32 range
            dict(zero_point=-49.0),  # and above it
        ],
        "bad_pixels": [dict(image=np.where(grid, np.nan, good.image), mask=grid * intrp)],
        "bad_psf": [
            dict(psf=GalSimPsf(psf))
            for psf in (
                _raising,
                _returns_even_image,
                _returns_nan_flux,
                _returns_zero_flux,
                _returns_nan_image,
                _returns_huge,
            )
        ],
    }
    out = {}
    for reason, changes in variants.items():
        for change in changes:
            visit = 100 + len(out)
            out[visit] = (reason, dataclasses.replace(good, visit=visit, **change))
    return out


@pytest.mark.filterwarnings("ignore::galsim.GalSimFFTSizeWarning")
def test_bad_inputs_are_rejected_and_change_nothing(tiny):
    patch, good, reference = tiny
    bad = _bad_inputs(good[0])
    far = make_exposure((210.0, 10.0), visit=300)  # on the other side of the sky
    built = build_patch(
        patch, [*good, *(e for _, e in bad.values()), far], TINY_BUILD, seed=1, progress=False
    )
    for index, cell in built.items():
        statuses = {record.visit: record.status for record in cell.inputs}
        assert statuses == {0: "used", 1: "used", **{v: r for v, (r, _) in bad.items()}}, index
        expected = reference[index]
        assert [r for r in cell.inputs if r.visit < 2] == expected.inputs
        # rejected inputs contribute nothing: the cell is bit-identical to the clean build
        for plane in ("image", "noise", "variance", "mfrac", "mask", "psf"):
            np.testing.assert_array_equal(getattr(cell, plane), getattr(expected, plane))


def test_masked_non_finite_pixels_are_used_without_spreading(tiny):
    patch, good, _ = tiny
    holes = good[0].image.copy()
    mask = good[0].mask.copy()
    holes[50:53, 50:60] = [[np.nan], [np.inf], [-np.inf]]
    mask[50:53, 50:60] = good[0].mask_bits.value("BAD")
    variance = np.where(np.isfinite(holes), 1.0, np.nan)  # unknown where the pixels are
    exposure = dataclasses.replace(good[0], image=holes, mask=mask, variance=variance)
    built = build_patch(patch, [exposure, good[1]], TINY_BUILD, progress=False)
    for cell in built.values():
        assert [r.status for r in cell.inputs] == ["used", "used"]
        for plane in (cell.image, cell.noise, cell.variance, cell.mfrac):
            assert np.isfinite(plane).all()
    assert max(cell.mfrac.max() for cell in built.values()) > 0.0  # the holes are recorded


def test_a_cell_falling_off_the_exposure_projection_is_an_edge(tiny, monkeypatch):
    """A WCS whose inverse fails inside the cell (NaN positions) gives an ``edge`` rejection
    instead of stopping the build. No grid then maps the patch into the exposure, so each
    cell maps itself (and finds the NaN)."""
    patch, good, reference = tiny
    broken = dataclasses.replace(good[0], visit=7)
    original = select_module.map_box
    original_grid = frame_module.grid_mapping

    def no_grid(coadd_wcs, box, exposure_wcs, *args, **options):
        if exposure_wcs is broken.wcs:
            return None
        return original_grid(coadd_wcs, box, exposure_wcs, *args, **options)

    def partly_unmappable(coadd_wcs, box, exposure_wcs, **options):
        mapping = original(coadd_wcs, box, exposure_wcs, **options)
        if exposure_wcs is not broken.wcs:
            return mapping
        x = mapping.x.copy()
        x[x.shape[0] // 2, x.shape[1] // 2] = np.nan
        return dataclasses.replace(mapping, x=x)

    monkeypatch.setattr(select_module, "map_box", partly_unmappable)
    monkeypatch.setattr(frame_module, "grid_mapping", no_grid)
    built = build_patch(patch, [*good, broken], TINY_BUILD, seed=1, progress=False)
    for index, cell in built.items():
        assert [r.status for r in cell.inputs] == ["used", "used", "edge"]
        np.testing.assert_array_equal(cell.image, reference[index].image)


@pytest.mark.parametrize(
    "psf",
    [_raising, _returns_even_image, _returns_nan_flux, _returns_huge],
    ids=lambda f: f.__name__,
)
def test_exposure_whose_psf_cannot_be_stored_is_refused(tmp_path, tiny, psf):
    exposure = dataclasses.replace(tiny[1][0], psf=GalSimPsf(psf))
    with pytest.raises(ExposureError, match=r"visit=0, detector=0\): its PSF cannot be stored"):
        write_exposure(exposure, tmp_path / "exposure.fits")
    assert os.listdir(tmp_path) == []


def test_inputs_that_cannot_share_a_patch_are_refused(tiny):
    patch, good, _ = tiny
    with pytest.raises(ValueError, match=r"duplicate input \(visit, detector\) = \(1, 0\)"):
        build_patch(patch, [*good, dataclasses.replace(good[0], visit=1)], progress=False)
    with pytest.raises(ValueError, match="several bands"):
        build_patch(patch, [good[0], dataclasses.replace(good[1], band="g")], progress=False)
    spaced = [dataclasses.replace(e, band="r ") for e in good]
    with pytest.raises(ValueError, match="cannot be recorded"):
        build_patch(patch, spaced, progress=False)
    with pytest.raises(ValueError, match="at least one exposure"):
        build_patch(patch, [], progress=False)
