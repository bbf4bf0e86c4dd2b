"""Correlated coadd noise, measured from a cell's noise realizations.

Resampling onto the cell grid correlates neighbouring coadd pixels (about 0.4 at lag 1 for
0.26 arcsec inputs on 0.2 arcsec cells), but a weight map (``1 / pixel variance``) describes
uncorrelated noise. Any quantity computed from the weight map alone, such as the flux
error and S/N of an ngmix/metadetect measurement or the detection threshold of sep,
therefore assumes too little noise: the true variance of a Gaussian-weighted flux is
~1.8 times what the weight implies. The noise realizations of a cell are resampled and
averaged exactly like its image, so they carry exactly this correlation; the helpers here
measure it and give the true variances.

Every function takes a :class:`~cellcoadd.model.cell_coadd.CellCoadd` (its realizations
are used over the cell's *inner* region) or an array of realizations of shape
``(K, ny, nx)`` (or one ``(ny, nx)`` image), e.g. realizations put through the same linear
operation as the image. The realizations have zero mean by construction, so no mean is
subtracted. Arrays are indexed ``[y, x]`` and lags ``(dy, dx)`` are in pixels.

* :func:`noise_covariance` -- the autocovariance ``C(dy, dx) = <n(y, x) n(y + dy, x + dx)>``
  for ``|dy|, |dx| <= max_lag``; :func:`noise_correlation` is ``C / C(0, 0)``.
* :func:`noise_power_spectrum` -- the mean ``|FFT(n)|^2 / (ny nx)`` (its mean over all
  frequencies is the pixel variance).
* :func:`weighted_flux_variance` -- the variance of ``sum(w * image)`` for a weight stamp
  ``w``: ``sum_lag C(lag) R_w(lag)`` with ``R_w`` the autocorrelation of ``w``.
* :func:`covariance_flux_variance` -- the same from a covariance already measured;
  :func:`metacal_noise_covariance` -- the covariance of a metacalibration image's noise
  (the image's own and its correction's), from the correction: what metacal's S/N uses.
* :func:`variance_factor` -- that variance divided by what uncorrelated noise of the same
  pixel variance would give (``C(0) sum(w^2)``); :func:`snr_correction` is its square
  root for a Gaussian weight: divide a weight-map S/N by it to get the true S/N.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cellcoadd.errors import CellCoaddRangeError, ShearError
from cellcoadd.model.cell_coadd import CellCoadd

#: Default largest lag (pixels) of the covariance sums. The Lanczos-3 kernel spans
#: +-3 input pixels (+-3.9 coadd pixels for 0.26 arcsec inputs on 0.2 arcsec cells), so the
#: resampled noise is correlated over at most about twice that.
DEFAULT_MAX_LAG = 8
#: Largest lag of the covariance of a metacalibration image's noise: reconvolution by a
#: PSF wider than the input's correlates it over a few PSF sigmas (~10 coadd pixels).
METACAL_MAX_LAG = 12


def _realizations(noise: CellCoadd | Any) -> np.ndarray:
    """The realizations as a float64 ``(K, ny, nx)`` array (inner region of a cell)."""
    if isinstance(noise, CellCoadd):
        if noise.n_noise == 0:
            raise ShearError(
                f"cell {noise.index} of tract {noise.tract} has no noise realization; "
                "build it with BuildConfig(n_noise >= 1)",
                cell=noise.index,
            )
        array = np.asarray(noise.inner.noise, dtype=np.float64)
    else:
        array = np.asarray(noise, dtype=np.float64)
        if array.ndim == 2:
            array = array[np.newaxis]
    if array.ndim != 3 or array.shape[0] == 0 or min(array.shape[1:]) < 2:
        raise ShearError(
            "noise realizations must be a CellCoadd or an array of shape (K, ny, nx) "
            f"with K >= 1 and ny, nx >= 2, got shape {array.shape}",
            value=array.shape,
        )
    if not np.all(np.isfinite(array)):
        raise ShearError("noise realizations contain non-finite values")
    return array


def _check_max_lag(max_lag: int, shape: tuple[int, ...]) -> int:
    max_lag = int(max_lag)
    if max_lag < 0 or max_lag >= min(shape[-2:]):
        raise CellCoaddRangeError(
            f"max_lag must be in [0, {min(shape[-2:]) - 1}] for realizations of shape "
            f"{shape[-2:]}, got {max_lag}",
            value=max_lag,
            low=0,
            high=min(shape[-2:]) - 1,
        )
    return max_lag


def _lag_sums(a: np.ndarray, b: np.ndarray, max_lag: int) -> np.ndarray:
    """``S[dy + L, dx + L] = sum_p a[p] b[p + lag]`` over overlapping pixels, ``|lag| <= L``.

    ``a`` and ``b`` have the same shape ``(..., ny, nx)``; leading axes are summed.
    """
    ny, nx = a.shape[-2:]
    # zero padding to a period >= 2 max_lag + 1: no wrap-around for |lag| <= max_lag
    shape = (max(ny, max_lag + 1) + max_lag, max(nx, max_lag + 1) + max_lag)
    fa = np.fft.rfft2(a, s=shape)
    fb = np.fft.rfft2(b, s=shape)
    cross = np.fft.irfft2(np.conj(fa) * fb, s=shape)
    if cross.ndim > 2:
        cross = cross.reshape(-1, *shape).sum(axis=0)
    lags = np.arange(-max_lag, max_lag + 1)
    return cross[np.ix_(lags % shape[0], lags % shape[1])]


def noise_covariance(noise: CellCoadd | Any, max_lag: int = DEFAULT_MAX_LAG) -> np.ndarray:
    """Autocovariance of the noise realizations, ``(2 max_lag + 1)`` square.

    ``C[max_lag + dy, max_lag + dx] = <n(y, x) n(y + dy, x + dx)>``, the mean over all
    realizations and all pixel pairs at that lag inside the arrays (each lag is normalised
    by its own number of pairs). ``C`` is point-symmetric; its centre is the pixel variance.
    """
    array = _realizations(noise)
    max_lag = _check_max_lag(max_lag, array.shape)
    k, ny, nx = array.shape
    sums = _lag_sums(array, array, max_lag)
    lags = np.arange(-max_lag, max_lag + 1)
    pairs = np.outer(ny - np.abs(lags), nx - np.abs(lags)) * k
    return np.asarray(sums / pairs)


def noise_correlation(noise: CellCoadd | Any, max_lag: int = DEFAULT_MAX_LAG) -> np.ndarray:
    """Correlation coefficients ``C / C(0, 0)`` of :func:`noise_covariance` (centre 1)."""
    covariance = noise_covariance(noise, max_lag)
    return np.asarray(covariance / covariance[max_lag, max_lag])


def noise_power_spectrum(noise: CellCoadd | Any) -> np.ndarray:
    """Mean power spectrum ``<|FFT(n)|^2> / (ny nx)`` of the realizations, shape ``(ny, nx)``.

    Unshifted (``numpy.fft`` order; frequencies ``numpy.fft.fftfreq(n)`` in cycles per
    pixel). Its mean over all frequencies is the pixel variance; white noise of variance
    ``s^2`` gives ``s^2`` everywhere. It is periodic (the realizations are not padded).
    """
    array = _realizations(noise)
    _, ny, nx = array.shape
    power = np.abs(np.fft.fft2(array)) ** 2
    return np.asarray(power.mean(axis=0) / (ny * nx))


def _weight_stamp(weight_image: Any) -> np.ndarray:
    weight = np.asarray(weight_image, dtype=np.float64)
    if weight.ndim != 2 or weight.size == 0 or not np.all(np.isfinite(weight)):
        raise ShearError(
            f"weight_image must be a finite 2-d array, got shape {weight.shape}", value=weight.shape
        )
    if not np.any(weight):
        raise ShearError("weight_image is zero everywhere")
    return weight


def weighted_flux_variance(
    noise: CellCoadd | Any,
    weight_image: Any,
    max_lag: int = DEFAULT_MAX_LAG,
) -> float:
    """Variance of ``sum(weight_image * image)`` under the realizations' correlated noise.

    ``sum_lag C(lag) R_w(lag)`` over ``|dy|, |dx| <= max_lag``, with ``C`` from
    :func:`noise_covariance` and ``R_w(lag) = sum_p w[p] w[p + lag]``. The noise is taken
    as stationary (the same covariance everywhere in the cell), so the weight stamp may
    have any shape and sit anywhere; only its shape matters. With ``max_lag`` at least the
    correlation length this is exact up to the estimation error of ``C`` (much smaller
    than the scatter of ``sum(w n_k)`` over the ``K`` realizations). ``max_lag`` is
    clipped to the realizations' size.
    """
    array = _realizations(noise)
    weight = _weight_stamp(weight_image)
    max_lag = min(int(max_lag), min(array.shape[1:]) - 1)
    max_lag = _check_max_lag(max_lag, array.shape)
    covariance = noise_covariance(array, max_lag)
    lag_y = min(max_lag, weight.shape[0] - 1)
    lag_x = min(max_lag, weight.shape[1] - 1)
    autocorrelation = _lag_sums(weight, weight, max(lag_y, lag_x))
    centre = autocorrelation.shape[0] // 2
    window = autocorrelation[
        centre - lag_y : centre + lag_y + 1, centre - lag_x : centre + lag_x + 1
    ]
    cov = covariance[max_lag - lag_y : max_lag + lag_y + 1, max_lag - lag_x : max_lag + lag_x + 1]
    return float(np.sum(cov * window))


def covariance_flux_variance(covariance: np.ndarray, weight_image: Any) -> float:
    """Variance of ``sum(weight_image * image)`` for noise of autocovariance ``covariance``.

    ``covariance`` is laid out as :func:`noise_covariance` gives it (``(2L + 1)`` square,
    lag ``(dy, dx)`` at ``[L + dy, L + dx]``); the noise is taken as stationary and
    uncorrelated beyond ``L``. ``sum_lag C(lag) R_w(lag)``, ``R_w`` the autocorrelation of
    the weight (lags beyond the weight's size contribute nothing).
    """
    weight = _weight_stamp(weight_image)
    cov = np.asarray(covariance, dtype=np.float64)
    max_lag = cov.shape[0] // 2
    autocorrelation = _lag_sums(weight, weight, max_lag)
    return float(np.sum(cov * autocorrelation))


def metacal_noise_covariance(correction: np.ndarray, max_lag: int = METACAL_MAX_LAG) -> np.ndarray:
    """Autocovariance of the whole noise of a metacalibration image, from its correction.

    A metacal image is ``M(image) + R^-1 M(R n)`` (:func:`cellcoadd.shear.metacal_images`:
    ``M`` the deconvolve-shear-reconvolve operation, ``R`` a 90-degree rotation, ``n`` a
    noise realization); ``correction`` is the second term. Its noise has the covariance of
    ``M(noise)`` turned by 90 degrees, and the first term's noise that of ``M(noise)``, so
    the sum's is ``C + rot90(C)`` with ``C`` the correction's (for input noise whose
    statistics a 90-degree turn leaves unchanged: white noise, and coadd noise to the
    extent the inputs' orientations average out). ``(2 max_lag + 1)`` square.
    """
    covariance = noise_covariance(np.asarray(correction, dtype=np.float64), max_lag)
    return np.asarray(covariance + np.rot90(covariance))


def variance_factor(
    noise: CellCoadd | Any,
    weight_image: Any,
    max_lag: int = DEFAULT_MAX_LAG,
) -> float:
    """True variance of ``sum(w * image)`` over the white-noise value ``C(0, 0) sum(w^2)``.

    The factor by which a weight map (``1 / pixel variance``) understates the variance of
    a linear measurement with weight stamp ``w``: 1 for uncorrelated noise, ~1.8 for a
    Gaussian of sigma 2.5 pixels on a 0.2 arcsec coadd of 0.26 arcsec inputs. For a sep
    detection filter ``w`` is the filter kernel.
    """
    weight = _weight_stamp(weight_image)
    array = _realizations(noise)
    pixel_variance = float(np.mean(array**2))
    white = pixel_variance * float(np.sum(weight**2))
    return weighted_flux_variance(array, weight, max_lag) / white


def gaussian_weight(sigma_pix: float, radius: float = 5.0) -> np.ndarray:
    """Round Gaussian ``exp(-r^2 / 2 sigma^2)`` on an odd stamp of half-size ``radius sigma``."""
    if not np.isfinite(sigma_pix) or sigma_pix <= 0.0:
        raise CellCoaddRangeError(
            f"sigma_pix must be finite and positive, got {sigma_pix}", value=sigma_pix, low=0.0
        )
    half = max(1, int(np.ceil(radius * sigma_pix)))
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    r2 = offsets[:, np.newaxis] ** 2 + offsets[np.newaxis, :] ** 2
    return np.asarray(np.exp(-0.5 * r2 / sigma_pix**2))


def snr_correction(
    noise: CellCoadd | Any,
    sigma_pix: float,
    max_lag: int | None = None,
) -> float:
    """``sqrt(variance_factor)`` for a round Gaussian weight of ``sigma_pix`` pixels.

    A S/N computed from the weight map (e.g. ngmix ``GaussMom`` / metadetect ``wmom``
    with ``fwhm = 2.3548 sigma_pix * pixel scale``) is too high by this factor: the true
    S/N is ``s2n / snr_correction``. ``max_lag`` defaults to the larger of
    :data:`DEFAULT_MAX_LAG` and ``4 sigma_pix``.
    """
    weight = gaussian_weight(sigma_pix)
    if max_lag is None:
        max_lag = max(DEFAULT_MAX_LAG, int(np.ceil(4.0 * sigma_pix)))
    return float(np.sqrt(variance_factor(noise, weight, max_lag)))


__all__ = [
    "DEFAULT_MAX_LAG",
    "METACAL_MAX_LAG",
    "covariance_flux_variance",
    "gaussian_weight",
    "metacal_noise_covariance",
    "noise_correlation",
    "noise_covariance",
    "noise_power_spectrum",
    "snr_correction",
    "variance_factor",
    "weighted_flux_variance",
]
