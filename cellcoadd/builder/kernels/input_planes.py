"""The planes of one exposure that the builder warps, filled only where the kernel reads.

For a selected exposure the builder warps, over its footprint, interleaved planes
(``pixels[y, x, p]``): the image and K noise realizations in counts at the common zero
point, the variance scaled alike, and, when some pixel is bad, the bad-pixel indicator
whose warp is the masked fraction. Bad pixels carry no image, noise or variance. The
noise comes from :mod:`cellcoadd.builder.kernels.noise`, pixel by pixel, so only the pixels some
kernel tap reads are computed; the others stay zero and are never read.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from cellcoadd.builder.kernels.descriptor import WARP_KERNEL
from cellcoadd.builder.kernels.noise import first_words, noise_key, normal_from_word
from cellcoadd.geometry.box import Box

_GROUP = 8  # output pixels per side of the groups whose taps are bounded together
# the taps of a position v: floor(v) + _FIRST_OFFSET .. floor(v) + _LAST_OFFSET
_FIRST_OFFSET = WARP_KERNEL.first_offset
_LAST_OFFSET = WARP_KERNEL.last_offset


@numba.njit(cache=True)
def _read_spans(
    x: np.ndarray,
    y: np.ndarray,
    x_start: int,
    y_start: int,
    n_box_cols: int,
    first: np.ndarray,
    stop: np.ndarray,
) -> None:
    """Widen, per row of the box (``x_start``, ``y_start``, ``first.size`` rows,
    ``n_box_cols`` columns), the half-open column range ``[first, stop)`` to hold every
    tap read at the positions ``(x, y)``.

    The taps of each group of ``_GROUP`` x ``_GROUP`` positions are bounded by one box,
    so a range may hold a few pixels that are not read, never miss one that is.
    """
    n_rows, n_cols = x.shape
    n_box_rows = first.shape[0]
    for row0 in range(0, n_rows, _GROUP):
        for col0 in range(0, n_cols, _GROUP):
            x_min = y_min = math.inf
            x_max = y_max = -math.inf
            for row in range(row0, min(row0 + _GROUP, n_rows)):
                for col in range(col0, min(col0 + _GROUP, n_cols)):
                    x_min = min(x_min, x[row, col])
                    x_max = max(x_max, x[row, col])
                    y_min = min(y_min, y[row, col])
                    y_max = max(y_max, y[row, col])
            x_lo = max(int(math.floor(x_min)) + _FIRST_OFFSET - x_start, 0)
            x_hi = min(int(math.floor(x_max)) + _LAST_OFFSET + 1 - x_start, n_box_cols)
            y_lo = max(int(math.floor(y_min)) + _FIRST_OFFSET - y_start, 0)
            y_hi = min(int(math.floor(y_max)) + _LAST_OFFSET + 1 - y_start, n_box_rows)
            for row in range(y_lo, y_hi):
                first[row] = min(first[row], x_lo)
                stop[row] = max(stop[row], x_hi)


@numba.njit(cache=True)
def _fill(
    pixels: np.ndarray,
    image: np.ndarray,
    variance: np.ndarray,
    scalar_variance: float,
    is_scalar: bool,
    bad: np.ndarray,
    flux_scale: float,
    noise_variance: float,
    x_start: int,
    y_start: int,
    first: np.ndarray,
    stop: np.ndarray,
    n_noise: int,
    key0: np.uint64,
    key1: np.uint64,
) -> None:
    with_mfrac = pixels.shape[2] == n_noise + 3
    variance_scale = flux_scale**2
    words = np.empty((n_noise, pixels.shape[1]), dtype=np.uint64)
    for row in range(pixels.shape[0]):
        start = first[row]
        if start >= stop[row]:
            continue
        first_words(
            x_start + start, y_start + row, n_noise, key0, key1, words[:, : stop[row] - start]
        )
        for col in range(start, stop[row]):
            if bad[row, col]:  # no signal, noise or variance; the pixel counts as masked
                if with_mfrac:
                    pixels[row, col, n_noise + 2] = 1.0
                continue
            pixel_variance = scalar_variance if is_scalar else variance[row, col]
            # noise from the background variance, or from the pixel's own (<= 0)
            sigma = math.sqrt(noise_variance if noise_variance > 0.0 else pixel_variance)
            pixels[row, col, 0] = image[row, col] * flux_scale
            for realization in range(n_noise):
                normal = normal_from_word(
                    words[realization, col - start],
                    x_start + col,
                    y_start + row,
                    realization,
                    key0,
                    key1,
                )
                pixels[row, col, 1 + realization] = normal * sigma * flux_scale
            pixels[row, col, n_noise + 1] = pixel_variance * variance_scale


def input_planes(
    image: np.ndarray,
    variance: np.ndarray | float,
    bad: np.ndarray,
    box: Box,
    x: np.ndarray | None,
    y: np.ndarray | None,
    flux_scale: float,
    n_noise: int,
    noise_seed: tuple[int, int, int],
    noise_variance: float = 0.0,
    origin: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """The planes to warp over ``box``, interleaved: shape ``(ny, nx, P)``, float64.

    Parameters
    ----------
    image : ndarray, shape box.shape
        Exposure counts over ``box`` (finite where not ``bad``).
    variance : ndarray of box.shape, or float
        Per-pixel variance (counts^2, positive where not ``bad``), or one value for all.
    bad : ndarray of bool, shape box.shape
        Pixels with a bad mask bit.
    box : Box
        The exposure pixels the arrays cover (its starts key the noise).
    x, y : ndarray, float64, or None
        Exposure pixel positions the kernel will be evaluated at; only the pixels their
        Lanczos-3 taps reach are filled. None: every pixel of ``box`` is filled.
    flux_scale : float
        Factor from exposure counts to counts at the common zero point.
    n_noise : int
        Number K of noise realizations.
    noise_seed : (seed, visit, detector)
        Key of the exposure's noise (see :func:`cellcoadd.builder.kernels.noise.noise_key`).
    noise_variance : float
        Variance (counts^2, before ``flux_scale``) of the noise realizations, e.g. the
        background variance; 0 draws each pixel's noise with its own ``variance``.
    origin : (int, int)
        Detector pixel of the exposure's ``[0, 0]`` (non-zero for a cutout): the noise is
        a function of detector pixels, so a cutout draws the same values as the whole.

    Returns
    -------
    ndarray
        Planes: image, K noise realizations (unit normal x sqrt(noise variance), scaled),
        variance x ``flux_scale**2`` and, if any pixel is bad, the bad-pixel indicator.
        Unread pixels and bad pixels are 0 (1 in the indicator where bad).
    """
    with_mfrac = bool(bad.any())
    pixels = np.zeros((*box.shape, n_noise + 2 + int(with_mfrac)))
    if x is None or y is None:
        first = np.zeros(box.shape[0], dtype=np.int64)
        stop = np.full(box.shape[0], box.shape[1], dtype=np.int64)
    else:
        x = np.ascontiguousarray(x, dtype=np.float64)
        y = np.ascontiguousarray(y, dtype=np.float64)
        # empty ranges ([width, 0)) until some tap reaches a row
        first = np.full(box.shape[0], box.shape[1], dtype=np.int64)
        stop = np.zeros(box.shape[0], dtype=np.int64)
        if x.size:
            _read_spans(x, y, box.x_start, box.y_start, box.shape[1], first, stop)
    scalar = np.isscalar(variance)
    variance_plane = np.zeros((1, 1)) if scalar else np.asarray(variance)  # no copy
    key0, key1 = noise_key(*noise_seed)
    _fill(
        pixels,
        image,
        variance_plane,
        float(variance) if scalar else 0.0,
        scalar,
        bad,
        float(flux_scale),
        float(noise_variance),
        box.x_start + origin[0],  # the noise is keyed by detector pixels
        box.y_start + origin[1],
        first,
        stop,
        n_noise,
        key0,
        key1,
    )
    return pixels
