"""Tests of metacalibration on plain arrays (cellcoadd.shear)."""

from __future__ import annotations

from dataclasses import replace

import galsim
import numpy as np
import pytest

from cellcoadd.errors import ShearError
from cellcoadd.shear import (
    METACAL_TYPES,
    PAPER_CUTS,
    SHAPE_DTYPE,
    MetacalError,
    MetacalFlags,
    SelectionCuts,
    bias_by_selection,
    mean_shear,
    measure_metacal,
    measure_shapes,
    metacal_images,
    multiplicative_bias,
    noise_covariances,
    reconvolution_psf,
    shear_response,
)
from cellcoadd.shear.noise_correlation import metacal_noise_covariance

SCALE = 0.2  # arcsec/pixel
SQUARE_JACOBIAN = np.array([[SCALE, 0.0], [0.0, SCALE]])
# A sheared, rotated, slightly non-square pixel grid.
SKEW_JACOBIAN = np.array([[0.19, 0.02], [-0.01, 0.21]])


def _wcs(jacobian: np.ndarray) -> galsim.JacobianWCS:
    return galsim.JacobianWCS(*np.asarray(jacobian).ravel())


def _elliptical_moffat() -> galsim.GSObject:
    return galsim.Moffat(beta=3.5, fwhm=0.7).shear(g1=0.03, g2=0.04)


def _psf_stamp(psf: galsim.GSObject, jacobian: np.ndarray, size: int = 33) -> np.ndarray:
    # drawImage's default method includes the pixel response, as the convention requires.
    return psf.drawImage(nx=size, ny=size, wcs=_wcs(jacobian)).array


def _observe(gal: galsim.GSObject, psf: galsim.GSObject, jacobian: np.ndarray, size: int = 64):
    return galsim.Convolve(gal, psf).drawImage(nx=size, ny=size, wcs=_wcs(jacobian)).array


# --- images -----------------------------------------------------------------------------


def test_noshear_is_galaxy_convolved_with_reconvolution_psf():
    psf = _elliptical_moffat()
    psf_image = _psf_stamp(psf, SKEW_JACOBIAN)
    galaxy = galsim.Gaussian(sigma=0.4, flux=100.0)
    image = _observe(galaxy, psf, SKEW_JACOBIAN, size=48)

    metacal = metacal_images(image, psf_image, None, SKEW_JACOBIAN)
    reconv = reconvolution_psf(psf_image, SKEW_JACOBIAN)
    expected = (
        galsim.Convolve(galaxy, reconv)
        .drawImage(nx=48, ny=48, wcs=_wcs(SKEW_JACOBIAN), method="no_pixel")
        .array
    )
    noshear = metacal["noshear"].image
    assert np.max(np.abs(noshear - expected)) < 1e-3 * expected.max()
    assert noshear.sum() == pytest.approx(100.0, rel=1e-3)
    # The returned PSF is the reconvolution PSF, odd, centred and of unit flux.
    psf_out = metacal["noshear"].psf_image
    n = psf_out.shape[0]
    assert psf_out.shape == (n, n) and n % 2 == 1
    assert np.unravel_index(np.argmax(psf_out), psf_out.shape) == (n // 2, n // 2)
    assert psf_out.sum() == pytest.approx(1.0, abs=1e-4)
    # All types share the one reconvolution PSF, and it is round.
    for name in METACAL_TYPES:
        np.testing.assert_array_equal(metacal[name].psf_image, psf_out)
    moments = galsim.hsm.FindAdaptiveMom(
        galsim.Image(psf_out, wcs=_wcs(SKEW_JACOBIAN)), use_sky_coords=True
    )
    assert abs(moments.observed_shape.g) < 1e-6


def test_sheared_types_carry_the_shear_and_conserve_flux():
    psf = _elliptical_moffat()
    image = _observe(galsim.Exponential(half_light_radius=0.4, flux=50.0), psf, SQUARE_JACOBIAN)
    metacal = metacal_images(image, _psf_stamp(psf, SQUARE_JACOBIAN), None, SQUARE_JACOBIAN)
    assert metacal["1p"].shear == (0.01, 0.0) and metacal["2m"].shear == (0.0, -0.01)
    for name in METACAL_TYPES:
        assert metacal[name].image.shape == image.shape
        assert metacal[name].image.sum() == pytest.approx(50.0, rel=2e-3)
        assert metacal[name].variance_factor == 1.0 and metacal[name].noise is None


def test_noise_correction_is_added_linearly_and_doubles_the_variance():
    rng = np.random.default_rng(11)
    psf = _elliptical_moffat()
    psf_image = _psf_stamp(psf, SKEW_JACOBIAN, size=25)
    image = _observe(galsim.Exponential(half_light_radius=0.4, flux=50.0), psf, SKEW_JACOBIAN, 40)
    # Non-square fields: the 90-degree rotation swaps the axes and must undo exactly.
    image = image[:, 4:36]
    noise = rng.normal(0.0, 0.1, size=image.shape)
    clean = metacal_images(image, psf_image, None, SKEW_JACOBIAN, types=("1p",))["1p"]
    noisy = metacal_images(image, psf_image, noise, SKEW_JACOBIAN, types=("1p",))["1p"]
    assert noisy.variance_factor == 2.0
    assert noisy.noise.shape == image.shape
    np.testing.assert_allclose(noisy.image - noisy.noise, clean.image, atol=1e-12)
    # The correction is the metacal transform of the noise: it scales with it.
    doubled = metacal_images(image, psf_image, 2 * noise, SKEW_JACOBIAN, types=("1p",))["1p"]
    np.testing.assert_allclose(doubled.noise, 2 * noisy.noise, atol=1e-12)


def test_every_type_uses_the_noshear_noise_covariance():
    # One covariance per object: a type's S/N moves with its flux alone, never with the
    # estimation noise of its own correction (which would push objects across an S/N cut
    # between 1p and 1m for no reason).
    rng = np.random.default_rng(4)
    psf = galsim.Moffat(beta=3.5, fwhm=0.8)
    psf_image = _psf_stamp(psf, SQUARE_JACOBIAN, size=25)
    image = _observe(galsim.Exponential(half_light_radius=0.4, flux=60.0), psf, SQUARE_JACOBIAN)
    image = image + rng.normal(0.0, 0.1, size=image.shape)
    noise = rng.normal(0.0, 0.1, size=image.shape)
    images = metacal_images(image, psf_image, noise, SQUARE_JACOBIAN)
    covariances = noise_covariances(images)
    expected = metacal_noise_covariance(images["noshear"].noise)
    for name in METACAL_TYPES:
        np.testing.assert_array_equal(covariances[name], expected)
    # each type's own estimate differs (that is what the shared one removes)
    own = {name: metacal_noise_covariance(images[name].noise) for name in ("1p", "1m")}
    assert np.max(np.abs(own["1p"] - own["1m"])) > 1e-3 * np.max(np.abs(expected))
    # the fixed wmom weight and one covariance: flux / S/N is the same in every type
    result = measure_metacal(
        image, psf_image, noise, SQUARE_JACOBIAN, 0.1, guess_centroid=(31.5, 31.5),
        shape="wmom",
    )  # fmt: skip
    flux_errors = [result[name]["flux"][0] / result[name]["s2n"][0] for name in METACAL_TYPES]
    np.testing.assert_allclose(flux_errors, flux_errors[0], rtol=1e-12)
    # without a correction nothing is measured: white noise
    assert set(
        noise_covariances(metacal_images(image, psf_image, None, SQUARE_JACOBIAN)).values()
    ) == {None}


# --- correlated-noise correction ------------------------------------------------------


def _autocorrelation(field: np.ndarray) -> np.ndarray:
    return np.fft.ifft2(np.abs(np.fft.fft2(field)) ** 2).real


def _quadrupole(correlation: np.ndarray, radius: float = 3.0) -> np.ndarray:
    """Spin-2 part (cos 2 theta, sin 2 theta) of a correlation function within radius px,
    relative to its zero lag; exactly zero for a function symmetric under 90 degrees."""
    n_y, n_x = correlation.shape
    dy, dx = np.meshgrid(np.fft.fftfreq(n_y) * n_y, np.fft.fftfreq(n_x) * n_x, indexing="ij")
    r2 = dx**2 + dy**2
    ring = (r2 > 0) & (r2 <= radius**2)
    cos2 = (dx[ring] ** 2 - dy[ring] ** 2) / r2[ring]
    sin2 = 2 * dx[ring] * dy[ring] / r2[ring]
    return (
        np.array([np.sum(correlation[ring] * cos2), np.sum(correlation[ring] * sin2)])
        / (correlation[0, 0])
    )


def _noise_kernel(size: int, sigma_x: float, sigma_y: float) -> np.ndarray:
    """Kernel K such that K * (white noise) has the wanted correlations (a delta if 0)."""
    kernel = np.zeros((size, size))
    if sigma_x == 0.0:
        kernel[size // 2, size // 2] = 1.0
        return kernel
    y, x = np.mgrid[:size, :size] - size // 2
    kernel = np.exp(-0.5 * ((x / sigma_x) ** 2 + (y / sigma_y) ** 2))
    return kernel / np.sqrt(np.sum(kernel**2))


def _noise_correlations(kernel: np.ndarray, psf_image: np.ndarray):
    """Exact correlation functions of metacal noise, without and with the correction.

    The transformation T is linear and shift invariant, so for noise K * w (w white) the
    transformed noise is T(K) * w with correlation acf(T(K)); the correction adds the
    independent term R^-1 T R (K) * w'. Passing K as both image and noise image gives
    T(K) and R^-1 T R (K) directly.
    """
    metacal = metacal_images(kernel, psf_image, kernel, SQUARE_JACOBIAN)
    out = {}
    for name, mc in metacal.items():
        transformed = _autocorrelation(mc.image - mc.noise)
        out[name] = (transformed, transformed + _autocorrelation(mc.noise))
    return out


def test_noise_correction_makes_noise_correlations_symmetric():
    # White input noise, strongly elliptical PSF: deconvolution and shear make the noise
    # anisotropic; with the correction its correlation is symmetric under 90 degrees, so
    # it carries no spin-2 signal into the shapes.
    psf_image = _psf_stamp(
        galsim.Moffat(beta=3.5, fwhm=0.7).shear(g1=0.1, g2=-0.05), SQUARE_JACOBIAN, 25
    )
    correlations = _noise_correlations(_noise_kernel(65, 0.0, 0.0), psf_image)
    for name, (uncorrected, corrected) in correlations.items():
        assert np.max(np.abs(_quadrupole(uncorrected))) > 0.5, name
        assert np.max(np.abs(_quadrupole(corrected))) < 1e-10, name
        # The full correlation function, not only its quadrupole, is symmetric.
        centred = np.fft.fftshift(corrected)  # odd size: zero lag at the centre
        np.testing.assert_allclose(np.rot90(centred), centred, atol=1e-12 * centred.max())


def test_noise_correction_removes_shear_dependence_of_anisotropic_noise():
    # Anisotropic input correlations (elliptical kernel), round PSF: without the
    # correction the noise correlation follows the applied shear (a spurious response);
    # with it the 1p and 1m noise correlations are identical.
    psf_image = _psf_stamp(galsim.Moffat(beta=3.5, fwhm=0.7), SQUARE_JACOBIAN, 25)
    correlations = _noise_correlations(_noise_kernel(65, 1.6, 0.7), psf_image)
    for plus, minus in (("1p", "1m"), ("2p", "2m")):
        change_uncorrected = _quadrupole(correlations[plus][0]) - _quadrupole(
            correlations[minus][0]
        )
        change_corrected = _quadrupole(correlations[plus][1]) - _quadrupole(correlations[minus][1])
        assert np.max(np.abs(change_uncorrected)) > 0.02
        assert np.max(np.abs(change_corrected)) < 1e-10


@pytest.mark.slow
def test_noise_correction_removes_additive_bias_of_faint_galaxies():
    # Faint round galaxies, white noise, elliptical PSF: the mean g2 is biased by the
    # deconvolved noise without the correction and consistent with zero with it. Pairs
    # of opposite noise (+n, -n) cancel the first-order noise scatter.
    rng = np.random.default_rng(3)
    psf = galsim.Moffat(beta=3.5, fwhm=0.7).shear(g2=0.1)
    psf_image = _psf_stamp(psf, SQUARE_JACOBIAN, 25)
    clean = _observe(
        galsim.Exponential(half_light_radius=0.4, flux=150.0), psf, SQUARE_JACOBIAN, 40
    )
    corrected, uncorrected = [], []
    for _ in range(600):
        noise_a = rng.normal(size=clean.shape)
        noise_b = rng.normal(size=clean.shape)
        pair_c, pair_u = [], []
        for sign in (1.0, -1.0):
            mc = metacal_images(
                clean + sign * noise_a,
                psf_image,
                sign * noise_b,
                SQUARE_JACOBIAN,
                types=("noshear",),
            )
            pair_c.append(measure_shapes(mc, 1.0)["noshear"]["g2"][0])
            bare = replace(
                mc["noshear"],
                image=mc["noshear"].image - mc["noshear"].noise,
                noise=None,
                variance_factor=1.0,
            )
            pair_u.append(measure_shapes({"noshear": bare}, 1.0)["noshear"]["g2"][0])
        corrected.append(np.mean(pair_c))
        uncorrected.append(np.mean(pair_u))
    corrected, uncorrected = np.array(corrected), np.array(uncorrected)
    # Drop the rare pairs where a measurement failed (NaN).
    measured = np.isfinite(corrected) & np.isfinite(uncorrected)
    assert measured.mean() > 0.95
    corrected, uncorrected = corrected[measured], uncorrected[measured]
    err_c = corrected.std() / np.sqrt(len(corrected))
    err_u = uncorrected.std() / np.sqrt(len(uncorrected))
    assert abs(uncorrected.mean()) > 5 * err_u
    assert abs(corrected.mean()) < 3.5 * err_c


# --- shapes and responses -------------------------------------------------------------


def test_response_of_round_gaussian_matches_expectation():
    # Round Gaussian galaxy and PSF: the adaptive-moments g responds with
    # R11 = R22 = T_gal / (T_gal + T_psf) and the off-diagonal terms vanish.
    psf = galsim.Gaussian(fwhm=0.8)
    sigma_gal = 0.4
    image = _observe(galsim.Gaussian(sigma=sigma_gal, flux=100.0), psf, SKEW_JACOBIAN, 48)
    result = measure_metacal(image, _psf_stamp(psf, SKEW_JACOBIAN), None, SKEW_JACOBIAN, 0.0)
    noshear = result["noshear"]
    assert noshear["flags"][0] == 0
    T_gal = 2 * sigma_gal**2
    T_psf = noshear["T_psf"][0]
    assert noshear["T"][0] == pytest.approx(T_gal + T_psf, rel=1e-3)
    R = shear_response(result).R
    expected = T_gal / (T_gal + T_psf)
    assert 0.3 < expected < 0.9
    assert R[0, 0] == pytest.approx(expected, rel=1e-3)
    assert R[1, 1] == pytest.approx(expected, rel=1e-3)
    assert abs(R[0, 1]) < 1e-4 and abs(R[1, 0]) < 1e-4
    assert noshear["flux"][0] == pytest.approx(100.0, rel=1e-3)
    assert noshear["x"][0] == pytest.approx(23.5, abs=1e-3)


@pytest.mark.parametrize("kind", ["gauss", "fitgauss"])
def test_recovers_shear_of_exponential_with_elliptical_psf(kind):
    psf = _elliptical_moffat()
    psf_image = _psf_stamp(psf, SQUARE_JACOBIAN)
    # A ring of two orientations cancels the intrinsic ellipticity.
    galaxies = [
        galsim.Exponential(half_light_radius=0.5).shear(
            galsim.Shear(g=0.2, beta=angle * galsim.degrees)
        )
        for angle in (0.0, 90.0)
    ]
    results = {
        sign: [
            measure_metacal(
                _observe(gal.shear(g1=sign * 0.02), psf, SQUARE_JACOBIAN),
                psf_image,
                None,
                SQUARE_JACOBIAN,
                0.0,
                psf=kind,
            )
            for gal in galaxies
        ]
        for sign in (1, -1)
    }
    for per_object in results.values():
        assert all(r[name]["flags"][0] == 0 for r in per_object for name in METACAL_TYPES)
    bias = multiplicative_bias(results[1], results[-1], true_g=0.02)
    assert abs(bias["m1"]) < 1e-3
    # The round reconvolution PSF removes the PSF-ellipticity leakage.
    assert abs(bias["c1"]) < 1e-5 and abs(bias["c2"]) < 1e-5
    g_plus, _ = mean_shear(results[1])
    assert g_plus[0] == pytest.approx(0.02, rel=1e-3)
    assert abs(g_plus[1]) < 1e-5


def test_dilated_psf_keeps_additive_leakage():
    # Reconvolving with the (elliptical) PSF itself leaves the PSF anisotropy in the
    # shapes: a round galaxy gets an additive shear of the order of the PSF's.
    psf = _elliptical_moffat()
    image = _observe(galsim.Exponential(half_light_radius=0.4), psf, SQUARE_JACOBIAN)
    psf_image = _psf_stamp(psf, SQUARE_JACOBIAN)
    dilated = measure_metacal(image, psf_image, None, SQUARE_JACOBIAN, 0.0, psf="dilate")
    round_ = measure_metacal(image, psf_image, None, SQUARE_JACOBIAN, 0.0, psf="gauss")
    assert dilated["noshear"]["g2"][0] > 0.01
    assert abs(round_["noshear"]["g2"][0]) < 1e-6


def test_signal_to_noise_scales_with_flux_and_noise():
    psf = _elliptical_moffat()
    psf_image = _psf_stamp(psf, SQUARE_JACOBIAN, 25)
    image = _observe(
        galsim.Exponential(half_light_radius=0.4, flux=100.0), psf, SQUARE_JACOBIAN, 40
    )
    low = measure_metacal(image, psf_image, None, SQUARE_JACOBIAN, noise_sigma=1.0)
    high = measure_metacal(3 * image, psf_image, None, SQUARE_JACOBIAN, noise_sigma=1.0)
    noisier = measure_metacal(image, psf_image, None, SQUARE_JACOBIAN, noise_sigma=2.0)
    s2n = low["noshear"]["s2n"][0]
    assert 10.0 < s2n < 200.0
    assert high["noshear"]["s2n"][0] == pytest.approx(3 * s2n, rel=1e-6)
    assert noisier["noshear"]["s2n"][0] == pytest.approx(s2n / 2, rel=1e-6)
    # With a noise image the S/N comes from the covariance of the metacal image's noise
    # (its correction's, tests/test_snr_covariance.py), not from noise_sigma: below the
    # white-noise value s2n / sqrt(2) (the reconvolution correlates the noise), and
    # halved by a noise image twice as large.
    noise = np.random.default_rng(4).standard_normal(image.shape)
    once = measure_metacal(image, psf_image, noise, SQUARE_JACOBIAN, 1.0)["noshear"]["s2n"][0]
    twice = measure_metacal(image, psf_image, 2 * noise, SQUARE_JACOBIAN, 1.0)["noshear"]["s2n"][0]
    assert once < s2n / np.sqrt(2)
    assert twice == pytest.approx(once / 2, rel=0.1)


# --- failures -------------------------------------------------------------------------


def test_failures_are_flagged_not_raised():
    psf_image = _psf_stamp(_elliptical_moffat(), SQUARE_JACOBIAN, 25)
    zeros = np.zeros((32, 32))
    result = measure_metacal(zeros, psf_image, zeros, SQUARE_JACOBIAN, 1.0)
    assert set(result) == set(METACAL_TYPES)
    for name in METACAL_TYPES:
        assert result[name].dtype == SHAPE_DTYPE
        assert result[name]["flags"][0] & MetacalFlags.HSM_FAILED
        assert np.isnan(result[name]["g1"][0])

    with_nan = zeros.copy()
    with_nan[3, 4] = np.nan
    result = measure_metacal(with_nan, psf_image, None, SQUARE_JACOBIAN, 1.0)
    assert all(result[name]["flags"][0] == MetacalFlags.NONFINITE for name in METACAL_TYPES)

    result = measure_metacal(zeros, np.zeros((25, 25)), None, SQUARE_JACOBIAN, 1.0)
    assert all(result[name]["flags"][0] == MetacalFlags.PSF_FAILED for name in METACAL_TYPES)

    negative = -_observe(
        galsim.Gaussian(sigma=0.4, flux=10.0), galsim.Gaussian(fwhm=0.7), SQUARE_JACOBIAN, 32
    )
    result = measure_metacal(negative, psf_image, None, SQUARE_JACOBIAN, 1.0)
    assert all(result[name]["flags"][0] != 0 for name in METACAL_TYPES)


def test_malformed_arguments_raise():
    psf_image = _psf_stamp(_elliptical_moffat(), SQUARE_JACOBIAN, 25)
    image = np.ones((32, 32))
    with pytest.raises(MetacalError, match="odd square"):
        metacal_images(image, psf_image[:-1, :-1], None, SQUARE_JACOBIAN)
    with pytest.raises(MetacalError, match="noise_image shape"):
        measure_metacal(image, psf_image, np.ones((31, 32)), SQUARE_JACOBIAN, 1.0)
    with pytest.raises(MetacalError, match="jacobian"):
        metacal_images(image, psf_image, None, np.zeros((2, 2)))
    with pytest.raises(MetacalError, match="reconvolution PSF"):
        measure_metacal(image, psf_image, None, SQUARE_JACOBIAN, 1.0, psf="moffat")
    with pytest.raises(MetacalError, match="step"):
        metacal_images(image, psf_image, None, SQUARE_JACOBIAN, step=0.0)


# --- ensemble estimators on synthetic catalogues ----------------------------------------


def _synthetic_catalogues(
    rng: np.random.Generator,
    n_pairs: int,
    g_true: tuple[float, float],
    R: float = 0.6,
    step: float = 0.01,
    alignment: float = 0.0,
    shape_noise: np.ndarray | None = None,
    measurement_noise: float = 0.0,
) -> dict[str, np.ndarray]:
    """Linear-response catalogues: e = e_int + R g (+ noise), for every metacal type.

    Intrinsic shapes come in ring pairs (e, -e). With ``alignment`` != 0 the S/N depends
    on the alignment of the shape with the applied shear, a shear-dependent selection.
    """
    e_int = rng.normal(0.0, 0.25, size=(n_pairs, 2)) if shape_noise is None else shape_noise
    # Interleaved (e, -e) so that jackknife blocks keep ring pairs together.
    e_int = np.stack([e_int, -e_int], axis=1).reshape(-1, 2)
    s2n = np.repeat(rng.uniform(5.0, 20.0, size=n_pairs), 2)
    noise = rng.normal(0.0, measurement_noise, size=(2 * n_pairs, 2))
    offsets = {
        "noshear": (0, 0),
        "1p": (step, 0),
        "1m": (-step, 0),
        "2p": (0, step),
        "2m": (0, -step),
    }
    catalogues = {}
    for name, (d1, d2) in offsets.items():
        g_applied = np.array([g_true[0] + d1, g_true[1] + d2])
        catalogue = np.zeros(2 * n_pairs, dtype=SHAPE_DTYPE)
        catalogue["g1"] = e_int[:, 0] + R * g_applied[0] + noise[:, 0]
        catalogue["g2"] = e_int[:, 1] + R * g_applied[1] + noise[:, 1]
        catalogue["s2n"] = s2n * (1.0 + alignment * (e_int @ g_applied))
        catalogue["T"] = 1.0
        catalogue["T_psf"] = 1.0
        catalogues[name] = catalogue
    return catalogues


def test_multiplicative_bias_of_synthetic_catalogues():
    rng = np.random.default_rng(7)
    n_pairs, R, g_true, sigma_n = 1000, 0.6, 0.02, 0.1
    m_true, c_true = 0.003, (2e-4, -5e-4)
    shapes = rng.normal(0.0, 0.25, size=(n_pairs, 2))
    plus = _synthetic_catalogues(
        rng,
        n_pairs,
        ((1 + m_true) * g_true + c_true[0], c_true[1]),
        R=R,
        shape_noise=shapes,
        measurement_noise=sigma_n,
    )
    minus = _synthetic_catalogues(
        rng,
        n_pairs,
        (-(1 + m_true) * g_true + c_true[0], c_true[1]),
        R=R,
        shape_noise=shapes,
        measurement_noise=sigma_n,
    )
    # Exact expectations for these realizations (shape noise cancels in the ring pairs).
    mean_plus = plus["noshear"]["g1"].mean() / R
    mean_minus = minus["noshear"]["g1"].mean() / R
    bias = multiplicative_bias(plus, minus, true_g=g_true)
    assert bias["m1"] == pytest.approx((mean_plus - mean_minus) / (2 * g_true) - 1, abs=1e-12)
    assert bias["c1"] == pytest.approx((mean_plus + mean_minus) / 2, abs=1e-12)
    assert bias["c2"] == pytest.approx(
        (plus["noshear"]["g2"].mean() + minus["noshear"]["g2"].mean()) / (2 * R), abs=1e-12
    )
    # The estimates are consistent with the truth, with jackknife errors close to the
    # analytic ones: only the independent measurement noise enters.
    n = 2 * n_pairs
    m_err = np.sqrt(2 * sigma_n**2 / n) / (2 * g_true * R)
    c_err = np.sqrt(sigma_n**2 / (2 * n)) / R
    assert bias["m1_err"] == pytest.approx(m_err, rel=0.25)
    assert bias["c1_err"] == pytest.approx(c_err, rel=0.25)
    assert bias["c2_err"] == pytest.approx(c_err, rel=0.25)
    assert abs(bias["m1"] - m_true) < 4 * m_err
    assert abs(bias["c1"] - c_true[0]) < 4 * c_err and abs(bias["c2"] - c_true[1]) < 4 * c_err

    noiseless_plus = _synthetic_catalogues(rng, 50, (0.0201, 0.0), R=R)
    noiseless_minus = _synthetic_catalogues(rng, 50, (-0.0199, 0.0), R=R)
    exact = multiplicative_bias(noiseless_plus, noiseless_minus, true_g=0.02)
    assert exact["m1"] == pytest.approx(0.0, abs=1e-12)
    assert exact["c1"] == pytest.approx(1e-4, abs=1e-12)


def test_selection_response_corrects_shear_dependent_selection():
    rng = np.random.default_rng(5)
    g_true = (0.02, -0.01)
    catalogues = _synthetic_catalogues(rng, 20000, g_true, alignment=8.0)
    response = shear_response(catalogues, selection=PAPER_CUTS)
    np.testing.assert_allclose(response.R, 0.6 * np.eye(2), atol=1e-12)
    assert response.R_S[0, 0] > 0.1 and response.R_S[1, 1] > 0.1
    assert 0 < response.n_selected < len(catalogues["noshear"])
    g, g_err = mean_shear(catalogues, selection=PAPER_CUTS)
    assert np.all(np.abs(g - g_true) < 4 * g_err)
    uncorrected = np.linalg.solve(response.R, response.mean_e)
    assert abs(uncorrected[0] - g_true[0]) > 10 * g_err[0]
    # Without cuts nothing is selected away, R_S vanishes and the shear is exact.
    plain = shear_response(catalogues)
    np.testing.assert_allclose(plain.R_S, 0.0, atol=1e-12)
    np.testing.assert_allclose(plain.shear, g_true, atol=1e-12)


def test_bias_by_selection_pairs_the_selections():
    rng = np.random.default_rng(11)
    n_pairs, g_true = 4000, 0.02
    shapes = rng.normal(0.0, 0.25, size=(n_pairs, 2))
    common = {"R": 0.6, "shape_noise": shapes, "measurement_noise": 0.1, "alignment": 8.0}
    plus = _synthetic_catalogues(rng, n_pairs, (g_true, 0.0), **common)
    minus = _synthetic_catalogues(rng, n_pairs, (-g_true, 0.0), **common)
    cut = SelectionCuts(s2n_min=12.0, T_ratio_min=0.5)  # shear-dependent: S/N aligns
    selections = {"none": None, "S/N > 12": cut, "again none": None, "all kept": SelectionCuts(
        s2n_min=-np.inf, T_ratio_min=-np.inf)}  # fmt: skip
    out = bias_by_selection(plus, minus, selections, true_g=g_true, group=2)
    assert list(out) == list(selections)
    # Each entry is multiplicative_bias's own for that selection.
    for name, selection in selections.items():
        alone = multiplicative_bias(plus, minus, true_g=g_true, selection=selection, group=2)
        assert out[name]["m1"] == pytest.approx(alone["m1"], abs=1e-14)
        assert out[name]["m1_err"] == pytest.approx(alone["m1_err"], rel=1e-12)
        assert out[name]["scatter"] == pytest.approx(alone["m1_err"] * np.sqrt(2 * n_pairs))
    assert "dm1" not in out["none"]
    # The same selection twice (or one removing nothing): no difference, no error.
    for name in ("again none", "all kept"):
        assert out[name]["dm1"] == pytest.approx(0.0, abs=1e-14)
        assert out[name]["dm1_err"] == pytest.approx(0.0, abs=1e-14)
    # A shear-dependent cut, corrected for its selection response, changes m1 by no more
    # than the paired error allows (uncorrected, such a cut is off by > 10 sigma: see
    # test_selection_response_corrects_shear_dependent_selection).
    cut_entry = out["S/N > 12"]
    assert cut_entry["dm1"] == pytest.approx(cut_entry["m1"] - out["none"]["m1"], abs=1e-14)
    assert cut_entry["dm1_err"] > 0
    assert abs(cut_entry["dm1"]) < 4 * cut_entry["dm1_err"]
    assert abs(cut_entry["m1"]) < 4 * cut_entry["m1_err"]
    with pytest.raises(ShearError, match="at least one selection"):
        bias_by_selection(plus, minus, {})


def test_response_skips_flagged_objects():
    rng = np.random.default_rng(9)
    catalogues = _synthetic_catalogues(rng, 100, (0.01, 0.0))
    per_object = [{name: cat[i : i + 1] for name, cat in catalogues.items()} for i in range(200)]
    failed = {name: np.zeros(1, dtype=SHAPE_DTYPE) for name in METACAL_TYPES}
    for name in METACAL_TYPES:
        failed[name]["flags"] = MetacalFlags.HSM_FAILED
        failed[name]["g1"] = np.nan
    g_all, _ = mean_shear(per_object)
    g_with_failure, _ = mean_shear([*per_object, failed])
    np.testing.assert_allclose(g_with_failure, g_all, atol=1e-12)
    np.testing.assert_allclose(g_all, (0.01, 0.0), atol=1e-12)
    with pytest.raises(ValueError, match="missing"):
        shear_response({"noshear": catalogues["noshear"]})


# --- fixed-weight Gaussian moments (wmom) ------------------------------------------------


def _weighted_gaussian(cov: np.ndarray, weight_fwhm: float) -> np.ndarray:
    """Covariance of a Gaussian of covariance ``cov`` times a round Gaussian weight."""
    sigma_w = weight_fwhm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    return np.linalg.inv(np.linalg.inv(cov) + np.eye(2) / sigma_w**2)


@pytest.mark.parametrize("jacobian", [SQUARE_JACOBIAN, SKEW_JACOBIAN], ids=["square", "skew"])
def test_wmom_shape_of_gaussian_matches_analytic_value(jacobian):
    from cellcoadd.shear.shapes import measure_wmom

    # galsim shear + WCS: the sky covariance of the profile is sigma^2 A A^T
    shear = galsim.Shear(g1=0.2, g2=-0.1)
    gal = galsim.Gaussian(sigma=0.5, flux=50.0).shear(shear)
    matrix = shear.getMatrix()
    cov = 0.25 * matrix @ matrix.T
    image = gal.drawImage(nx=81, ny=81, wcs=_wcs(jacobian), method="no_pixel").array
    record = measure_wmom(image, _wcs(jacobian), 4.0, (40.0, 40.0), weight_fwhm=1.2)
    eff = _weighted_gaussian(cov, 1.2)
    T = eff[0, 0] + eff[1, 1]
    assert record["flags"][0] == 0
    assert record["T"][0] == pytest.approx(T, rel=1e-6)
    assert record["g1"][0] == pytest.approx((eff[0, 0] - eff[1, 1]) / T, rel=1e-6)
    assert record["g2"][0] == pytest.approx(2.0 * eff[0, 1] / T, rel=1e-6)
    flux = 50.0 * np.sqrt(np.linalg.det(eff) / np.linalg.det(cov))
    assert record["flux"][0] == pytest.approx(flux, rel=1e-6)
    assert record["s2n"][0] > 0 and (record["x"][0], record["y"][0]) == (40.0, 40.0)


def test_wmom_metacal_response_of_round_gaussian_matches_expectation():
    # Metacal image: Gaussian of variance s^2 = sigma_g^2 + sigma_r^2; with a weight of
    # variance w^2 the polarisation responds with R = 2 sigma_g^2 w^2 / (s^2 (s^2 + w^2)).
    psf = galsim.Gaussian(fwhm=0.8)
    sigma_gal, fwhm = 0.4, 1.2
    image = _observe(galsim.Gaussian(sigma=sigma_gal, flux=100.0), psf, SKEW_JACOBIAN, 64)
    psf_image = _psf_stamp(psf, SKEW_JACOBIAN)
    result = measure_metacal(
        image, psf_image, None, SKEW_JACOBIAN, 0.0, guess_centroid=(31.5, 31.5),
        shape="wmom", weight_fwhm=fwhm,
    )  # fmt: skip
    sigma_r = reconvolution_psf(psf_image, SKEW_JACOBIAN).sigma
    s2 = sigma_gal**2 + sigma_r**2
    w2 = (fwhm / (2.0 * np.sqrt(2.0 * np.log(2.0)))) ** 2
    expected = 2.0 * sigma_gal**2 * w2 / (s2 * (s2 + w2))
    R = shear_response(result).R
    assert R[0, 0] == pytest.approx(expected, rel=2e-3)
    assert R[1, 1] == pytest.approx(expected, rel=2e-3)
    assert abs(R[0, 1]) < 1e-4 and abs(R[1, 0]) < 1e-4
    noshear = result["noshear"][0]
    assert noshear["flags"] == 0 and noshear["T"] < noshear["T"] / noshear["T_psf"] * 10
    assert noshear["T"] / noshear["T_psf"] > 1.0  # both in the same weight
    with pytest.raises(MetacalError, match="shape"):
        measure_metacal(image, psf_image, None, SKEW_JACOBIAN, 0.0, shape="ksigma")
