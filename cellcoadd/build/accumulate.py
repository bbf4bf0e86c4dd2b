"""Accumulating a warp straight into running sums, for inputs stored pixel by pixel.

The builder keeps an exposure's planes interleaved (all planes of a pixel together), so
each tap reads them in one go; the kernel weights are those of
:mod:`cellcoadd.build.warp`, and the result equals ``warp_planes`` bit for bit.
"""

from __future__ import annotations

import numba
import numpy as np

from cellcoadd.build.warp import (
    _block_sum,
    _block_sums2,
    _block_sums4,
    _check_positions,
    _row_weights,
)


@numba.njit(cache=True)
def _accumulate_interleaved(
    flat_pixels: np.ndarray,
    nx_in: int,
    x_src: np.ndarray,
    y_src: np.ndarray,
    out: np.ndarray,
    plane_weights: np.ndarray,
    scales: np.ndarray,
    plane_scales: np.ndarray,
) -> None:
    """Kernel of :func:`accumulate_warped`; ``flat_pixels`` is ``(ny_in, nx_in, P)`` raveled."""
    n_planes = plane_weights.shape[0]
    tap_stride = np.uint64(n_planes)
    row_stride = np.uint64(nx_in) * tap_stride
    factors = np.empty(n_planes)
    for row in range(x_src.shape[0]):
        weights_x, weights_y, first_x, first_y, exact_x, exact_y = _row_weights(x_src, y_src, row)
        for col in range(x_src.shape[1]):
            for p in range(n_planes):
                which = plane_scales[p]
                weight = plane_weights[p]
                factors[p] = weight * scales[which, row, col] if which >= 0 else weight
            if exact_x[col] >= 0 and exact_y[col] >= 0:
                source = np.uint64(exact_y[col]) * row_stride + np.uint64(exact_x[col]) * tap_stride
                for p in range(n_planes):
                    out[p, row, col] += factors[p] * flat_pixels[source + np.uint64(p)]
                continue
            wx = (
                weights_x[0, col],
                weights_x[1, col],
                weights_x[2, col],
                weights_x[3, col],
                weights_x[4, col],
                weights_x[5, col],
            )
            corner = first_y[col] * row_stride + first_x[col] * tap_stride
            p = 0
            while p + 4 <= n_planes:
                start = corner + np.uint64(p)
                t0, t1, t2, t3 = _block_sums4(
                    flat_pixels, start, row_stride, tap_stride, wx, weights_y, col
                )
                out[p, row, col] += factors[p] * t0
                out[p + 1, row, col] += factors[p + 1] * t1
                out[p + 2, row, col] += factors[p + 2] * t2
                out[p + 3, row, col] += factors[p + 3] * t3
                p += 4
            if p + 2 <= n_planes:
                start = corner + np.uint64(p)
                t0, t1 = _block_sums2(
                    flat_pixels, start, row_stride, tap_stride, wx, weights_y, col
                )
                out[p, row, col] += factors[p] * t0
                out[p + 1, row, col] += factors[p + 1] * t1
                p += 2
            if p < n_planes:
                start = corner + np.uint64(p)
                total = _block_sum(flat_pixels, start, row_stride, tap_stride, wx, weights_y, col)
                out[p, row, col] += factors[p] * total


def accumulate_warped(
    pixels: np.ndarray,
    x_src: np.ndarray,
    y_src: np.ndarray,
    out: np.ndarray,
    plane_weights: np.ndarray,
    scales: np.ndarray | None = None,
    plane_scales: np.ndarray | None = None,
) -> np.ndarray:
    """Warp planes stored pixel by pixel and add each with its own weight and scale.

    For every plane ``p`` this adds to ``out[p]`` exactly (bit for bit) what
    ``plane_weights[p] * scales[plane_scales[p]] * warp_planes(planes)[p]`` would add, or
    ``plane_weights[p] * warp_planes(planes)[p]`` when ``plane_scales[p]`` is -1. Storing
    the planes of one input pixel together lets one pass over each 6x6 block serve all of
    them, and accumulating in the kernel saves the temporaries.

    Parameters
    ----------
    pixels : ndarray, shape (ny_in, nx_in, P), float64
        The ``P`` input planes, interleaved: ``pixels[y, x]`` holds every plane's value
        at input pixel ``(x, y)``.
    x_src, y_src : ndarray, shape (ny_out, nx_out), float64
        Output pixel centres in input pixel coordinates, as for :func:`warp_planes`.
    out : ndarray, shape (P, ny_out, nx_out), float64
        C-contiguous accumulator, updated in place.
    plane_weights : array_like, shape (P,)
        Finite scalar weight of each plane.
    scales : ndarray, shape (S, ny_out, nx_out), optional
        Per-output-pixel factors (e.g. the pixel-area ratio and its square).
    plane_scales : array_like of int, shape (P,), optional
        Index into ``scales`` of each plane's factor, -1 for none (default: none).

    Returns
    -------
    ndarray
        ``out``.
    """
    pixels = np.asarray(pixels)
    if pixels.ndim != 3 or pixels.dtype != np.float64:
        raise ValueError(f"pixels must be a 3-D float64 array, got {pixels.dtype} {pixels.shape}")
    n_planes = pixels.shape[2]
    x_src, y_src = _check_positions(x_src, y_src, pixels.shape[:2])
    out_shape = (n_planes, *x_src.shape)
    if not isinstance(out, np.ndarray) or out.dtype != np.float64 or out.shape != out_shape:
        raise ValueError(f"out must be a float64 array of shape {out_shape}")
    if not out.flags.c_contiguous or not out.flags.writeable:
        raise ValueError("out must be C-contiguous and writeable")
    weights = np.asarray(plane_weights, dtype=np.float64)
    if weights.shape != (n_planes,) or not np.isfinite(weights).all():
        raise ValueError(f"plane_weights must be {n_planes} finite numbers")
    if scales is None:
        scales = np.ones((1, 1, 1))
    scales = np.ascontiguousarray(scales, dtype=np.float64)
    which = np.full(n_planes, -1, dtype=np.int64)
    if plane_scales is not None:
        which = np.asarray(plane_scales, dtype=np.int64)
        if scales.shape[1:] != x_src.shape or which.shape != (n_planes,):
            raise ValueError("scales must be (S, ny_out, nx_out) with one index per plane")
        if which.min() < -1 or which.max() >= scales.shape[0]:
            raise ValueError(f"plane_scales must lie in [-1, {scales.shape[0] - 1}]")
    if x_src.size and n_planes:
        flat_pixels = np.ascontiguousarray(pixels).reshape(-1)
        _accumulate_interleaved(
            flat_pixels, int(pixels.shape[1]), x_src, y_src, out, weights, scales, which
        )
    return out
