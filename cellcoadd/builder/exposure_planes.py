"""What one selected exposure contributes to a cell before the warp: its planes, with bad
pixels interpolated, and its mask in the coadd's bit numbering.

Bad pixels (the bits named in ``BuildConfig.bad_mask_bits``) are interpolated in the
image, in every noise realization and in the variance with the same weights (a
Gaussian-weighted local plane fit, :mod:`cellcoadd.builder.kernels.mask_interpolation`),
so the coadd stays a linear, signal-independent combination of the inputs and its PSF
stays defined. The interpolation reads good pixels up to
:data:`~cellcoadd.builder.kernels.mask_interpolation.DEFAULT_MAX_RADIUS` pixels away:
the planes are filled over the footprint grown by that much (clipped to the exposure),
so a given exposure pixel gets the same value in every cell. The masked-fraction plane
(the bad-pixel indicator, warped) records where interpolated pixels contributed.
"""

from __future__ import annotations

import numpy as np

from cellcoadd.builder.kernels.input_planes import input_planes
from cellcoadd.builder.kernels.mask_interpolation import (
    DEFAULT_MAX_RADIUS,
    interpolate_bad_pixels,
)
from cellcoadd.builder.select import Candidate
from cellcoadd.geometry.box import Box
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.maskbits import MaskBits


def noise_variance(exposure: Exposure, config: BuildConfig) -> float:
    """Variance (counts^2 at the exposure's zero point) of the noise realizations: the
    exposure's background variance by default, 0 (each pixel's own) for
    ``noise_variance="pixel"``."""
    if config.noise_variance == "pixel":
        return 0.0
    return exposure.background_variance


def _variance_over(exposure: Exposure, box: Box) -> float | np.ndarray:
    # Exposure holds a float or an image-shaped array
    if isinstance(exposure.variance, np.ndarray):
        return exposure.variance[box.slices]
    return exposure.variance


def exposure_planes(
    candidate: Candidate, config: BuildConfig, seed: int, bad_bits: int
) -> np.ndarray | None:
    """The interleaved planes of ``candidate`` over its footprint, ready for the warp.

    Returns
    -------
    ndarray, shape (ny, nx, P), float64, or None
        Image, K noise realizations, variance (all at the common zero point) and, when
        some pixel is bad, the bad-pixel indicator (see
        :func:`~cellcoadd.builder.kernels.input_planes.input_planes`). None when some bad
        pixel of the footprint has no good pixel within the interpolation radius (the
        input is then rejected for the cell as ``masked_fraction``).
    """
    exposure, box, mapping = candidate.exposure, candidate.footprint, candidate.mapping
    key = (seed, exposure.visit, exposure.detector)
    noise = noise_variance(exposure, config)
    if not candidate.bad.any():
        return input_planes(
            exposure.image[box.slices],
            _variance_over(exposure, box),
            candidate.bad,
            box,
            mapping.x,
            mapping.y,
            candidate.flux_scale,
            config.n_noise,
            key,
            noise,
            exposure.origin,
        )
    grown = box.grow(DEFAULT_MAX_RADIUS).intersection(Box.from_shape(exposure.shape))
    assert exposure.mask is not None  # Exposure.__post_init__ fills it
    bad = (exposure.mask[grown.slices] & bad_bits) != 0
    pixels = input_planes(
        exposure.image[grown.slices],
        _variance_over(exposure, grown),
        bad,
        grown,
        None,  # every pixel: the interpolation reads beyond the kernel's taps
        None,
        candidate.flux_scale,
        config.n_noise,
        key,
        noise,
        exposure.origin,
    )
    unfilled = interpolate_bad_pixels(pixels, bad)
    inside = (
        slice(box.y_start - grown.y_start, box.y_stop - grown.y_start),
        slice(box.x_start - grown.x_start, box.x_stop - grown.x_start),
    )
    if unfilled[inside].any():
        return None
    pixels[..., -1] = bad  # the indicator was interpolated like the rest: restore it
    return np.ascontiguousarray(pixels[inside])


def translated_mask(exposure: Exposure, box: Box, coadd_bits: MaskBits) -> np.ndarray:
    """The exposure's mask over ``box`` in the coadd's bit numbering (bits matched by
    name, see :meth:`cellcoadd.model.maskbits.MaskBits.translation_to`)."""
    assert exposure.mask is not None  # Exposure.__post_init__ fills it
    mask = exposure.mask[box.slices]
    translation = exposure.mask_bits.translation_to(coadd_bits)
    if translation is None:  # the same numbering
        return mask
    out = np.zeros(mask.shape, dtype=np.int32)
    for bit in np.flatnonzero(translation):
        out[(mask >> bit) & 1 == 1] |= np.int32(translation[bit])
    return out
