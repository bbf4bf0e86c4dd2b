"""Flux S/N loss of coadd fits versus joint multi-epoch fits (paper section 5.1, appendix A)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from cellcoadd.analysis import (
    continuous_gaussian_ratio,
    epoch_psf_sigmas,
    exact_ratio_curve,
    exact_variance_ratio,
    gaussian_templates,
    lsst_snr_loss,
    monte_carlo_ratio,
    toy_variance_ratio,
    variance_coadd,
    variance_multi,
)
from cellcoadd.analysis.gaussian_epochs import FWHM_PER_SIGMA, galaxy_sigma
from cellcoadd.cli.analyze import analyze
from cellcoadd.plots import plot_snr_loss


def _random_problem(seed: int, n_epochs: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    templates = rng.normal(size=(n_epochs, 5, 4)) + rng.uniform(0, 2)
    sigma = rng.uniform(0.2, 3.0, size=(n_epochs, 5, 4))
    weights = rng.uniform(0.05, 2.0, size=n_epochs)
    return templates, sigma, weights


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_epochs=st.integers(1, 6))
def test_exact_ratio_is_never_below_one(seed: int, n_epochs: int) -> None:
    # The coadd fit is a linear unbiased estimator; the joint fit is the best one.
    templates, sigma, weights = _random_problem(seed, n_epochs)
    assert exact_variance_ratio(templates, sigma, weights) >= 1.0 - 1e-12
    assert exact_variance_ratio(templates, sigma[:, 0, 0]) >= 1.0 - 1e-12
    assert exact_variance_ratio(templates) >= 1.0 - 1e-12


def test_variance_coadd_matches_the_linear_estimator_it_describes() -> None:
    # Var of A_coadd written as an explicit linear combination of every epoch's pixels,
    # a_i = (w_i / sum w) C_coadd^-1 m_coadd / norm, is sum_i a_i^T C_i a_i.
    templates, sigma, weights = _random_problem(3, 4)
    w = weights / weights.sum()
    m_coadd = np.tensordot(w, templates, axes=1)
    c_coadd = np.tensordot(w**2, sigma**2, axes=1)
    norm = np.sum(m_coadd**2 / c_coadd)
    coefficients = w[:, None, None] * (m_coadd / c_coadd)[None] / norm
    direct = np.sum(coefficients**2 * sigma**2)
    assert variance_coadd(templates, sigma, weights) == pytest.approx(direct, rel=1e-12)
    # And the joint fit is generalised least squares on the concatenated data.
    design = (templates / sigma).reshape(-1, 1)
    assert variance_multi(templates, sigma) == pytest.approx(
        float(np.linalg.inv(design.T @ design)[0, 0]), rel=1e-12
    )


def test_identical_templates_lose_nothing() -> None:
    template = gaussian_templates(0.3, n_epochs=1)[0]
    templates = np.repeat(template[None], 6, axis=0)
    assert exact_variance_ratio(templates) == pytest.approx(1.0, abs=1e-12)
    # Unequal noise: inverse-variance weights are optimal, other weights are not.
    sigma = np.array([0.5, 1.0, 1.5, 2.0, 1.0, 0.7])
    assert exact_variance_ratio(templates, sigma, 1.0 / sigma**2) == pytest.approx(1.0, abs=1e-12)
    assert exact_variance_ratio(templates, sigma) > 1.01


def test_toy_formula_values() -> None:
    assert toy_variance_ratio(0.0, 0.1) == pytest.approx(1.02)
    assert toy_variance_ratio(0.8, 0.3) == pytest.approx(1.0072)
    np.testing.assert_allclose(toy_variance_ratio(np.array([0.0, 0.5, 1.0]), 0.3), [1.18, 1.045, 1])


def test_epoch_psf_sizes_have_the_requested_mean_and_scatter() -> None:
    sigmas = epoch_psf_sigmas(10, 0.38, 0.1)
    assert sigmas.mean() == pytest.approx(0.38, rel=1e-12)
    assert sigmas.std() / sigmas.mean() == pytest.approx(0.1, rel=1e-12)
    random_a = epoch_psf_sigmas(10, 0.38, 0.1, np.random.default_rng(1))
    random_b = epoch_psf_sigmas(10, 0.38, 0.1, np.random.default_rng(1))
    np.testing.assert_array_equal(random_a, random_b)
    with pytest.raises(ValueError, match="non-positive"):
        epoch_psf_sigmas(10, 0.4, 0.9)


def test_gaussian_templates_are_unit_flux_and_centred() -> None:
    templates = gaussian_templates(0.5, n_epochs=5, dsigma_over_sigma=0.2)
    n, ny, nx = templates.shape
    assert n == 5 and ny == nx and nx % 2 == 1
    np.testing.assert_allclose(templates.sum(axis=(1, 2)), 1.0, atol=1e-4)
    y, x = np.mgrid[:ny, :nx]
    for template in templates:
        assert np.sum(template * x) == pytest.approx(nx // 2, abs=1e-6)
        assert np.sum(template * y) == pytest.approx(ny // 2, abs=1e-6)
    # Wider PSF -> lower peak: epoch sizes really differ.
    sigmas = epoch_psf_sigmas(5, 0.9 / FWHM_PER_SIGMA, 0.2)
    assert np.all(np.diff(templates.max(axis=(1, 2))[np.argsort(sigmas)]) < 0)
    assert galaxy_sigma(0.5, 0.4) == pytest.approx(0.4)


def test_pixelised_exact_ratio_tends_to_the_continuous_formula() -> None:
    sigmas = epoch_psf_sigmas(8, 0.4, 0.2)
    for resolution in (0.0, 0.6):
        fine = gaussian_templates(resolution, psf_sigmas=sigmas, pixel_scale=0.02)
        object_sigmas = np.hypot(galaxy_sigma(resolution, sigmas.mean()), sigmas)
        continuous = continuous_gaussian_ratio(object_sigmas)
        assert exact_variance_ratio(fine) - 1 == pytest.approx(continuous - 1, rel=3e-3)


def test_toy_is_the_small_scatter_limit_of_the_exact_ratio() -> None:
    # The appendix's toy is a second-order expansion: the continuous exact ratio tends to it.
    for resolution in (0.0, 0.5):
        sigmas = epoch_psf_sigmas(10, 1.0, 0.01)
        object_sigmas = np.hypot(galaxy_sigma(resolution, 1.0), sigmas)
        excess = continuous_gaussian_ratio(object_sigmas) - 1
        assert excess == pytest.approx(toy_variance_ratio(resolution, 0.01) - 1, rel=0.02)


def test_toy_slightly_over_predicts_the_exact_ratio_for_paper_settings() -> None:
    # Paper section 5.1: FWHM 0.9", 0.26"/px, dsigma_p/sigma_p = 0.1, R from 0 to 0.8.
    resolutions = np.linspace(0.0, 0.8, 5)
    exact = exact_ratio_curve(resolutions, dsigma_over_sigma=0.1)
    toy = toy_variance_ratio(resolutions, 0.1)
    assert np.all(exact > 1.0)
    assert np.all(exact < toy)
    assert np.all(exact - 1 > 0.9 * (toy - 1))
    assert np.all(np.diff(exact) < 0)  # larger galaxies lose less


def test_monte_carlo_agrees_with_the_exact_ratio() -> None:
    table = monte_carlo_ratio(resolutions=(0.0, 0.5), dsigma_over_sigma=0.3, n_trials=2000, seed=11)
    pulls = (table.ratio_mc - table.ratio_exact) / table.ratio_mc_err
    assert np.all(np.abs(pulls) < 3.0), table.to_text()
    # The effect is resolved, not just consistent with no loss at all.
    assert table.ratio_mc[0] - 1 > 5 * table.ratio_mc_err[0]
    np.testing.assert_allclose(table.ratio_toy, toy_variance_ratio(np.array([0.0, 0.5]), 0.3))


def test_monte_carlo_with_random_psf_sizes_and_paper_scatter() -> None:
    table = monte_carlo_ratio(
        resolutions=(0.0,), n_trials=3000, seed=5, psf_sizes="random", n_psf_sets=10
    )
    assert abs(table.ratio_mc[0] - table.ratio_exact[0]) < 3 * table.ratio_mc_err[0]
    assert table.n_psf_sets == 10


def test_monte_carlo_is_deterministic_from_the_seed() -> None:
    first = monte_carlo_ratio(resolutions=(0.2,), n_trials=200, seed=4)
    second = monte_carlo_ratio(resolutions=(0.2,), n_trials=200, seed=4)
    other = monte_carlo_ratio(resolutions=(0.2,), n_trials=200, seed=5)
    assert first.ratio_mc[0] == second.ratio_mc[0]
    assert first.ratio_mc[0] != other.ratio_mc[0]
    json.dumps(first.to_dict())


@pytest.mark.slow
def test_monte_carlo_errors_are_calibrated() -> None:
    pulls = []
    for seed in range(60):
        table = monte_carlo_ratio(
            resolutions=(0.0,), dsigma_over_sigma=0.3, n_trials=400, seed=seed
        )
        pulls.append((table.ratio_mc[0] - table.ratio_exact[0]) / table.ratio_mc_err[0])
    assert 0.75 < np.std(pulls) < 1.3
    assert abs(np.mean(pulls)) < 0.45


def test_lsst_case() -> None:
    # Paper: ~1.2 for stars and ~1.01 at R = 0.8 with dsigma_p/sigma_p = 0.3, sigma_p = 0.4".
    lsst = lsst_snr_loss(resolutions=(0.0, 0.8))
    star, galaxy = lsst["exact"]
    assert 1.15 < star < 1.3
    assert star > lsst["toy"][0]  # beyond second order at 30 % scatter
    assert 1.004 < galaxy < 1.01
    np.testing.assert_allclose(lsst["noise_exact"] ** 2, lsst["exact"])


def test_plot_snr_loss_writes_a_small_png(tmp_path) -> None:
    table = monte_carlo_ratio(resolutions=(0.0, 0.8), n_trials=100, seed=0)
    path = plot_snr_loss(table, tmp_path / "snr.png", n_curve=5)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert path.stat().st_size < 200_000


def test_cli_snr_loss(tmp_path) -> None:
    runner = CliRunner()
    result = runner.invoke(
        analyze, ["snr-loss", "--trials", "100", "--resolution", "0", "--resolution", "0.5"]
    )
    assert result.exit_code == 0, result.output
    assert "exact" in result.output and "LSST" in result.output
    result = runner.invoke(analyze, ["snr-loss", "--trials", "100", "--resolution", "0", "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.output)
    assert payload["monte_carlo"]["resolution"] == [0.0]
    assert runner.invoke(analyze, ["snr-loss", "--help"]).exit_code == 0
