"""Masks and noise as surveys have them: bad pixels interpolated (not zero-filled), bit
maps matched by name, noise realizations from the background variance."""

from __future__ import annotations

import dataclasses

import galsim
import numpy as np
import pytest
from exposure_factory import make_exposure

from cellcoadd import BuildConfig, MaskBits, SkyMap, SkyMapConfig, build_cell, build_patch
from cellcoadd.errors import InputError

SKY = SkyMapConfig(
    pixel_scale=0.2, cell_inner=40, cell_border=10, cells_per_patch=2, patches_per_tract=2
)
# counts at the inputs' zero point 30, so pixel values compare with the inputs' as is
BUILD = BuildConfig(n_noise=2, psf_size=21, units="count", zero_point=30.0)
# DES single-epoch bad-pixel bit names (DESDM's BADPIX_* values as bit indices)
DES_BITS = MaskBits(
    bits={
        "BADPIX_BPM": 0,
        "BADPIX_SATURATE": 1,
        "BADPIX_INTERP": 2,
        "BADPIX_BADAMP": 3,
        "BADPIX_CRAY": 4,
        "BADPIX_STAR": 5,
        "BADPIX_TRAIL": 6,
        "BADPIX_EDGEBLEED": 7,
        "BADPIX_SSXTALK": 8,
        "BADPIX_EDGE": 9,
        "BADPIX_STREAK": 10,
        "BADPIX_SUSPECT": 11,
    }
)
DES_BAD = ("BADPIX_BPM", "BADPIX_SATURATE", "BADPIX_CRAY", "BADPIX_EDGE", "BADPIX_STREAK")


@pytest.fixture(scope="module")
def cell():
    return SkyMap.from_centers([(30.0, -10.0)], SKY)[0].cell(1, 1)


def _with_mask(exposure, mask, mask_bits=None):
    return dataclasses.replace(exposure, mask=mask, mask_bits=mask_bits or exposure.mask_bits)


def _random_bad_mask(shape, seed, value, fraction=0.02):
    """Scattered bad pixels, a bad column and a small hole."""
    rng = np.random.default_rng(seed)
    mask = np.where(rng.random(shape) < fraction, value, 0).astype(np.int32)
    mask[:, 70 + seed] |= value
    mask[60:66, 90:97] |= value
    return mask


def test_constant_sky_stays_constant_where_inputs_are_masked(cell):
    sky = 57.83
    sat = MaskBits().value("SAT")
    exposures = [
        _with_mask(
            make_exposure(
                cell.center_sky, sky=sky, visit=k, rotation_deg=17.0 * k, pixel_scale=0.2
            ),
            _random_bad_mask((160, 160), k, sat) if k == 0 else None,
        )
        for k in range(4)
    ]
    coadd = build_cell(cell, exposures, BUILD)
    assert coadd.n_used == 4
    touched = coadd.mfrac > 0
    assert touched.mean() > 0.05  # the masked input reached many coadd pixels
    np.testing.assert_allclose(coadd.image, sky, rtol=1e-6)
    # one input of four (equal weights) was masked: a quarter, up to the Lanczos overshoot
    assert coadd.mfrac.max() <= 0.25 * 1.3


def test_star_away_from_masked_pixels_equals_the_psf(cell):
    x0, y0 = cell.center_sky
    star = [(x0, y0, galsim.DeltaFunction(flux=1e4))]
    sat = MaskBits().value("CR")
    exposures = []
    for k in range(3):
        exposure = make_exposure(cell.center_sky, sources=star, visit=k, offset=(0.3 * k, 0.1))
        mask = np.zeros(exposure.shape, dtype=np.int32)
        mask[10:20, 10:30] = sat  # far from the star
        exposures.append(_with_mask(exposure, mask))
    coadd = build_cell(cell, exposures, BUILD)
    ny, nx = coadd.image.shape
    half = BUILD.psf_size // 2
    stamp = coadd.image[ny // 2 - half : ny // 2 + half + 1, nx // 2 - half : nx // 2 + half + 1]
    stamp = stamp / stamp.sum()
    assert np.abs(stamp - coadd.psf).max() < 1e-3 * coadd.psf.max()


def test_noise_realizations_match_the_image_noise_where_interpolated(cell):
    """Pure-noise exposures with bad pixels: inside the interpolated footprint the coadd
    image and a noise realization have the same variance (both got the same weights)."""
    sigma = 2.0
    cr = MaskBits().value("CR")
    exposures = [
        _with_mask(
            make_exposure(cell.center_sky, noise_sigma=sigma, seed=100 + k, visit=k),
            _random_bad_mask((160, 160), k, cr, fraction=0.05),
        )
        for k in range(3)
    ]
    coadd = build_cell(cell, exposures, BuildConfig(n_noise=4, psf_size=21))
    interpolated = coadd.mfrac > 0.02
    assert interpolated.sum() > 500
    image_var = coadd.image[interpolated].var()
    noise_var = coadd.noise[:, interpolated].var(axis=1)
    # pixels are correlated: allow the spread of a variance from ~N/10 independent values
    n_eff = interpolated.sum() / 10
    tolerance = 3 * image_var * np.sqrt(2 / n_eff)
    assert np.all(np.abs(noise_var - image_var) < tolerance + 3 * noise_var * np.sqrt(2 / n_eff))


def test_bits_are_translated_by_name(cell):
    ours = make_exposure(cell.center_sky, visit=1)
    des = make_exposure(cell.center_sky, visit=2, offset=(0.4, 0.2))
    des_mask = np.zeros(des.shape, dtype=np.int32)
    des_mask[80, 80] = DES_BITS.value("BADPIX_SATURATE")
    des_mask[70, 75] = DES_BITS.value("BADPIX_STAR")  # not bad: only labelled
    des = _with_mask(des, des_mask, DES_BITS)
    config = BuildConfig(
        n_noise=1, psf_size=21, bad_mask_bits=("SAT", "BADPIX_SATURATE"), optional_mask_bits=()
    )
    with pytest.raises(InputError, match=r"visit=1.*BADPIX_SATURATE"):
        build_cell(cell, [ours, des], config)
    config = config.model_copy(update={"optional_mask_bits": ("SAT", "BADPIX_SATURATE")})
    coadd = build_cell(cell, [ours, des], config)
    bits = MaskBits.union([ours.mask_bits, des.mask_bits])  # the map build_cell used
    assert {"BADPIX_SATURATE", "BADPIX_STAR", "SAT", "NO_DATA"} <= set(bits.bits)
    names = {name for value in np.unique(coadd.mask) for name in bits.names(int(value))}
    assert names == {"BADPIX_SATURATE", "BADPIX_STAR"}  # not SAT, INTRP...: DES's own names


def test_des_bit_names_with_default_config_are_refused_before_work(cell):
    des = _with_mask(make_exposure(cell.center_sky, visit=7, detector=12), None, DES_BITS)
    tract = SkyMap.from_centers([(30.0, -10.0)], SKY)[0]
    with pytest.raises(InputError, match=r"visit=7, detector=12.*\['BAD', 'SAT', 'CR'"):
        build_patch(tract.patch(0, 0), [des], BUILD, progress=False)


def test_cosmic_rays_are_not_coadded_with_des_bits(cell):
    sigma = 2.5
    exposures = []
    for k in range(4):
        exposure = make_exposure(cell.center_sky, noise_sigma=sigma, seed=k, visit=k)
        image = exposure.image.copy()
        mask = np.zeros(exposure.shape, dtype=np.int32)
        rng = np.random.default_rng(k)
        ys, xs = rng.integers(30, 130, size=(2, 60))
        image[ys, xs] += rng.uniform(50, 700, size=60) * sigma  # cosmic rays
        mask[ys, xs] = DES_BITS.value("BADPIX_CRAY")
        exposures.append(dataclasses.replace(exposure, image=image, mask=mask, mask_bits=DES_BITS))
    config = BuildConfig(n_noise=1, psf_size=21, bad_mask_bits=DES_BAD)
    coadd = build_cell(cell, exposures, config)
    noise_sigma = float(np.std(coadd.noise[0]))
    assert np.abs(coadd.image).max() < 6 * noise_sigma


def test_noise_realizations_carry_no_image_of_the_sources(cell):
    """LSST-style variance planes include the sources' Poisson noise; the realizations are
    drawn with the background variance, so a bright star leaves no trace in them."""
    background = 2.5**2
    star = [(cell.center_sky[0], cell.center_sky[1], galsim.Gaussian(sigma=0.5, flux=2e6))]
    exposures = []
    for k in range(4):
        exposure = make_exposure(cell.center_sky, sources=star, visit=k, offset=(0.25 * k, 0))
        variance = background + np.clip(exposure.image, 0, None)  # Poisson noise of the star
        exposures.append(dataclasses.replace(exposure, variance=variance))
    peak_variance = max(float(e.variance.max()) for e in exposures)
    assert peak_variance > 100 * background
    coadd = build_cell(cell, exposures, BuildConfig(n_noise=16, psf_size=21))
    ny, nx = coadd.image.shape
    centre = coadd.noise[:, ny // 2 - 2 : ny // 2 + 3, nx // 2 - 2 : nx // 2 + 3]
    far = coadd.noise[:, 5:25, 5:25]
    var_centre, var_far = centre.var(), far.var()
    n = centre.size / 4  # neighbouring coadd pixels correlate
    assert abs(var_centre - var_far) < 3 * var_far * np.sqrt(2 / n)
    # the old behaviour, still available, draws the star into the noise
    per_pixel = build_cell(
        cell, exposures, BuildConfig(n_noise=4, psf_size=21, noise_variance="pixel")
    )
    assert per_pixel.noise[:, ny // 2, nx // 2].var() > 20 * var_far
