"""Exposures loaded on demand: sources described by headers, cut to each cell, one at a
time, with results equal to in-memory builds and identical for any executor."""

from __future__ import annotations

import dataclasses
import gc
import weakref

import galsim
import numpy as np
import pytest
from exposure_factory import make_exposure, make_wcs

from cellcoadd import BuildConfig, Exposure, MaskBits, SkyMap, SkyMapConfig, build_cell, build_patch
from cellcoadd.errors import ExposureError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.wcs_utils import canonical_wcs, shifted_wcs
from cellcoadd.model.sources import ExposureHeader, ExposureSource, cutout_box

SKY = SkyMapConfig(
    pixel_scale=0.2, cell_inner=40, cell_border=10, cells_per_patch=2, patches_per_tract=2
)
BUILD = BuildConfig(n_noise=2, psf_size=21)
ALIVE: set[int] = set()  # ids of loaded cutouts not yet freed (this process)
PEAK = [0]


class ArraySource(ExposureSource):
    """An in-memory exposure served like a file: header now, cutouts on demand."""

    def __init__(self, exposure: Exposure):
        self.exposure = exposure

    def header(self) -> ExposureHeader:
        e = self.exposure
        return ExposureHeader(
            visit=e.visit,
            detector=e.detector,
            band=e.band,
            wcs=e.wcs,
            shape=e.shape,
            valid_box=e.valid_box,
            zero_point=e.zero_point,
            mask_bits=e.mask_bits,
        )

    def load(self, box: Box | None = None) -> Exposure:
        e = self.exposure
        box = cutout_box(self.header(), box)
        valid = e.valid_box.intersection(box)
        variance = e.variance if np.isscalar(e.variance) else e.variance[box.slices]
        cut = Exposure(
            image=e.image[box.slices].copy(),
            wcs=shifted_wcs(e.wcs, box.x_start, box.y_start),
            variance=variance,
            psf=e.psf,
            visit=e.visit,
            detector=e.detector,
            band=e.band,
            zero_point=e.zero_point,
            mask=e.mask[box.slices].copy(),
            mask_bits=e.mask_bits,
            valid_box=valid.shifted(-box.x_start, -box.y_start),
            origin=(box.x_start, box.y_start),
        )
        ALIVE.add(id(cut))
        PEAK[0] = max(PEAK[0], len(ALIVE))
        weakref.finalize(cut, ALIVE.discard, id(cut))
        return cut


def _exposures(center, n=4):
    star = [(center[0], center[1], galsim.Gaussian(sigma=0.4, flux=5e4))]
    cr = MaskBits().value("CR")
    out = []
    for k in range(n):
        exposure = make_exposure(
            center,
            shape=(300, 260),
            sources=star,
            noise_sigma=1.0,
            seed=k,
            visit=k,
            rotation_deg=23.0 * k,
            offset=(0.3 * k, -0.2 * k),
            sip=k % 2 == 1,
        )
        mask = np.zeros(exposure.shape, dtype=np.int32)
        mask[100 + 7 * k, 40:200] = cr  # a bad row under the cells
        out.append(dataclasses.replace(exposure, mask=mask))
    return out


@pytest.fixture(scope="module")
def tract():
    return SkyMap.from_centers([(30.0, -10.0)], SKY)[0]


def test_sources_build_what_exposures_build(tract):
    cell = tract.cell(1, 1)
    exposures = _exposures(cell.center_sky)
    direct = build_cell(cell, exposures, BUILD, seed=3)
    from_sources = build_cell(cell, [ArraySource(e) for e in exposures], BUILD, seed=3)
    assert direct.n_used == from_sources.n_used == 4
    assert [r.status for r in direct.inputs] == [r.status for r in from_sources.inputs]
    scale = float(np.abs(direct.image).max())
    # cutouts shift the WCS reference pixel: the mapping differs by rounding only
    np.testing.assert_allclose(from_sources.image, direct.image, rtol=0, atol=1e-5 * scale)
    np.testing.assert_allclose(from_sources.noise, direct.noise, rtol=0, atol=1e-5)
    np.testing.assert_allclose(from_sources.psf, direct.psf, rtol=0, atol=1e-7)
    np.testing.assert_array_equal(from_sources.mask, direct.mask)
    np.testing.assert_allclose(from_sources.mfrac, direct.mfrac, rtol=0, atol=1e-6)


def test_a_cell_holds_one_loaded_exposure_at_a_time(tract):
    cell = tract.cell(1, 1)
    sources = [ArraySource(e) for e in _exposures(cell.center_sky, n=6)]
    gc.collect()
    PEAK[0] = len(ALIVE)
    build_cell(cell, sources, BUILD)
    assert PEAK[0] <= 2  # the one being added, and the next one while the first is freed


def test_patch_from_sources_is_identical_for_any_executor(tract):
    patch = tract.patch(0, 0)
    center = tract.pixel_to_sky([40.0], [40.0])
    sources = [ArraySource(e) for e in _exposures((float(center[0][0]), float(center[1][0])))]
    serial = build_patch(patch, sources, BUILD, seed=5, progress=False)
    pooled = build_patch(patch, sources, BUILD, seed=5, progress=False, workers=2)
    assert sum(c.n_used for c in serial.cells.values()) > 0
    for index, cell in serial.cells.items():
        assert cell.equals(pooled.cells[index]), index


def test_exposure_files_load_cutouts(tmp_path, tract):
    from cellcoadd.io import read_exposure, write_exposure
    from cellcoadd.io.exposures.exposure_source import ExposureFile

    cell = tract.cell(1, 1)
    exposure = _exposures(cell.center_sky, n=2)[1]  # SIP, rotated, a bad row
    exposure = dataclasses.replace(exposure, variance=np.full(exposure.shape, 1.5))
    path = write_exposure(exposure, tmp_path / "e.fits")
    source = ExposureFile(path)
    header = source.header()
    assert (header.key, header.shape, header.band) == (exposure.key, exposure.shape, "r")
    box = Box(x_start=40, x_stop=170, y_start=25, y_stop=230)
    cut, whole = source.load(box), read_exposure(path)
    assert cut.origin == (40, 25)
    np.testing.assert_array_equal(cut.image, whole.image[box.slices])
    np.testing.assert_array_equal(cut.mask, whole.mask[box.slices])
    np.testing.assert_array_equal(cut.variance, whole.variance[box.slices])
    x, y = np.array([0.0, 50.5, 120.0]), np.array([3.0, 199.0, 80.25])
    np.testing.assert_allclose(
        np.array(cut.wcs.all_pix2world(x, y, 0)),
        np.array(whole.wcs.all_pix2world(x + 40, y + 25, 0)),
        rtol=0,
        atol=1e-10,
    )
    # the cutout draws the PSF the whole exposure draws at the same detector pixel
    stamp = Box(x_start=60, x_stop=75, y_start=90, y_stop=105)
    np.testing.assert_allclose(
        cut.draw_psf(67.3 - 40, 97.6 - 25, stamp.shifted(-40, -25)),
        whole.draw_psf(67.3, 97.6, stamp),
        rtol=0,
        atol=1e-12,
    )
    # a cutout written and read again keeps its place on the detector
    again = read_exposure(write_exposure(cut, tmp_path / "cut.fits"))
    assert again.origin == (40, 25)


def test_replace_keeps_the_canonical_wcs_and_validates_the_rest():
    """Exposure.replace shares the (canonical) WCS instead of converting it again, gives
    what dataclasses.replace gives, converts a new WCS, and still validates every field."""
    exposure = make_exposure((30.0, -10.0), sip=True, rotation_deg=17.0, visit=3, detector=9)
    copy = exposure.replace(image=exposure.image + 1.0, detector=10)
    assert copy.wcs is exposure.wcs and copy.detector == 10
    reference = dataclasses.replace(exposure, image=exposure.image + 1.0, detector=10)
    assert copy.wcs.to_header_string(relax=True) == reference.wcs.to_header_string(relax=True)
    for name in ("crpix", "crval", "pc", "cdelt"):
        np.testing.assert_array_equal(getattr(copy.wcs.wcs, name), getattr(reference.wcs.wcs, name))
    np.testing.assert_array_equal(copy.wcs.sip.a, reference.wcs.sip.a)
    np.testing.assert_array_equal(
        copy.local_jacobian(20.5, 70.0), reference.local_jacobian(20.5, 70.0)
    )

    raw = make_wcs((30.0, -10.0), (160, 160), 0.26, rotation_deg=40.0, sip=True)
    moved = exposure.replace(wcs=raw)
    assert moved.wcs is not raw
    assert moved.wcs.to_header_string(relax=True) == canonical_wcs(raw).to_header_string(relax=True)
    with pytest.raises(ExposureError, match=r"visit=3, detector=9.*mask"):
        exposure.replace(mask=np.full((3, 3), 0, dtype=np.int32))
    with pytest.raises(ExposureError, match="non-finite"):
        exposure.replace(image=np.full(exposure.shape, np.nan))
