"""Flux S/N lost by fitting a coadd instead of all epochs jointly (paper section 5.1, appendix A).

For a linear ("matched filter") fit of the amplitude ``A`` of a template ``m`` to data with
noise covariance ``C`` the estimator variance is ``1 / (m^T C^-1 m)``. Fitting every epoch
jointly uses the per-epoch templates ``m_i`` (paper eq. A7); fitting a coadd uses the coadded
template ``m_coadd = sum w_i m_i / sum w_i`` and the coadd covariance
``C_coadd = sum w_i^2 C_i / (sum w_i)^2`` (paper eq. A5, written there for the straight mean
``w_i = 1``). The coadd estimator is linear and unbiased, so by the Gauss-Markov theorem its
variance is never below the joint fit's: the ratio is >= 1, with equality when all templates
agree (and the weights are inverse-variance). For Gaussian galaxies and PSFs whose size scatters
by ``dsigma_p / sigma_p`` between epochs, the paper's toy model (eq. 10, derived at the end of
appendix A) gives ``1 + 2 (1 - R)^2 (dsigma_p / sigma_p)^2`` with
``R = sigma_g^2 / (sigma_g^2 + sigma_p^2)``.

The Gaussian templates of the paper's test come from :mod:`cellcoadd.analysis.gaussian_epochs`.
Templates here are pixel arrays of shape ``(n_epochs, ny, nx)`` on one common grid (the
objects sit at the same sub-pixel position in every epoch, so no resampling is involved) and
the noise is diagonal (independent pixels).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np

from cellcoadd.analysis.gaussian_epochs import (
    FWHM_PER_SIGMA,
    continuous_gaussian_ratio,
    epoch_psf_sigmas,
    galaxy_sigma,
    gaussian_templates,
)
from cellcoadd.errors import CellCoaddRangeError, CellCoaddValueError

__all__ = [
    "SnrLossTable",
    "coadd_template",
    "exact_ratio_curve",
    "exact_variance_ratio",
    "lsst_snr_loss",
    "monte_carlo_ratio",
    "toy_variance_ratio",
    "variance_coadd",
    "variance_multi",
    "variance_ratio_with_error",
]

PsfSizeDraw = Literal["quantiles", "random"]


def _noise_sigma_array(templates: np.ndarray, noise_sigma: float | np.ndarray) -> np.ndarray:
    """Broadcast a scalar, per-epoch ``(N,)`` or per-pixel noise sigma to the template shape."""
    sigma = np.asarray(noise_sigma, dtype=float)
    if sigma.ndim == 1:
        if sigma.shape[0] != templates.shape[0]:
            raise CellCoaddValueError(
                f"per-epoch noise_sigma has {sigma.shape[0]} values for {templates.shape[0]} epochs"
            )
        sigma = sigma[:, None, None]
    sigma = np.broadcast_to(sigma, templates.shape)
    if not np.all(np.isfinite(sigma) & (sigma > 0)):
        raise CellCoaddValueError("noise_sigma must be finite and positive everywhere")
    return sigma


def _as_templates(templates: np.ndarray) -> np.ndarray:
    array = np.asarray(templates, dtype=float)
    if array.ndim != 3 or array.shape[0] < 1:
        raise CellCoaddValueError(
            f"templates must have shape (n_epochs, ny, nx), got {array.shape}", value=array.shape
        )
    return array


def variance_multi(templates: np.ndarray, noise_sigma: float | np.ndarray = 1.0) -> float:
    """Variance of the joint multi-epoch amplitude fit, paper eq. A7.

    Parameters
    ----------
    templates : ndarray, shape (n_epochs, ny, nx)
        Template ``m_i`` of each epoch (flux per pixel for unit amplitude).
    noise_sigma : float or ndarray
        Noise standard deviation per pixel: a scalar, one value per epoch ``(n_epochs,)`` or
        one per pixel (template shape). Same units as the templates times the amplitude.

    Returns
    -------
    float
        ``1 / sum_i m_i^T C_i^-1 m_i`` (amplitude units squared).
    """
    m = _as_templates(templates)
    sigma = _noise_sigma_array(m, noise_sigma)
    return float(1.0 / np.sum(m**2 / sigma**2))


def coadd_template(templates: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Weighted mean template ``sum w_i m_i / sum w_i`` (straight mean when ``weights`` is None)."""
    m = _as_templates(templates)
    w = _epoch_weights(m.shape[0], weights)
    return np.tensordot(w, m, axes=1) / w.sum()


def _epoch_weights(n_epochs: int, weights: np.ndarray | None) -> np.ndarray:
    if weights is None:
        return np.ones(n_epochs)
    w = np.asarray(weights, dtype=float)
    if w.shape != (n_epochs,) or not np.all(np.isfinite(w) & (w >= 0)) or w.sum() <= 0:
        raise CellCoaddValueError(
            f"weights must be {n_epochs} finite non-negative numbers, not all zero"
        )
    return w


def variance_coadd(
    templates: np.ndarray,
    noise_sigma: float | np.ndarray = 1.0,
    weights: np.ndarray | None = None,
) -> float:
    """Variance of the amplitude fitted on the weighted-mean coadd, paper eq. A5.

    Parameters
    ----------
    templates : ndarray, shape (n_epochs, ny, nx)
        Template ``m_i`` of each epoch.
    noise_sigma : float or ndarray
        Noise standard deviation per pixel (scalar, per epoch or per pixel), as in
        :func:`variance_multi`.
    weights : ndarray, shape (n_epochs,), optional
        Scalar coadd weight of each epoch; the straight mean of the paper when omitted.

    Returns
    -------
    float
        ``1 / (m_coadd^T C_coadd^-1 m_coadd)`` with ``C_coadd = sum w_i^2 C_i / (sum w_i)^2``.
    """
    m = _as_templates(templates)
    sigma = _noise_sigma_array(m, noise_sigma)
    w = _epoch_weights(m.shape[0], weights)
    m_coadd = np.tensordot(w, m, axes=1) / w.sum()
    var_coadd_pixels = np.tensordot(w**2, sigma**2, axes=1) / w.sum() ** 2
    return float(1.0 / np.sum(m_coadd**2 / var_coadd_pixels))


def exact_variance_ratio(
    templates: np.ndarray,
    noise_sigma: float | np.ndarray = 1.0,
    weights: np.ndarray | None = None,
) -> float:
    """``var(A_coadd) / var(A_multi)`` from the exact expressions (paper eqs. A5 / A7); >= 1."""
    return variance_coadd(templates, noise_sigma, weights) / variance_multi(templates, noise_sigma)


def toy_variance_ratio(
    resolution: float | np.ndarray, dsigma_over_sigma: float | np.ndarray
) -> float | np.ndarray:
    """Toy-model variance ratio ``1 + 2 (1 - R)^2 (dsigma_p / sigma_p)^2``, paper eq. 10.

    Parameters
    ----------
    resolution : float or ndarray
        ``R = sigma_g^2 / (sigma_g^2 + sigma_p^2)``, 0 for a star.
    dsigma_over_sigma : float or ndarray
        RMS scatter of the PSF size across epochs relative to the mean PSF size.
    """
    ratio = 1.0 + 2.0 * (1.0 - np.asarray(resolution)) ** 2 * np.asarray(dsigma_over_sigma) ** 2
    return float(ratio) if np.ndim(ratio) == 0 else ratio


def exact_ratio_curve(
    resolutions: Sequence[float] | np.ndarray,
    dsigma_over_sigma: float = 0.1,
    n_epochs: int = 10,
    psf_fwhm: float = 0.9,
    pixel_scale: float = 0.26,
) -> np.ndarray:
    """Exact (pixelised, GalSim-drawn) variance ratio at each ``R`` with quantile PSF sizes."""
    return np.array(
        [
            exact_variance_ratio(
                gaussian_templates(r, n_epochs, dsigma_over_sigma, psf_fwhm, pixel_scale)
            )
            for r in resolutions
        ]
    )


def variance_ratio_with_error(coadd: np.ndarray, multi: np.ndarray) -> tuple[float, float]:
    """Ratio of sample variances of two paired estimators and its delta-method standard error.

    The error uses the sample fourth moments, so it is valid for any distribution and
    accounts for the strong correlation between the two estimators (same noise).
    """
    x = coadd - coadd.mean()
    y = multi - multi.mean()
    n = x.size
    var_x, var_y = np.mean(x**2), np.mean(y**2)
    ratio = var_x / var_y
    rel_var = (
        (np.mean(x**4) / var_x**2 - 1.0)
        + (np.mean(y**4) / var_y**2 - 1.0)
        - 2.0 * (np.mean(x**2 * y**2) / (var_x * var_y) - 1.0)
    ) / n
    return float(ratio), float(ratio * np.sqrt(max(rel_var, 0.0)))


def _fit_amplitudes(
    templates: np.ndarray,
    n_trials: int,
    noise_sigma: float,
    flux: float,
    rng: np.random.Generator,
    chunk_elements: int = 4_000_000,
) -> tuple[np.ndarray, np.ndarray]:
    """Matched-filter amplitudes on the straight-mean coadd and jointly on the epochs.

    Uniform white noise ``noise_sigma`` in every epoch, so both least-squares fits reduce to
    normalised projections onto the true templates.
    """
    n_epochs = templates.shape[0]
    m = templates.reshape(n_epochs, -1)
    m_coadd = m.mean(axis=0)
    norm_multi = np.sum(m * m)
    norm_coadd = np.dot(m_coadd, m_coadd)
    # Single precision cuts the cost of the normal draws by a third; projections lose ~1e-7
    # relative, far below the Monte Carlo error.
    signal = (flux * m).astype(np.float32)
    m32, m_coadd32 = m.astype(np.float32).ravel(), m_coadd.astype(np.float32)
    per_chunk = max(1, chunk_elements // m.size)
    coadd_fit, multi_fit = np.empty(n_trials), np.empty(n_trials)
    for start in range(0, n_trials, per_chunk):
        stop = min(start + per_chunk, n_trials)
        noise = rng.standard_normal((stop - start, *m.shape), dtype=np.float32)
        data = signal + np.float32(noise_sigma) * noise
        multi_fit[start:stop] = data.reshape(stop - start, -1) @ m32 / norm_multi
        coadd_fit[start:stop] = data.mean(axis=1) @ m_coadd32 / norm_coadd
    return coadd_fit, multi_fit


@dataclass(frozen=True)
class SnrLossTable:
    """Monte Carlo, exact and toy variance ratios ``var(A_coadd) / var(A_multi)`` versus ``R``.

    Attributes
    ----------
    resolution : ndarray
        ``R`` of each row.
    ratio_mc, ratio_mc_err : ndarray
        Measured ratio of the sample variances and its standard error.
    ratio_exact : ndarray
        Exact prediction (eqs. A5 / A7) for the same templates (mean over PSF-size sets of
        each variance when the sizes are random).
    ratio_toy : ndarray
        Toy model, eq. 10.
    dsigma_over_sigma, n_epochs, n_trials, psf_fwhm, pixel_scale, psf_sizes, n_psf_sets, seed
        The settings that produced the table.
    """

    resolution: np.ndarray
    ratio_mc: np.ndarray
    ratio_mc_err: np.ndarray
    ratio_exact: np.ndarray
    ratio_toy: np.ndarray
    dsigma_over_sigma: float
    n_epochs: int
    n_trials: int
    psf_fwhm: float
    pixel_scale: float
    psf_sizes: str
    n_psf_sets: int
    seed: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable copy (arrays become lists)."""
        return {k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in asdict(self).items()}

    def to_text(self) -> str:
        """Fixed-width table, one row per ``R``, with the deviation of MC from exact in sigmas."""
        lines = [
            f"var(A_coadd)/var(A_multi): dsigma_p/sigma_p={self.dsigma_over_sigma:g}, "
            f'{self.n_epochs} epochs, PSF FWHM {self.psf_fwhm:g}", {self.pixel_scale:g}"/px, '
            f"{self.n_trials} trials, PSF sizes: {self.psf_sizes}",
            f"{'R':>6} {'MC':>9} {'+-':>8} {'exact':>9} {'toy':>9} {'(MC-exact)/err':>15}",
        ]
        for row in zip(
            self.resolution,
            self.ratio_mc,
            self.ratio_mc_err,
            self.ratio_exact,
            self.ratio_toy,
            strict=True,
        ):
            r, mc, err, exact, toy = (float(v) for v in row)
            pull = (mc - exact) / err if err > 0 else float("nan")
            lines.append(f"{r:6.3f} {mc:9.5f} {err:8.5f} {exact:9.5f} {toy:9.5f} {pull:15.2f}")
        return "\n".join(lines)


def monte_carlo_ratio(
    resolutions: Sequence[float] | np.ndarray = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.83),
    dsigma_over_sigma: float = 0.1,
    n_epochs: int = 10,
    n_trials: int = 4000,
    seed: int = 0,
    *,
    psf_fwhm: float = 0.9,
    pixel_scale: float = 0.26,
    psf_sizes: PsfSizeDraw = "quantiles",
    n_psf_sets: int = 1,
    noise_sigma: float = 1.0,
    flux: float = 100.0,
) -> SnrLossTable:
    """Reproduce the paper's Fig. 4: measured coadd/multi-epoch flux variance ratio versus ``R``.

    Objects sit at the stamp centre in every epoch (no interpolation), all epochs have the
    same white noise, the coadd is the straight mean, and the flux is fitted by linear least
    squares with the true templates, on the coadd and jointly on all epochs. Noise is drawn
    directly in pixel space; both estimators are linear in it.

    Parameters
    ----------
    resolutions : sequence of float
        Values of ``R`` in [0, 1).
    dsigma_over_sigma : float
        Relative RMS scatter of the PSF sigma between epochs (0.1 in the paper).
    n_epochs : int
        Epochs per object (10 in the paper's simulations).
    n_trials : int
        Noise realizations per ``R`` (split evenly between PSF-size sets).
    seed : int
        Seed of the single random stream (noise and, if random, PSF sizes).
    psf_fwhm, pixel_scale : float
        Mean PSF FWHM (arcsec) and pixel scale (arcsec/pixel).
    psf_sizes : "quantiles" or "random"
        Deterministic representative PSF sizes, or ``n_psf_sets`` independent normal draws.
    n_psf_sets : int
        Number of PSF-size sets when ``psf_sizes="random"``.
    noise_sigma, flux : float
        Pixel noise sigma and true flux (neither changes the ratio).

    Returns
    -------
    SnrLossTable
    """
    if psf_sizes not in ("quantiles", "random"):
        raise CellCoaddValueError(
            f"psf_sizes must be 'quantiles' or 'random', got {psf_sizes!r}",
            value=psf_sizes,
            allowed=("quantiles", "random"),
        )
    n_sets = n_psf_sets if psf_sizes == "random" else 1
    if n_trials < 10 * n_sets:
        raise CellCoaddRangeError(
            f"need at least 10 trials per PSF-size set, got {n_trials} for {n_sets}",
            value=n_trials,
            low=10 * n_sets,
        )
    rng = np.random.default_rng(seed)
    psf_sigma = psf_fwhm / FWHM_PER_SIGMA
    trials_per_set = np.full(n_sets, n_trials // n_sets)
    trials_per_set[: n_trials % n_sets] += 1
    rows: list[tuple[float, float, float]] = []
    for resolution in resolutions:
        coadd_fits, multi_fits, var_coadd, var_multi = [], [], 0.0, 0.0
        for set_trials in trials_per_set:
            sigmas = epoch_psf_sigmas(
                n_epochs, psf_sigma, dsigma_over_sigma, rng if psf_sizes == "random" else None
            )
            templates = gaussian_templates(
                float(resolution), psf_sigmas=sigmas, pixel_scale=pixel_scale
            )
            var_coadd += variance_coadd(templates, noise_sigma) / n_sets
            var_multi += variance_multi(templates, noise_sigma) / n_sets
            coadd_fit, multi_fit = _fit_amplitudes(
                templates, int(set_trials), noise_sigma, flux, rng
            )
            coadd_fits.append(coadd_fit)
            multi_fits.append(multi_fit)
        ratio, err = variance_ratio_with_error(
            np.concatenate(coadd_fits), np.concatenate(multi_fits)
        )
        rows.append((ratio, err, var_coadd / var_multi))
    values = np.array(rows).reshape(-1, 3)
    resolution_array = np.asarray(resolutions, dtype=float)
    return SnrLossTable(
        resolution=resolution_array,
        ratio_mc=values[:, 0],
        ratio_mc_err=values[:, 1],
        ratio_exact=values[:, 2],
        ratio_toy=np.asarray(toy_variance_ratio(resolution_array, dsigma_over_sigma)),
        dsigma_over_sigma=dsigma_over_sigma,
        n_epochs=n_epochs,
        n_trials=n_trials,
        psf_fwhm=psf_fwhm,
        pixel_scale=pixel_scale,
        psf_sizes=psf_sizes,
        n_psf_sets=n_sets,
        seed=seed,
    )


def lsst_snr_loss(
    resolutions: Sequence[float] = (0.0, 0.8),
    dsigma_over_sigma: float = 0.3,
    psf_sigma: float = 0.4,
    pixel_scale: float = 0.2,
    n_epochs: int = 10,
) -> dict[str, np.ndarray]:
    """The paper's LSST estimate: ``dsigma_p/sigma_p ~ 0.3``, ``sigma_p ~ 0.4"`` (section 5.1).

    Returns
    -------
    dict
        ``resolution``; ``exact`` (pixelised, quantile PSF sizes); ``continuous`` (same sizes,
        no pixels); ``toy`` (eq. 10), all variance ratios; ``noise_exact``, its square root.
    """
    sigmas = epoch_psf_sigmas(n_epochs, psf_sigma, dsigma_over_sigma)
    resolution = np.asarray(resolutions, dtype=float)
    exact, continuous = [], []
    for r in resolution:
        templates = gaussian_templates(float(r), psf_sigmas=sigmas, pixel_scale=pixel_scale)
        exact.append(exact_variance_ratio(templates))
        gal = galaxy_sigma(float(r), float(sigmas.mean()))
        continuous.append(continuous_gaussian_ratio(np.hypot(gal, sigmas)))
    exact_array = np.array(exact)
    return {
        "resolution": resolution,
        "exact": exact_array,
        "continuous": np.array(continuous),
        "toy": np.asarray(toy_variance_ratio(resolution, dsigma_over_sigma)),
        "noise_exact": np.sqrt(exact_array),
    }
