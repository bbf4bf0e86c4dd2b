"""S/N from the noise's covariance: the true scatter of the weighted flux, the same S/N in
coadd, single-epoch and multi-epoch measurements; and the size cut of ``wmom`` shapes."""

from __future__ import annotations

import warnings

import galsim
import numpy as np
import pytest
from scipy import ndimage

from cellcoadd.pipelines.validation.stamp_pairs import measure_pair
from cellcoadd.pipelines.validation.validation_settings import ValidationSettings
from cellcoadd.shear import PAPER_CUTS, WMOM_CUTS, cuts_for_shape, measure_metacal
from cellcoadd.shear.noise_correlation import (
    covariance_flux_variance,
    metacal_noise_covariance,
    noise_covariance,
)
from cellcoadd.shear.shapes import gaussian_weight_image

SCALE = 0.2
JACOBIAN = np.array([[SCALE, 0.0], [0.0, SCALE]])
PSF = galsim.Moffat(beta=3.5, fwhm=0.8)


def test_flux_variance_from_the_covariance_matches_realizations():
    """sum_lag C(lag) R_W(lag), C measured on 200 realizations, is the variance of
    sum(W n) over many (noise smoothed by a 3x3 kernel: lag-1 correlation ~0.67)."""
    rng = np.random.default_rng(3)
    kernel = np.ones((3, 3)) / 9.0
    noise = np.array(
        [ndimage.convolve(rng.standard_normal((48, 48)), kernel, mode="wrap") for _ in range(3000)]
    )
    u, v = np.meshgrid(np.arange(48) - 23.5, np.arange(48) - 23.5)
    weight = gaussian_weight_image(u, v, np.eye(2) / 3.0**2)
    truth = float(np.var(np.einsum("kij,ij->k", noise, weight)))
    estimate = covariance_flux_variance(noise_covariance(noise[:200], 8), weight)
    white = float(np.mean(noise[:4] ** 2) * np.sum(weight**2))
    assert estimate == pytest.approx(truth, rel=0.06)
    assert truth / white > 5.0  # what a white-noise formula misses here


def test_metacal_snr_is_the_flux_over_its_true_scatter():
    """On a white-noise image, metacal's wmom S/N (flux / its error) is the flux over the
    scatter of the noshear flux across noise realizations: the reconvolution correlates
    the noise, and the S/N from the correction's covariance follows. (An adaptive
    weight's amplitude scatters more than a fixed weight's flux, so admom is left out.)"""
    shape = "wmom"
    image = (
        galsim.Convolve(galsim.Exponential(half_light_radius=0.5, flux=400.0), PSF)
        .drawImage(nx=48, ny=48, wcs=galsim.JacobianWCS(SCALE, 0.0, 0.0, SCALE))
        .array
    )
    psf_image = PSF.drawImage(nx=33, ny=33, scale=SCALE).array
    rng = np.random.default_rng(11)
    fluxes, errors = [], []
    for _ in range(80):
        noisy = image + rng.standard_normal(image.shape)
        own = rng.standard_normal(image.shape)
        record = measure_metacal(noisy, psf_image, own, JACOBIAN, 1.0, shape=shape)["noshear"]
        fluxes.append(float(record["flux"][0]))
        errors.append(float(record["flux"][0] / record["s2n"][0]))
    scatter = float(np.std(fluxes))
    assert np.median(errors) == pytest.approx(scatter, rel=0.15)


def test_metacal_noise_covariance_is_symmetrised():
    rng = np.random.default_rng(1)
    correction = ndimage.convolve(rng.standard_normal((60, 60)), np.ones((1, 3)) / 3.0)
    covariance = metacal_noise_covariance(correction, 4)
    np.testing.assert_allclose(covariance, np.rot90(covariance), rtol=0, atol=1e-12)
    np.testing.assert_allclose(covariance, covariance[::-1, ::-1], rtol=0, atol=1e-12)


def test_snr_is_the_same_in_coadd_single_and_multi_epoch_modes():
    """The same objects at the same optimal S/N (20) get the same measured S/N in every
    mode (it was 1.28 x the optimal on coadds against 0.76 jointly on the epochs and 0.84
    on one epoch, wmom): the same cut selects the same objects."""
    medians = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for mode in ("coadd", "multi-epoch", "single"):
            settings = ValidationSettings(
                mode=mode, method="metacal", seed=7, snr=(20.0, 20.0), shape="wmom"
            )
            pairs = [measure_pair(settings, i) for i in range(6)]
            medians[mode] = float(np.median([p.plus["noshear"]["s2n"][0] / 20.0 for p in pairs]))
    # metacal's noise correction doubles the noise variance: 1 / sqrt(2) of the optimal
    for mode, value in medians.items():
        assert value == pytest.approx(0.70, abs=0.06), (mode, medians)


def test_wmom_size_cut_sits_at_the_point_source_line():
    """In a fixed weight a star's T equals the PSF's: T/T_psf = 1, which the paper's 0.5
    keeps and the wmom cut (> 1) does not; a resolved galaxy passes both."""
    psf_image = PSF.drawImage(nx=33, ny=33, scale=SCALE).array
    wcs = galsim.JacobianWCS(SCALE, 0.0, 0.0, SCALE)
    star = PSF.drawImage(nx=48, ny=48, wcs=wcs).array * 1e4
    galaxy = (
        galsim.Convolve(galsim.Exponential(half_light_radius=0.4, flux=1e4), PSF)
        .drawImage(nx=48, ny=48, wcs=wcs)
        .array
    )
    for image, passes in ((star, False), (galaxy, True)):
        record = measure_metacal(image, psf_image, None, JACOBIAN, 1e-3, shape="wmom")["noshear"]
        ratio = float(record["T"][0] / record["T_psf"][0])
        assert (ratio > 1.05) is passes and ratio > 0.95
        assert bool(PAPER_CUTS(record)[0])
        assert bool(WMOM_CUTS(record)[0]) is passes or abs(ratio - 1.0) < 1e-2
    assert cuts_for_shape("wmom") is WMOM_CUTS and cuts_for_shape("admom") is PAPER_CUTS
