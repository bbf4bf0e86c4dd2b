"""Gaussian galaxies seen through epoch-dependent Gaussian PSFs (the paper's Fig. 4 model).

Only the PSF size changes between epochs; the galaxy's size follows from the resolution
``R = sigma_g^2 / (sigma_g^2 + sigma_p^2)`` and the mean PSF sigma ``sigma_p``. Templates are
drawn with GalSim (pixel response included) at the centre of an odd stamp, so every epoch
shares one pixel grid and no resampling is involved.
"""

from __future__ import annotations

from statistics import NormalDist

import galsim
import numpy as np

from cellcoadd.errors import CellCoaddRangeError, CellCoaddValueError

#: FWHM of a Gaussian in units of its sigma, 2 sqrt(2 ln 2).
FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


def galaxy_sigma(resolution: float, psf_sigma: float) -> float:
    """Galaxy sigma giving resolution ``R`` with a PSF of sigma ``psf_sigma`` (same unit)."""
    if not 0.0 <= resolution < 1.0:
        raise CellCoaddRangeError(
            f"resolution must be in [0, 1), got {resolution}", value=resolution, low=0.0, high=1.0
        )
    return float(psf_sigma * np.sqrt(resolution / (1.0 - resolution)))


def epoch_psf_sigmas(
    n_epochs: int,
    psf_sigma: float,
    dsigma_over_sigma: float,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """PSF Gaussian sigma of each epoch, scattered about ``psf_sigma``.

    Parameters
    ----------
    n_epochs : int
        Number of epochs.
    psf_sigma : float
        Mean PSF sigma (arcsec).
    dsigma_over_sigma : float
        Relative RMS scatter of the PSF sigma.
    rng : numpy.random.Generator, optional
        Without it the sizes are the normal quantiles at ``(i + 1/2) / n_epochs``, rescaled
        so their mean is exactly ``psf_sigma`` and their RMS scatter exactly
        ``dsigma_over_sigma * psf_sigma`` (a deterministic, representative set). With it they
        are independent normal draws.

    Returns
    -------
    ndarray, shape (n_epochs,)
        Positive PSF sigmas, arcsec.
    """
    if n_epochs < 1:
        raise CellCoaddRangeError(f"n_epochs must be >= 1, got {n_epochs}", value=n_epochs, low=1)
    if rng is None:
        unit = NormalDist()
        z = np.array([unit.inv_cdf((i + 0.5) / n_epochs) for i in range(n_epochs)])
        spread = z.std()
        z = (z - z.mean()) / spread if spread > 0 else np.zeros(n_epochs)
    else:
        z = rng.standard_normal(n_epochs)
    sigmas = psf_sigma * (1.0 + dsigma_over_sigma * z)
    if np.any(sigmas <= 0):
        raise CellCoaddValueError(
            f"dsigma_over_sigma={dsigma_over_sigma} with {n_epochs} epochs gives non-positive PSF "
            "sizes; use a smaller scatter or fewer epochs",
            value=dsigma_over_sigma,
        )
    return sigmas


def _stamp_size(max_sigma_arcsec: float, pixel_scale: float) -> int:
    """Odd stamp side covering +-6 sigma of the widest epoch image."""
    return 2 * int(np.ceil(6.0 * max_sigma_arcsec / pixel_scale)) + 1


def gaussian_templates(
    resolution: float,
    n_epochs: int = 10,
    dsigma_over_sigma: float = 0.1,
    psf_fwhm: float = 0.9,
    pixel_scale: float = 0.26,
    *,
    psf_sigmas: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
    stamp_size: int | None = None,
) -> np.ndarray:
    """Unit-flux templates of a circular Gaussian galaxy seen through per-epoch Gaussian PSFs.

    Drawn with GalSim (pixel response included) at the centre of an odd stamp, as in the
    paper's Fig. 4 test: the galaxy sigma follows from ``R`` and the *mean* PSF sigma, and only
    the PSF size changes between epochs.

    Parameters
    ----------
    resolution : float
        ``R = sigma_g^2 / (sigma_g^2 + sigma_p^2)`` in [0, 1); 0 draws a star.
    n_epochs : int
        Number of epochs (ignored when ``psf_sigmas`` is given).
    dsigma_over_sigma : float
        Relative RMS scatter of the PSF sigma between epochs.
    psf_fwhm : float
        Mean PSF FWHM, arcsec (0.9 in the paper).
    pixel_scale : float
        Pixel scale, arcsec/pixel (0.26 in the paper).
    psf_sigmas : ndarray, optional
        Explicit per-epoch PSF sigmas, arcsec; otherwise from :func:`epoch_psf_sigmas`.
    rng : numpy.random.Generator, optional
        Passed to :func:`epoch_psf_sigmas` (random instead of quantile PSF sizes).
    stamp_size : int, optional
        Odd stamp side, pixels; by default it covers +-6 sigma of the widest epoch.

    Returns
    -------
    ndarray, shape (n_epochs, stamp_size, stamp_size)
        Templates in flux per pixel for unit total flux.
    """
    psf_sigma = psf_fwhm / FWHM_PER_SIGMA
    if psf_sigmas is None:
        psf_sigmas = epoch_psf_sigmas(n_epochs, psf_sigma, dsigma_over_sigma, rng)
    psf_sigmas = np.asarray(psf_sigmas, dtype=float)
    gal_sigma = galaxy_sigma(resolution, float(psf_sigmas.mean()))
    if stamp_size is None:
        stamp_size = _stamp_size(float(np.hypot(gal_sigma, psf_sigmas.max())), pixel_scale)
    if stamp_size % 2 == 0:
        raise CellCoaddValueError(
            f"stamp_size must be odd so the object sits on a pixel centre: {stamp_size}",
            value=stamp_size,
        )
    templates = np.empty((psf_sigmas.size, stamp_size, stamp_size))
    for epoch, sigma_p in enumerate(psf_sigmas):
        profile: galsim.GSObject = galsim.Gaussian(sigma=float(sigma_p))
        if gal_sigma > 0:
            profile = galsim.Convolve(galsim.Gaussian(sigma=gal_sigma), profile)
        image = profile.drawImage(nx=stamp_size, ny=stamp_size, scale=pixel_scale)
        templates[epoch] = image.array
    return templates


def continuous_gaussian_ratio(object_sigmas: np.ndarray) -> float:
    """Exact straight-mean variance ratio for unpixelised circular Gaussians (no pixel noise grid).

    For unit-flux Gaussians ``m_i . m_j = 1 / (2 pi (s_i^2 + s_j^2))``, so eqs. A5 / A7 give
    ``ratio = sum_i 1/(2 s_i^2) / ((1/N) sum_ij 1/(s_i^2 + s_j^2))``.

    Parameters
    ----------
    object_sigmas : ndarray, shape (n_epochs,)
        Observed (PSF-convolved) object sigma in each epoch, any unit.
    """
    s2 = np.asarray(object_sigmas, dtype=float) ** 2
    numerator = np.sum(1.0 / (2.0 * s2))
    denominator = np.sum(1.0 / (s2[:, None] + s2[None, :])) / s2.size
    return float(numerator / denominator)
