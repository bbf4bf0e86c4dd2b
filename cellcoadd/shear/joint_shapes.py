"""Shapes measured jointly on several epochs of one object (multi-epoch metacalibration).

Every epoch keeps its own pixels. A Gaussian weight ``W`` is defined once *in sky
coordinates* (arcsec, GalSim ``u`` West / ``v`` North, about the object's reference sky
position) and evaluated at each epoch's pixel centres through that epoch's jacobian; each
epoch gives the sums of :func:`~cellcoadd.shear.shapes.gaussian_moment_sums` (``sum W I``,
``sum W I u``, ..., ``sum W^2``). Pixel values are fluxes per pixel, so ``sum W I`` is a
Riemann sum of ``integral W S dA`` (``S`` the surface brightness) and every epoch
estimates the same quantities when their images share one PSF (after metacalibration,
the common reconvolution PSF). The joint sums are their weighted mean with the
*inverse-variance* epoch weights

``w_k = A_k / var_k``

(``A_k`` the pixel area, arcsec^2, ``var_k`` the pixel noise variance of epoch ``k``): in
the continuum limit ``Var(sum W I) = var_k sum W^2 ~ var_k integral W^2 dA / A_k``, so
``w_k`` is proportional to the inverse variance of each epoch's sums, and it depends
neither on the signal nor on the weight. Zero variances (noise-free images) fall back to
``w_k = A_k``. The variance of the joint ``F = sum W I`` is
``sum_k w_k^2 var_k sum W_k^2 / (sum_k w_k)^2``, which sets the S/N.

Two estimators, the multi-epoch versions of :mod:`cellcoadd.shear.shapes`:

* ``wmom`` (:func:`joint_wmom`): the round weight of FWHM ``weight_fwhm`` centred on the
  reference position; ``e = (M_uu - M_vv, 2 M_uv) / T`` from the joint normalised
  moments. With one epoch it is :func:`~cellcoadd.shear.shapes.measure_wmom` exactly.
* ``admom`` (:func:`joint_admom`): joint adaptive moments. The weight (centre ``c``,
  covariance ``Sigma``) is iterated to the fixed point of GalSim's HSM (Hirata & Seljak
  2003), ``B = 0`` and ``Sigma = 2 C / F`` (``F``, ``B``, ``C`` the joint sums of order 0,
  1, 2 about ``c``), now on the joint sums: each step is the one that is exact for a
  Gaussian profile (``M^-1 = G^-1 + Sigma^-1`` for a Gaussian ``G`` seen through the
  weight, ``M`` the weighted covariance), or HSM's own step (``c += 2 B / F``,
  ``Sigma = 2 C / F``) when that one is ill-defined, until centre and covariance change by
  less than ``tol``. The shape is the reduced shear of ``Sigma``, ``T = Sigma_uu +
  Sigma_vv``, the S/N that of the joint flux in the converged weight. Each metacal type
  runs the whole iteration itself (the same function of the images for every type, as
  metacalibration needs). With one epoch it agrees with HSM's adaptive moments to a few
  1e-6 (HSM stops at its own tolerance and truncates the weight beyond ``rho^2 = 25``;
  here every pixel counts).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import galsim
import numpy as np

from cellcoadd.errors import ShearError
from cellcoadd.geometry.wcs_utils import jacobian_wcs
from cellcoadd.shear.noise_correlation import covariance_flux_variance
from cellcoadd.shear.shapes import (
    SHAPE_DTYPE,
    MetacalFlags,
    empty_record,
    gaussian_moment_sums,
    gaussian_weight_image,
    round_inverse_cov,
    sky_offsets,
    wmom_record,
)

__all__ = ["EpochPixels", "joint_admom", "joint_psf_T", "joint_sums", "joint_wmom"]

#: Convergence of :func:`joint_admom`: changes of the centre (arcsec) and of the weight's
#: covariance (relative to its trace) below this.
ADMOM_TOL = 1.0e-8
#: Iterations of :func:`joint_admom` before it gives up (HSM allows 400).
ADMOM_MAX_ITER = 400


@dataclass(frozen=True, eq=False)
class EpochPixels:
    """One epoch's image for a joint measurement.

    Attributes
    ----------
    image : ndarray, shape (ny, nx)
        Pixel values (flux per pixel, image units), indexed ``[y, x]``.
    jacobian : ndarray, shape (2, 2)
        ``[[du/dx, du/dy], [dv/dx, dv/dy]]`` (arcsec/pixel).
    centre : (float, float)
        0-based pixel position ``(x, y)`` of the object's reference sky position.
    variance : float
        Pixel noise variance (image units squared); 0 for a noise-free image.
    u, v : ndarray, shape (ny, nx)
        Sky offsets (arcsec) of the pixel centres from the reference position.
    noise_covariance : ndarray or None
        Autocovariance of the epoch's noise (as
        :func:`~cellcoadd.shear.noise_correlation.noise_covariance` lays it out), for the
        S/N; None: white noise of ``variance``. The epochs' relative weights use
        ``variance`` either way.
    """

    image: np.ndarray
    jacobian: np.ndarray
    centre: tuple[float, float]
    variance: float
    u: np.ndarray
    v: np.ndarray
    noise_covariance: np.ndarray | None = None

    @classmethod
    def from_image(
        cls,
        image: np.ndarray,
        jacobian: np.ndarray,
        centre: tuple[float, float],
        variance: float,
        noise_covariance: np.ndarray | None = None,
    ) -> EpochPixels:
        """Make the epoch's sky offsets from its jacobian and reference pixel."""
        array = np.ascontiguousarray(image, dtype=np.float64)
        jac = np.asarray(jacobian, dtype=np.float64)
        centre = (float(centre[0]), float(centre[1]))
        u, v = sky_offsets(array.shape, jacobian_wcs(jac), centre)
        return cls(array, jac, centre, float(variance), u, v, noise_covariance)

    @property
    def pixel_area(self) -> float:
        """Pixel area, arcsec^2."""
        return float(abs(np.linalg.det(self.jacobian)))


def _epoch_weights(epochs: Sequence[EpochPixels]) -> np.ndarray:
    areas = np.array([e.pixel_area for e in epochs])
    variances = np.array([e.variance for e in epochs])
    if np.all(variances > 0.0):
        return areas / variances
    return areas


def joint_sums(
    epochs: Sequence[EpochPixels],
    inverse_cov: np.ndarray,
    offset: tuple[float, float] | np.ndarray = (0.0, 0.0),
) -> tuple[np.ndarray, float]:
    """Inverse-variance weighted mean of the epochs' Gaussian-weighted sums.

    Parameters
    ----------
    epochs : sequence of EpochPixels
        At least one.
    inverse_cov : ndarray, shape (2, 2)
        Inverse covariance of the weight (arcsec^-2), in sky coordinates.
    offset : (du, dv)
        Centre of the weight relative to the reference position, arcsec.

    Returns
    -------
    sums : ndarray, shape (7,)
        The joint :func:`~cellcoadd.shear.shapes.gaussian_moment_sums` (moments about the
        weight's centre); entry 6 is the weighted mean of ``sum W^2``.
    flux_variance : float
        Noise variance of ``sums[0]`` (image units squared): from each epoch's
        ``noise_covariance`` where it is given, else white noise of its ``variance``.
    """
    if not epochs:
        raise ShearError("a joint measurement needs at least one epoch")
    weights = _epoch_weights(epochs)
    du, dv = float(offset[0]), float(offset[1])
    total = np.zeros(7)
    flux_variance = 0.0
    for weight, epoch in zip(weights, epochs, strict=True):
        sums = gaussian_moment_sums(epoch.image, epoch.u - du, epoch.v - dv, inverse_cov)
        total += weight * sums
        if epoch.noise_covariance is None:
            flux_variance += weight * weight * epoch.variance * sums[6]
        else:
            window = gaussian_weight_image(epoch.u - du, epoch.v - dv, inverse_cov)
            flux_variance += (
                weight * weight * covariance_flux_variance(epoch.noise_covariance, window)
            )
    norm = float(np.sum(weights))
    return total / norm, flux_variance / norm**2


def _pixel_position(epoch: EpochPixels, offset: np.ndarray) -> tuple[float, float]:
    """Pixel position in ``epoch`` of the sky offset ``offset`` from the reference."""
    dx, dy = np.linalg.solve(epoch.jacobian, offset)
    return (epoch.centre[0] + float(dx), epoch.centre[1] + float(dy))


def joint_wmom(epochs: Sequence[EpochPixels], weight_fwhm: float) -> np.ndarray:
    """Joint fixed-weight moments shape (see the module docstring) as a length-1 record.

    ``x, y`` are the reference position in the first epoch's pixels; ``flux`` is the joint
    ``sum W I``; ``T_psf`` is left 0 for the caller (:func:`joint_psf_T`).
    """
    if not all(np.all(np.isfinite(e.image)) for e in epochs):
        return empty_record(MetacalFlags.NONFINITE)
    sums, flux_variance = joint_sums(epochs, round_inverse_cov(weight_fwhm))
    return wmom_record(sums, flux_variance, epochs[0].centre)


def _positive_definite(matrix: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(matrix)) and matrix[0, 0] > 0.0 and np.linalg.det(matrix) > 0.0)


def _admom_step(sums: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """The next centre offset and weight covariance from the sums in weight ``cov``.

    The weighted mean ``m`` and covariance ``M`` of a Gaussian object of covariance ``G``
    seen through the weight satisfy ``M^-1 = G^-1 + cov^-1`` and ``m = M G^-1 (x - c)``:
    the step to ``G`` and to its centre ``x`` is exact for a Gaussian (a few iterations
    for a galaxy). When ``M^-1 - cov^-1`` is not positive definite, or the step would
    more than double or halve the weight, HSM's step (``c += 2 m``, ``cov = 2 C / F``, the
    fixed point being the same) is taken instead. ``None``: the moments are unusable.
    """
    flux = sums[0]
    if not flux > 0.0:
        return np.zeros(2), None
    mean = sums[1:3] / flux
    raw = np.array([[sums[3], sums[5]], [sums[5], sums[4]]]) / flux
    second = raw - np.outer(mean, mean)
    if _positive_definite(second):
        precision = np.linalg.inv(second) - np.linalg.inv(cov)
        if _positive_definite(precision):
            target = np.linalg.inv(precision)
            ratio = np.trace(target) / np.trace(cov)
            if 0.5 < ratio < 2.0:
                return target @ np.linalg.solve(second, mean), target
    hsm = 2.0 * raw
    return 2.0 * mean, hsm if _positive_definite(hsm) else None


def joint_admom(
    epochs: Sequence[EpochPixels],
    guess_sigma: float,
    tol: float = ADMOM_TOL,
    max_iter: int = ADMOM_MAX_ITER,
) -> np.ndarray:
    """Joint adaptive-moments shape (see the module docstring) as a length-1 record.

    Parameters
    ----------
    epochs : sequence of EpochPixels
        The epochs, all of the same object and PSF.
    guess_sigma : float
        Sigma (arcsec) of the round starting weight, centred on the reference position.
    tol : float
        Convergence threshold (arcsec for the centre, relative to ``T`` for the covariance).
    max_iter : int
        Iterations before the measurement is flagged ``HSM_FAILED``.

    Returns
    -------
    ndarray
        Length-1 :data:`~cellcoadd.shear.shapes.SHAPE_DTYPE` array: ``g1, g2`` the reduced
        shear of the converged weight, ``T`` its trace (arcsec^2), ``flux`` the amplitude
        of the matching Gaussian (``2 sum W I``), ``s2n`` of the joint ``sum W I``, ``x, y``
        the centre in the first epoch's pixels; ``T_psf`` is left 0. Failures are flagged.
    """
    if not all(np.all(np.isfinite(e.image)) for e in epochs):
        return empty_record(MetacalFlags.NONFINITE)
    if not (np.isfinite(guess_sigma) and guess_sigma > 0.0):
        return empty_record(MetacalFlags.HSM_FAILED)
    # the weight may not outgrow the largest stamp (as HSM bounds its moments)
    limit = max(e.pixel_area * e.image.size for e in epochs)
    centre = np.zeros(2)
    cov = np.eye(2) * guess_sigma**2
    for _ in range(max_iter):
        sums, flux_variance = joint_sums(epochs, np.linalg.inv(cov), centre)
        step, new_cov = _admom_step(sums, cov)
        if new_cov is None:
            return empty_record(MetacalFlags.HSM_FAILED)
        trace = new_cov[0, 0] + new_cov[1, 1]
        if trace > limit or np.hypot(*(centre + step)) ** 2 > limit:
            return empty_record(MetacalFlags.HSM_FAILED)
        change = max(float(np.hypot(*step)), float(np.max(np.abs(new_cov - cov))) / trace)
        centre = centre + step
        cov = new_cov
        if change < tol:
            break
    else:
        return empty_record(MetacalFlags.HSM_FAILED)
    # the sums in the converged weight about the converged centre
    sums, flux_variance = joint_sums(epochs, np.linalg.inv(cov), centre)
    flux = float(sums[0])
    T = float(cov[0, 0] + cov[1, 1])
    shape = galsim.Shear(e1=(cov[0, 0] - cov[1, 1]) / T, e2=2.0 * cov[0, 1] / T)
    if flux_variance > 0.0:
        s2n = flux / np.sqrt(flux_variance)
    else:
        s2n = np.inf if flux > 0.0 else np.nan
    record = np.zeros(1, dtype=SHAPE_DTYPE)
    record["g1"] = shape.g1
    record["g2"] = shape.g2
    record["T"] = T
    record["flux"] = 2.0 * flux
    record["s2n"] = s2n
    record["x"], record["y"] = _pixel_position(epochs[0], centre)
    if not (flux > 0.0 and s2n > 0.0):
        record["flags"] = MetacalFlags.NONPOSITIVE_FLUX
    return record


def joint_psf_T(
    psf_images: Sequence[np.ndarray],
    epochs: Sequence[EpochPixels],
    weight_fwhm: float | None = None,
) -> float:
    """``T`` (arcsec^2) of PSF stamps measured jointly like the epochs' images.

    Each stamp (odd, centred on its central pixel, on the pixel grid of the epoch of the
    same rank) enters with that epoch's weight. ``weight_fwhm`` None: joint adaptive
    moments (started at the stamp's second moment); otherwise the joint moments in the
    round ``wmom`` weight of that FWHM. NaN when the measurement fails.

    Parameters
    ----------
    psf_images : sequence of ndarray
        One PSF stamp per epoch (the same PSF drawn on each epoch's grid).
    epochs : sequence of EpochPixels
        The epochs whose jacobians and weights the stamps share.
    weight_fwhm : float, optional
        FWHM (arcsec) of the ``wmom`` weight; None for adaptive moments.
    """
    stamps = [
        EpochPixels.from_image(psf, e.jacobian, (psf.shape[1] // 2, psf.shape[0] // 2), e.variance)
        for psf, e in zip(psf_images, epochs, strict=True)
    ]
    if weight_fwhm is not None:
        record = joint_wmom(stamps, weight_fwhm)
    else:
        # HSM's default start: 5 pixels
        record = joint_admom(stamps, 5.0 * np.sqrt(stamps[0].pixel_area))
    if record["flags"][0] != 0:
        return float("nan")
    return float(record["T"][0])
