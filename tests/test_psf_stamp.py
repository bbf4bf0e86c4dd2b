"""The coadd PSF stamp: its default size, the flux it leaves out, recorded and warned of."""

from __future__ import annotations

import warnings

import galsim
import numpy as np
import pytest
from conftest import DES_PSF
from exposure_factory import make_exposure

from cellcoadd import BuildConfig, SkyMap, SkyMapConfig, build_cell, build_patch
from cellcoadd.errors import ConfigError, PsfStampWarning
from cellcoadd.geometry.box import Box
from cellcoadd.model.build_config import DEFAULT_PSF_SIZE
from cellcoadd.model.patch_coadd import FORMAT_VERSION
from cellcoadd.pipelines.validation.validation_settings import ValidationSettings

COADD_SCALE = 0.2
EXPOSURE_SCALE = 0.26
DECAM_SCALE = 0.263
# a default-sized cell (outer box 250 px) and a small one (outer box 60 px)
BIG = SkyMapConfig(cell_inner=150, cell_border=50, cells_per_patch=1, patches_per_tract=1)
SMALL = SkyMapConfig(cell_inner=40, cell_border=10, cells_per_patch=2, patches_per_tract=1)

# GalSim's default folding threshold (5e-3) folds ~1e-4 of a Kolmogorov PSF's wing flux
# back into a drawn stamp, in the builder's drawings and in the expected values alike
ACCURATE = galsim.GSParams(folding_threshold=2e-5, maximum_fft_size=16384)
KOLMOGOROV = galsim.Kolmogorov(fwhm=0.7, gsparams=ACCURATE)
KOLMOGOROV_AIRY = galsim.Convolve(
    galsim.Kolmogorov(fwhm=0.7), galsim.Airy(lam=700.0, diam=8.4, obscuration=0.4)
).withGSParams(ACCURATE)
MOFFAT = galsim.Moffat(beta=3.5, fwhm=1.15)  # the simulator's widest PSF


def _inside_by_integration(psf: galsim.GSObject, size: int) -> float:
    """Flux of ``psf`` convolved with the exposure pixel inside a centred ``size`` x
    ``size`` box of coadd pixels (drawn with the coadd pixel, i.e. integrated over each)."""
    profile = galsim.Convolve(psf, galsim.Pixel(EXPOSURE_SCALE))
    image = profile.drawImage(nx=size, ny=size, scale=COADD_SCALE, method="fft")
    return float(image.array.sum())


def _build(config: SkyMapConfig, psf: galsim.GSObject, psf_size: int | None, n: int = 3):
    tract = SkyMap.from_centers([(30.0, -10.0)], config)[0]
    cell = tract.cell(0, 0)
    ra, dec = cell.center_sky
    side = int(1.45 * config.cell_outer * COADD_SCALE / EXPOSURE_SCALE) + 24  # rotated
    exposures = [
        make_exposure(
            (ra, dec),
            shape=(side, side),
            pixel_scale=EXPOSURE_SCALE,
            rotation_deg=20.0 * k,
            offset=(0.1 * k, -0.3 * k),
            psf=psf,
            visit=k,
            detector=k + 1,
        )  # fmt: skip
        for k in range(n)
    ]
    build = BuildConfig(n_noise=1, psf_size=psf_size)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        coadd = build_cell(cell, exposures, build)
    return coadd, [w for w in caught if issubclass(w.category, PsfStampWarning)]


@pytest.mark.parametrize(
    ("psf", "size"), [(KOLMOGOROV, 35), (KOLMOGOROV_AIRY, 35), (KOLMOGOROV, 75), (MOFFAT, 35)]
)
def test_flux_outside_the_stamp_is_measured_and_warned_of(psf, size):
    """Each used input records the flux its PSF loses outside the stamp, which matches
    GalSim's integral of the same profile over the stamp to 5e-5 (measured: <= 1.5e-5;
    it is counted in the exposure's pixels over the stamp's area, not from the resampled
    stamp's sum, which resampling changes by ~1e-4); the cell's value is their weighted
    mean and a build warns, naming the cell, above 1e-4."""
    coadd, caught = _build(BIG, psf, size)
    assert coadd.psf.shape == (size, size) and coadd.n_used == 3
    expected = 1.0 - _inside_by_integration(psf, size)
    assert expected > 1e-3  # these stamps really do cut the PSF
    for record in coadd.inputs:
        assert record.psf_flux_outside == pytest.approx(expected, abs=5e-5)
    assert coadd.psf_flux_outside == pytest.approx(expected, abs=5e-5)
    assert coadd.psf.sum() == pytest.approx(1.0, abs=1e-12)  # renormalised all the same
    assert len(caught) == 1
    message = str(caught[0].message)
    assert f"{size}-pixel PSF stamp" in message and "cell (0, 0) of tract 0" in message


def test_default_stamp_holds_the_simulators_psf():
    """Left out, psf_size is DEFAULT_PSF_SIZE (75) on default cells: the simulator's
    widest Moffat then loses < 1e-4 and no warning is given; Kolmogorov + Airy still
    loses ~2e-3 there, and is warned of."""
    coadd, caught = _build(BIG, MOFFAT, None)
    assert coadd.psf.shape == (DEFAULT_PSF_SIZE, DEFAULT_PSF_SIZE)
    assert 0.0 < coadd.psf_flux_outside < 1e-4 and not caught
    coadd, caught = _build(BIG, KOLMOGOROV_AIRY, None)
    assert 1e-3 < coadd.psf_flux_outside < 3e-3 and len(caught) == 1


def test_default_stamp_fits_a_small_cell_and_the_patch_records_its_size():
    """On cells whose outer box is smaller than the default the stamp is the largest odd
    size the box holds, the size the patch's metadata records."""
    tract = SkyMap.from_centers([(30.0, -10.0)], SMALL)[0]
    patch = tract.patch(0, 0)
    box = patch.outer_bbox
    ra, dec = (float(v) for v in tract.wcs.pixel_to_world_values(
        (box.x_start + box.x_stop - 1) / 2, (box.y_start + box.y_stop - 1) / 2))  # fmt: skip
    exposures = [
        make_exposure((ra, dec), shape=(200, 200), pixel_scale=EXPOSURE_SCALE, psf=MOFFAT,
                      visit=k, detector=1)
        for k in range(2)
    ]  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PsfStampWarning)
        coadd = build_patch(patch, exposures, BuildConfig(n_noise=1), seed=1)
    assert coadd.metadata.build_config.psf_size == 59 == coadd.metadata.psf_size
    assert {c.psf.shape for c in coadd.cells.values()} == {(59, 59)}


def test_resolution_rules():
    assert BuildConfig().psf_size is None
    assert BuildConfig().resolved(250).psf_size == DEFAULT_PSF_SIZE
    assert BuildConfig().resolved(60).psf_size == 59
    assert BuildConfig().resolved(61).psf_size == 61
    assert BuildConfig(psf_size=35).resolved(20).psf_size == 35  # an explicit size stays
    with pytest.raises(ConfigError, match="psf_size is not set"):
        _ = BuildConfig().stamp_size
    # the validation's stamp cell (41 + 2 x 5 px) gets a 51-pixel stamp, kept through JSON
    settings = ValidationSettings()
    assert settings.build.psf_size == 51
    assert ValidationSettings.model_validate_json(settings.model_dump_json()) == settings
    assert ValidationSettings(build=BuildConfig(n_noise=2, psf_size=35)).build.psf_size == 35


def test_flux_outside_round_trips_and_old_tables_read_as_nan(tmp_path):
    """The recorded fractions survive both formats bit for bit; an inputs table without
    the column (files before format 1.3) reads as NaN."""
    from numpy.lib import recfunctions

    from cellcoadd.io import api
    from cellcoadd.io.coadd.inputs_table import inputs_from_array, inputs_to_array

    tract = SkyMap.from_centers([(30.0, -10.0)], SMALL)[0]
    patch = tract.patch(0, 0)
    box = patch.outer_bbox
    ra, dec = (float(v) for v in tract.wcs.pixel_to_world_values(
        (box.x_start + box.x_stop - 1) / 2, (box.y_start + box.y_stop - 1) / 2))  # fmt: skip
    exposures = [
        make_exposure((ra, dec), shape=(200, 200), pixel_scale=EXPOSURE_SCALE,
                      psf=KOLMOGOROV, visit=k, detector=3, rotation_deg=31.0 * k)
        for k in range(2)
    ]  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PsfStampWarning)
        coadd = build_patch(patch, exposures, BuildConfig(n_noise=1, psf_size=31), seed=2)
    values = [r.psf_flux_outside for c in coadd.cells.values() for r in c.inputs if r.is_used]
    assert values and all(2e-3 < v < 2e-2 for v in values)
    for name in ("patch.fits", "patch.h5"):
        back = api.read(api.write(coadd, tmp_path / name) or tmp_path / name)
        assert back.metadata.format_version == FORMAT_VERSION
        for index, cell in coadd.cells.items():
            pairs = zip(cell.inputs, back.cells[index].inputs, strict=True)
            assert all(a.identical(b) for a, b in pairs)
            assert back.cells[index].psf_flux_outside == cell.psf_flux_outside
    records = next(c.inputs for c in coadd.cells.values() if c.n_used)
    table = inputs_to_array(records, ascii_only=True)
    old = recfunctions.drop_fields(table, "psf_flux_outside", usemask=False)
    for old_record, record in zip(inputs_from_array(old, ascii_only=True), records, strict=True):
        assert np.isnan(old_record.psf_flux_outside)
        assert old_record.weight == record.weight and old_record.psf_T == record.psf_T


def _psfex_cell(rotate: bool, psf_size: int):
    """A cell of 0.2" (rotated) or 0.263" (the exposures' grid) pixels coadded from 4
    exposures of the real DECam PSFEx model (25 x 25 samples: ~15 px of support), at
    varied sub-pixel phases and places of the CCD."""
    import math

    from astropy.wcs import WCS

    from cellcoadd.io import read_psfex
    from cellcoadd.model.exposure import Exposure

    scale = COADD_SCALE if rotate else DECAM_SCALE
    config = SkyMapConfig(
        pixel_scale=scale, cell_inner=150, cell_border=50, cells_per_patch=1, patches_per_tract=1
    )
    cell = SkyMap.from_centers([(60.0, -30.0)], config)[0].cell(0, 0)
    model = read_psfex(DES_PSF)
    exposures = []
    for k in range(4):
        if rotate:
            wcs = WCS(naxis=2)
            wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
            wcs.wcs.crval = list(cell.center_sky)
            wcs.wcs.crpix = [251.0 + 0.37 * k, 251.0 - 0.21 * k]
            c, s = math.cos(math.radians(23.0 * k)), math.sin(math.radians(23.0 * k))
            wcs.wcs.cd = np.array([[-c, s], [s, c]]) * DECAM_SCALE / 3600.0
        else:  # exposure pixel (i, j) = cell pixel (i - dx, j - dy): no resampling
            wcs = cell.wcs.deepcopy()
            wcs.wcs.crpix = wcs.wcs.crpix + np.array([125.0 + 3 * k, 125.0 - 2 * k])
        wcs.wcs.set()
        exposures.append(
            Exposure(
                image=np.zeros((500, 500)),
                wcs=wcs,
                variance=1.0,
                psf=model,
                visit=k,
                detector=12,
                band="r",
                zero_point=30.0,
                origin=(1000 + 97 * k, 1500 - 61 * k),
            )  # fmt: skip
        )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        coadd = build_cell(cell, exposures, BuildConfig(n_noise=0, psf_size=psf_size))
    assert coadd.n_used == 4
    return coadd, exposures, [w for w in caught if issubclass(w.category, PsfStampWarning)]


def test_a_psfex_model_records_its_own_flux_beyond_the_stamp():
    """The DECam PSFEx model has no flux beyond ~15 px (its own support: PSFEx models a
    circle of 12.5 samples, the hard edge of the stored cell PSF at r ~ 12 px, plus
    Lanczos-3's reach), so a 75-pixel stamp holds all of it: psf_flux_outside is 0 to
    1e-5 and no warning is given. It used to record up to 6.5e-3 (either sign), the
    phase-dependent sum of PSFEx's resampled grid (~0.5%) and resampling's own error."""
    coadd, _, caught = _psfex_cell(rotate=True, psf_size=75)
    for record in coadd.inputs:
        assert abs(record.psf_flux_outside) <= 1e-5, record
    assert abs(coadd.psf_flux_outside) <= 1e-5 and not caught
    # a stamp smaller than the model (7 px on the exposures' grid, no resampling): what
    # it lacks is the model's flux outside those pixels, counted on the model's drawing
    coadd, exposures, caught = _psfex_cell(rotate=False, psf_size=15)
    ny, nx = coadd.outer_bbox.shape
    for record, exposure in zip(coadd.inputs, exposures, strict=True):
        sky = coadd.wcs.pixel_to_world_values(nx // 2, ny // 2)
        x, y = (float(v) for v in exposure.wcs.world_to_pixel_values(*sky))
        i, j = round(x), round(y)
        whole = exposure.draw_psf(x, y, Box(x_start=i - 40, x_stop=i + 41,
                                            y_start=j - 40, y_stop=j + 41))  # fmt: skip
        inside = whole[40 - 7 : 40 + 8, 40 - 7 : 40 + 8].sum() / whole.sum()
        assert 1e-2 < 1.0 - inside < 0.1
        assert record.psf_flux_outside == pytest.approx(1.0 - inside, abs=1e-5)
    assert len(caught) == 1
