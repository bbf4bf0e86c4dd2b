"""Shape of one image: the shape record, its flags and two measurements.

``"admom"`` (:func:`measure_shape`): GalSim HSM adaptive moments converted to sky
coordinates by the image's WCS (``u`` West, ``v`` North): the reduced shear ``g = (a - b) /
(a + b) * (cos 2 phi, sin 2 phi)`` (GalSim ``observed_shape``) and ``T = Ixx + Iyy`` in
arcsec^2. The S/N is that of the flux in the matched (adaptive) Gaussian weight.

``"wmom"`` (:func:`measure_wmom`): moments in a *fixed* round Gaussian weight of FWHM
``weight_fwhm`` arcsec centred on a fixed position (the ``wmom`` estimator of ngmix /
metadetect): with ``W`` the weight and ``(u, v)`` sky offsets from the centre,
``F = sum W I``, ``M_ij = sum W I u_i u_j / F``, ``T = M_uu + M_vv`` and the polarisation
``e = (M_uu - M_vv, 2 M_uv) / T`` reported as ``g1, g2`` (metacalibration calibrates any
estimator; for a round Gaussian of sigma ``s`` sheared by ``g``, weight sigma ``w``,
``e = 2 w^2 / (s^2 + w^2) g`` to first order). Nothing is iterated, so it cannot fail to
converge at low S/N; the S/N is ``F / sqrt(var F)``.

**S/N and correlated noise.** ``var F`` is ``var sum W^2`` for white noise of pixel
variance ``var``; given the noise's autocovariance ``C`` (``noise_covariance=``, as
:func:`~cellcoadd.shear.noise_correlation.noise_covariance` lays it out) it is
``sum_lag C(lag) R_W(lag)``, ``R_W`` the autocorrelation of the weight: the true variance
whatever correlates the noise (a coadd's resampling, metacalibration's reconvolution), so
the same S/N cut means the same thing on coadds, single epochs and joint epochs.
"""

from __future__ import annotations

import enum
from typing import Literal

import galsim
import numpy as np

from cellcoadd.shear.noise_correlation import covariance_flux_variance

#: One measured shape per row; ``T`` and ``T_psf`` in arcsec^2, ``flux`` in image units
#: (sum of pixel values), ``x, y`` the 0-based pixel centroid.
SHAPE_DTYPE = np.dtype(
    [("flags", "i4")]
    + [(name, "f8") for name in ("g1", "g2", "T", "T_psf", "flux", "s2n", "x", "y")]
)


#: Shape estimators: adaptive moments, or moments in a fixed Gaussian weight.
ShapeKind = Literal["admom", "wmom"]
SHAPE_KINDS: tuple[str, ...] = ("admom", "wmom")
#: Default FWHM (arcsec) of the fixed ``wmom`` weight (metadetect's choice for LSST/DES).
WMOM_FWHM = 1.2


class MetacalFlags(enum.IntFlag):
    """Bits of the ``flags`` field of :data:`SHAPE_DTYPE` (0 means a good measurement)."""

    HSM_FAILED = 1  #: adaptive moments did not converge on the metacal image
    NONPOSITIVE_FLUX = 2  #: weighted flux <= 0 or a non-finite S/N
    PSF_FAILED = 4  #: the PSF is unusable or its moments failed
    NONFINITE = 8  #: non-finite pixels in the image or the noise image
    TRANSFORM_FAILED = 16  #: GalSim could not build or draw the metacal images


def empty_record(flags: int) -> np.ndarray:
    """A length-1 :data:`SHAPE_DTYPE` array flagged ``flags``, every other field NaN."""
    record = np.zeros(1, dtype=SHAPE_DTYPE)
    assert SHAPE_DTYPE.names is not None  # a structured dtype
    for name in SHAPE_DTYPE.names:
        if name != "flags":
            record[name] = np.nan
    record["flags"] = flags
    return record


def _sky_T(sigma: float, shape: galsim.Shear) -> float:
    # T = Ixx + Iyy for moments with det(M)^(1/4) = sigma and distortion |e|.
    return 2.0 * sigma**2 / np.sqrt(1.0 - shape.e**2)


def measure_shape(
    array: np.ndarray,
    wcs: galsim.BaseWCS,
    noise_variance: float,
    guess_centroid: tuple[float, float] | None,
    guess_sigma: float,
    noise_covariance: np.ndarray | None = None,
) -> np.ndarray:
    """Adaptive-moments shape of ``array`` (indexed ``[y, x]``) as a length-1 record.

    Parameters
    ----------
    array : ndarray, shape (ny, nx)
        The image, pixel centres at integer 0-based coordinates.
    wcs : galsim.BaseWCS
        Pixel to sky (arcsec) mapping used to report ``g1, g2, T`` in sky coordinates.
    noise_variance : float
        Per-pixel noise variance (image units squared); 0 gives an infinite S/N.
    guess_centroid : (x, y) or None
        0-based pixel position to start from (None: the image centre).
    guess_sigma : float
        Starting Gaussian sigma in pixels.
    noise_covariance : ndarray, optional
        Autocovariance of the noise (see the module docstring); given, the S/N uses it
        and ``noise_variance`` is not used.

    Returns
    -------
    ndarray
        Length-1 :data:`SHAPE_DTYPE` array; ``T_psf`` is left 0 for the caller. Failures
        are flagged, never raised.
    """
    if not np.all(np.isfinite(array)):
        return empty_record(MetacalFlags.NONFINITE)
    gimage = galsim.Image(np.ascontiguousarray(array), xmin=0, ymin=0, wcs=wcs)
    centroid = gimage.true_center if guess_centroid is None else galsim.PositionD(*guess_centroid)
    moments = galsim.hsm.FindAdaptiveMom(
        gimage, guess_sig=guess_sigma, guess_centroid=centroid, strict=False
    )
    if moments.moments_status != 0:
        return empty_record(MetacalFlags.HSM_FAILED)

    # S/N of the flux in the matched (adaptive) Gaussian weight W: sum(W I) / sqrt(var F),
    # var F = var * sum(W^2) for white noise
    ny, nx = array.shape
    moments_matrix = moments.moments_sigma**2 * _shape_matrix(moments.observed_shape)
    dx = np.arange(nx)[np.newaxis, :] - moments.moments_centroid.x
    dy = np.arange(ny)[:, np.newaxis] - moments.moments_centroid.y
    inverse = np.linalg.inv(moments_matrix)
    rho2 = inverse[0, 0] * dx**2 + 2.0 * inverse[0, 1] * dx * dy + inverse[1, 1] * dy**2
    weight = np.exp(-0.5 * rho2)
    weighted_flux = float(np.sum(weight * array))
    flux_variance = (
        noise_variance * float(np.sum(weight**2))
        if noise_covariance is None
        else covariance_flux_variance(noise_covariance, weight)
    )
    if flux_variance > 0.0:
        s2n = weighted_flux / np.sqrt(flux_variance)
    else:
        s2n = np.inf if weighted_flux > 0.0 else np.nan

    sky = moments.applyWCS(wcs, image_pos=moments.moments_centroid)
    record = np.zeros(1, dtype=SHAPE_DTYPE)
    record["g1"] = sky.observed_shape.g1
    record["g2"] = sky.observed_shape.g2
    record["T"] = _sky_T(sky.moments_sigma, sky.observed_shape)
    record["flux"] = moments.moments_amp
    record["s2n"] = s2n
    record["x"] = moments.moments_centroid.x
    record["y"] = moments.moments_centroid.y
    if not (weighted_flux > 0.0 and moments.moments_amp > 0.0 and s2n > 0.0):
        record["flags"] = MetacalFlags.NONPOSITIVE_FLUX
    return record


def _shape_matrix(shape: galsim.Shear) -> np.ndarray:
    # Unit-determinant matrix A with moments M = sigma^2 A for a shape g (pixel frame).
    transform = shape.getMatrix()
    return transform @ transform.T


def psf_T(psf_image: np.ndarray, wcs: galsim.BaseWCS, weight_fwhm: float | None = None) -> float:
    """``T`` (arcsec^2) of a PSF stamp from its adaptive moments (NaN when they fail), or
    from its moments in the fixed ``wmom`` weight of FWHM ``weight_fwhm`` about its
    central pixel."""
    if weight_fwhm is not None:
        n = psf_image.shape[0] // 2
        flux, muu, mvv, _, _ = weighted_moments(
            np.asarray(psf_image, dtype=np.float64), wcs, (float(n), float(n)), weight_fwhm
        )
        return muu + mvv if flux > 0.0 else np.nan
    gimage = galsim.Image(np.ascontiguousarray(psf_image), xmin=0, ymin=0, wcs=wcs)
    moments = galsim.hsm.FindAdaptiveMom(gimage, strict=False, use_sky_coords=True)
    if moments.moments_status != 0:
        return np.nan
    return _sky_T(moments.moments_sigma, moments.observed_shape)


def sky_offsets(
    shape: tuple[int, int], wcs: galsim.BaseWCS, centre: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Sky offsets ``(u, v)`` (arcsec) of the pixel centres of an array of ``shape`` from
    pixel ``centre``, through the local jacobian of ``wcs`` at ``centre``."""
    ny, nx = shape
    jac = wcs.jacobian(image_pos=galsim.PositionD(*centre))
    dx = np.arange(nx)[np.newaxis, :] - centre[0]
    dy = np.arange(ny)[:, np.newaxis] - centre[1]
    return jac.dudx * dx + jac.dudy * dy, jac.dvdx * dx + jac.dvdy * dy


def fwhm_to_sigma(fwhm: float) -> float:
    """Sigma of a Gaussian of full width at half maximum ``fwhm`` (same unit)."""
    return float(fwhm / (2.0 * np.sqrt(2.0 * np.log(2.0))))


def gaussian_weight_image(u: np.ndarray, v: np.ndarray, inverse_cov: np.ndarray) -> np.ndarray:
    """The Gaussian weight ``W = exp(-d^T inverse_cov d / 2)`` at sky offsets ``d = (u, v)``
    (arcsec) of the pixel centres; ``inverse_cov`` in arcsec^-2."""
    a, b, c = inverse_cov[0, 0], inverse_cov[0, 1], inverse_cov[1, 1]
    return np.asarray(np.exp(-0.5 * (a * u * u + 2.0 * b * u * v + c * v * v)))


def gaussian_moment_sums(
    array: np.ndarray, u: np.ndarray, v: np.ndarray, inverse_cov: np.ndarray
) -> np.ndarray:
    """Sums of ``array`` in the Gaussian weight ``W = exp(-d^T inverse_cov d / 2)``.

    Parameters
    ----------
    array : ndarray, shape (ny, nx)
        Pixel values (image units).
    u, v : ndarray, shape (ny, nx)
        Sky offsets ``d = (u, v)`` (arcsec) of the pixel centres from the weight's centre
        (see :func:`sky_offsets`).
    inverse_cov : ndarray, shape (2, 2)
        Inverse covariance of the weight, arcsec^-2.

    Returns
    -------
    ndarray, shape (7,)
        ``sum W I``, ``sum W I u``, ``sum W I v``, ``sum W I u^2``, ``sum W I v^2``,
        ``sum W I u v`` (image units times arcsec^0, ^1 or ^2) and ``sum W^2``: the pieces
        that single-image and joint multi-epoch moments are made of.
    """
    weight = gaussian_weight_image(u, v, inverse_cov)
    wi = weight * array
    wiu, wiv = wi * u, wi * v
    return np.array(
        [
            np.sum(wi),
            np.sum(wiu),
            np.sum(wiv),
            np.sum(wiu * u),
            np.sum(wiv * v),
            np.sum(wiu * v),
            np.sum(weight * weight),
        ]
    )


def round_inverse_cov(weight_fwhm: float) -> np.ndarray:
    """Inverse covariance (arcsec^-2) of the round ``wmom`` weight of FWHM ``weight_fwhm``."""
    return np.eye(2) / fwhm_to_sigma(weight_fwhm) ** 2


def wmom_from_sums(sums: np.ndarray) -> tuple[float, float, float, float]:
    """``(F, M_uu, M_vv, M_uv)`` from :func:`gaussian_moment_sums` (``M`` normalised by
    ``F``, arcsec^2; NaN or infinite when ``F = 0``)."""
    flux = float(sums[0])
    with np.errstate(invalid="ignore", divide="ignore"):
        muu, mvv, muv = (float(x) for x in np.asarray(sums[3:6]) / flux)
    return flux, muu, mvv, muv


def weighted_moments(
    array: np.ndarray,
    wcs: galsim.BaseWCS,
    centre: tuple[float, float] | None,
    weight_fwhm: float = WMOM_FWHM,
) -> tuple[float, float, float, float, float]:
    """``(F, M_uu, M_vv, M_uv, sum W^2)`` of ``array`` in a round Gaussian weight of FWHM
    ``weight_fwhm`` arcsec centred on pixel ``centre`` (None: the image centre); ``M`` are
    normalised by ``F``, in arcsec^2."""
    ny, nx = array.shape
    if centre is None:
        centre = ((nx - 1) / 2.0, (ny - 1) / 2.0)
    u, v = sky_offsets(array.shape, wcs, centre)
    sums = gaussian_moment_sums(array, u, v, round_inverse_cov(weight_fwhm))
    return (*wmom_from_sums(sums), float(sums[6]))


def wmom_record(sums: np.ndarray, flux_variance: float, centre: tuple[float, float]) -> np.ndarray:
    """The ``wmom`` shape record from (possibly joint) weighted sums.

    Parameters
    ----------
    sums : ndarray, shape (7,)
        :func:`gaussian_moment_sums` of one image, or a weighted mean of several epochs'.
    flux_variance : float
        Noise variance of ``sums[0]`` (image units squared); 0 gives an infinite S/N.
    centre : (x, y)
        Pixel position of the weight's centre, reported as ``x, y``.
    """
    flux, muu, mvv, muv = wmom_from_sums(sums)
    T = muu + mvv
    if flux_variance > 0.0:
        s2n = flux / np.sqrt(flux_variance)
    else:
        s2n = np.inf if flux > 0.0 else np.nan
    record = np.zeros(1, dtype=SHAPE_DTYPE)
    with np.errstate(invalid="ignore", divide="ignore"):
        record["g1"] = (muu - mvv) / T
        record["g2"] = 2.0 * muv / T
    record["T"] = T
    record["flux"] = flux
    record["s2n"] = s2n
    record["x"], record["y"] = centre
    if not (flux > 0.0 and T > 0.0 and s2n > 0.0):
        record["flags"] = MetacalFlags.NONPOSITIVE_FLUX
    return record


def measure_wmom(
    array: np.ndarray,
    wcs: galsim.BaseWCS,
    noise_variance: float,
    centre: tuple[float, float] | None,
    weight_fwhm: float = WMOM_FWHM,
    noise_covariance: np.ndarray | None = None,
) -> np.ndarray:
    """Fixed-weight Gaussian moments shape of ``array`` as a length-1 record.

    See the module docstring; ``centre`` is the fixed 0-based pixel position of the
    weight (None: the image centre), reported as ``x, y``; ``flux`` is the weighted flux
    ``sum W I``. ``T_psf`` is left 0 for the caller (:func:`psf_T` with ``weight_fwhm``).
    The S/N uses ``noise_covariance`` when given, else white noise of ``noise_variance``.
    """
    if not np.all(np.isfinite(array)):
        return empty_record(MetacalFlags.NONFINITE)
    ny, nx = array.shape
    if centre is None:
        centre = ((nx - 1) / 2.0, (ny - 1) / 2.0)
    u, v = sky_offsets(array.shape, wcs, centre)
    inverse_cov = round_inverse_cov(weight_fwhm)
    sums = gaussian_moment_sums(array, u, v, inverse_cov)
    if noise_covariance is None:
        return wmom_record(sums, noise_variance * float(sums[6]), centre)
    weight = gaussian_weight_image(u, v, inverse_cov)
    return wmom_record(sums, covariance_flux_variance(noise_covariance, weight), centre)
