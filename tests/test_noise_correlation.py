"""Correlated coadd noise from a cell's realizations: correlation, power, weighted variances."""

from __future__ import annotations

import galsim
import numpy as np
import pytest
from exposure_factory import make_exposure

from cellcoadd import BuildConfig, SkyMap, SkyMapConfig, build_cell
from cellcoadd.shear import (
    gaussian_weight,
    noise_correlation,
    noise_covariance,
    noise_power_spectrum,
    snr_correction,
    variance_factor,
    weighted_flux_variance,
)

CONFIG = SkyMapConfig(cell_inner=100, cell_border=20, cells_per_patch=2, patches_per_tract=1)
K = 32  # noise realizations (>= 8; more make the empirical checks tighter)
SIGMA_PIX = 2.5  # Gaussian weight (pixels): about metadetect's wmom fwhm = 1.2 arcsec


@pytest.fixture(scope="module")
def coadd():
    cell = SkyMap.from_centers([(30.0, -10.0)], CONFIG)[0].cell(1, 0)
    exposures = [
        make_exposure(
            cell.center_sky,
            shape=(180, 180),
            pixel_scale=0.26,
            rotation_deg=rotation,
            offset=offset,
            psf=galsim.Moffat(beta=3.5, fwhm=0.9),
            noise_sigma=1.0,
            visit=visit,
            seed=visit,
        )
        for visit, (rotation, offset) in enumerate(
            [(0.0, (0.3, -0.2)), (30.0, (-0.1, 0.4)), (-65.0, (0.2, 0.1)), (120.0, (0.45, 0.3))]
        )
    ]
    return build_cell(cell, exposures, BuildConfig(n_noise=K, psf_size=25), seed=11)


def test_lag_one_correlation_matches_a_direct_estimate(coadd):
    noise = np.asarray(coadd.inner.noise, dtype=np.float64)
    rho = noise_correlation(coadd, max_lag=2)
    assert rho.shape == (5, 5) and rho[2, 2] == 1.0
    variance = np.mean(noise**2)
    along_x = np.mean(noise[:, :, :-1] * noise[:, :, 1:]) / variance
    along_y = np.mean(noise[:, :-1, :] * noise[:, 1:, :]) / variance
    diagonal = np.mean(noise[:, :-1, :-1] * noise[:, 1:, 1:]) / variance
    assert rho[2, 3] == pytest.approx(along_x, abs=1e-12)
    assert rho[2, 1] == pytest.approx(along_x, abs=1e-12)  # point symmetry
    assert rho[3, 2] == pytest.approx(along_y, abs=1e-12)
    assert rho[3, 3] == pytest.approx(diagonal, abs=1e-12)
    # resampling 0.26" pixels onto 0.2" ones correlates neighbours strongly
    assert 0.25 < along_x < 0.55 and 0.25 < along_y < 0.55
    covariance = noise_covariance(coadd, max_lag=2)
    assert covariance[2, 2] == pytest.approx(variance, rel=1e-12)
    np.testing.assert_allclose(covariance / covariance[2, 2], rho, atol=1e-12)


def test_power_spectrum_is_the_transform_of_the_covariance(coadd):
    power = noise_power_spectrum(coadd)
    noise = np.asarray(coadd.inner.noise, dtype=np.float64)
    assert power.shape == noise.shape[1:] and np.all(power >= 0.0)
    assert power.mean() == pytest.approx(np.mean(noise**2), rel=1e-12)
    # its inverse transform is the circular autocovariance: at lag 1 it agrees with the
    # (non-circular) estimate up to the wrapped pairs (1 in 100 columns)
    circular = np.fft.ifft2(power).real
    lag1 = noise_covariance(coadd, max_lag=1)[1, 2]
    assert circular[0, 1] == pytest.approx(lag1, rel=0.03)
    # correlated noise is red: less power at the highest frequencies than at the lowest
    ny, nx = power.shape
    assert power[ny // 2, nx // 2] < 0.3 * power[:3, :3].mean()


def test_weighted_flux_variance_matches_the_realizations(coadd):
    weight = gaussian_weight(SIGMA_PIX)
    size = weight.shape[0]
    predicted = weighted_flux_variance(coadd, weight, max_lag=12)
    noise = np.asarray(coadd.inner.noise, dtype=np.float64)
    n = noise.shape[1] // size
    # sum(w n) over non-overlapping stamps of every realization: independent samples
    fluxes = np.array(
        [
            np.sum(weight * plane[i * size : (i + 1) * size, j * size : (j + 1) * size])
            for plane in noise
            for i in range(n)
            for j in range(n)
        ]
    )
    empirical = np.mean(fluxes**2)  # zero-mean noise
    error = empirical * np.sqrt(2.0 / fluxes.size)
    assert fluxes.size >= 100
    assert abs(predicted - empirical) < 3.0 * error, (predicted, empirical, error)
    # the weight map's white-noise value is far off
    white = np.mean(noise**2) * np.sum(weight**2)
    assert abs(white - empirical) > 4.0 * error
    factor = variance_factor(coadd, weight, max_lag=12)
    assert factor == pytest.approx(predicted / white, rel=1e-12)
    assert 1.5 < factor < 2.5
    assert snr_correction(coadd, SIGMA_PIX, max_lag=12) == pytest.approx(np.sqrt(factor))
    # the covariance has died out by the default lag: a larger one changes nothing
    assert weighted_flux_variance(coadd, weight) == pytest.approx(predicted, rel=0.01)


def test_a_single_pixel_weight_gives_the_pixel_variance(coadd):
    noise = np.asarray(coadd.inner.noise, dtype=np.float64)
    assert weighted_flux_variance(coadd, [[2.0]]) == pytest.approx(4.0 * np.mean(noise**2))
    assert variance_factor(coadd, [[1.0]]) == pytest.approx(1.0)


def test_white_noise_has_no_correlation_and_factor_one():
    rng = np.random.default_rng(5)
    white = rng.normal(0.0, 3.0, (K, 120, 120))
    rho = noise_correlation(white, max_lag=3)
    off_centre = np.delete(rho.ravel(), rho.size // 2)
    assert np.max(np.abs(off_centre)) < 5.0 / np.sqrt(white.size)
    assert variance_factor(white, gaussian_weight(SIGMA_PIX)) == pytest.approx(1.0, abs=0.03)
    assert snr_correction(white, SIGMA_PIX) == pytest.approx(1.0, abs=0.015)
    power = noise_power_spectrum(white)
    assert power.mean() == pytest.approx(9.0, rel=0.01)
    # flat: no trend from low to high frequency beyond the scatter
    ny, nx = power.shape
    assert power[ny // 4 : 3 * ny // 4, nx // 4 : 3 * nx // 4].mean() == pytest.approx(
        9.0, rel=0.03
    )


def test_single_image_and_arguments(coadd):
    plane = np.asarray(coadd.inner.noise[0], dtype=np.float64)
    np.testing.assert_allclose(noise_correlation(plane, 1), noise_correlation(plane[None], 1))
    with pytest.raises(ValueError, match="max_lag"):
        noise_correlation(coadd, max_lag=coadd.inner.noise.shape[-1])
    with pytest.raises(ValueError, match="shape"):
        noise_correlation(np.zeros((2, 3, 4, 5)))
    with pytest.raises(ValueError, match="non-finite"):
        noise_correlation(np.full((1, 8, 8), np.nan))
    with pytest.raises(ValueError, match="zero everywhere"):
        weighted_flux_variance(coadd, np.zeros((5, 5)))
    with pytest.raises(ValueError, match="sigma_pix"):
        snr_correction(coadd, 0.0)


def test_a_cell_without_realizations_is_refused(coadd):
    cell = SkyMap.from_centers([(30.0, -10.0)], CONFIG)[0].cell(1, 0)
    exposure = make_exposure(cell.center_sky, shape=(180, 180), noise_sigma=1.0)
    no_noise = build_cell(cell, [exposure], BuildConfig(n_noise=0, psf_size=25))
    with pytest.raises(ValueError, match="n_noise"):
        noise_correlation(no_noise)
