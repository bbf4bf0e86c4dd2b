"""Adaptive-moments shape of one image: the shape record, its flags and the measurement.

Shapes are GalSim HSM adaptive moments converted to sky coordinates by the image's WCS
(``u`` West, ``v`` North): the reduced shear ``g = (a - b) / (a + b) * (cos 2 phi, sin 2
phi)`` (GalSim ``observed_shape``) and ``T = Ixx + Iyy`` in arcsec^2. The S/N is that of
the flux in the matched (adaptive) Gaussian weight, for white noise.
"""

from __future__ import annotations

import enum

import galsim
import numpy as np

#: One measured shape per row; ``T`` and ``T_psf`` in arcsec^2, ``flux`` in image units
#: (sum of pixel values), ``x, y`` the 0-based pixel centroid.
SHAPE_DTYPE = np.dtype(
    [("flags", "i4")]
    + [(name, "f8") for name in ("g1", "g2", "T", "T_psf", "flux", "s2n", "x", "y")]
)


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

    # S/N of the flux in the matched (adaptive) Gaussian weight W, for white noise:
    # sum(W I) / sqrt(var * sum(W^2)).
    ny, nx = array.shape
    moments_matrix = moments.moments_sigma**2 * _shape_matrix(moments.observed_shape)
    dx = np.arange(nx)[np.newaxis, :] - moments.moments_centroid.x
    dy = np.arange(ny)[:, np.newaxis] - moments.moments_centroid.y
    inverse = np.linalg.inv(moments_matrix)
    rho2 = inverse[0, 0] * dx**2 + 2.0 * inverse[0, 1] * dx * dy + inverse[1, 1] * dy**2
    weight = np.exp(-0.5 * rho2)
    weighted_flux = float(np.sum(weight * array))
    if noise_variance > 0.0:
        s2n = weighted_flux / np.sqrt(noise_variance * np.sum(weight**2))
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


def psf_T(psf_image: np.ndarray, wcs: galsim.BaseWCS) -> float:
    """``T`` (arcsec^2) of a PSF stamp from its adaptive moments, NaN when they fail."""
    gimage = galsim.Image(np.ascontiguousarray(psf_image), xmin=0, ymin=0, wcs=wcs)
    moments = galsim.hsm.FindAdaptiveMom(gimage, strict=False, use_sky_coords=True)
    if moments.moments_status != 0:
        return np.nan
    return _sky_T(moments.moments_sigma, moments.observed_shape)
