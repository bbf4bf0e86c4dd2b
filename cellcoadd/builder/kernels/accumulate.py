"""Accumulating a warp straight into running sums, for inputs stored pixel by pixel.

The builder keeps an exposure's planes interleaved (all planes of a pixel together), so a
row of a 6x6 footprint is one run of ``6 P`` adjacent values that SIMD vectors read
whole (:mod:`cellcoadd.builder.kernels.block_sums`). The output is resampled in runs of up
to ``TABLE_WIDTH`` pixels along a row: the Lanczos weights and footprint indices of the
run first (vectorised over pixels, :func:`cellcoadd.builder.kernels.lanczos.fill_table`),
then the 6x6 sums of every pixel into a small buffer, then ``out += factor * sum`` per
plane, vectorised over pixels. The output is swept in vertical strips of that width, so
consecutive runs read overlapping input and a large output does not stream its whole
footprint through the caches for every row.

Every value depends only on the output pixel's position, the input and the weights: the
same operations in the same order for every pixel and plane, whatever its place in the
output, the strip, the vector lanes or the number of planes.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import ArrayLike

from cellcoadd.builder.kernels.block_sums import (
    MAX_PLANES_AT_ONCE,
    block_sums_1,
    block_sums_2,
    block_sums_3,
    block_sums_4,
    block_sums_5,
    block_sums_6,
    block_sums_7,
    block_sums_8,
    block_sums_group,
    prefetch,
)
from cellcoadd.builder.kernels.lanczos import (
    N_TAPS,
    TABLE_ROWS,
    TABLE_WIDTH,
    check_positions,
    fill_table,
)
from cellcoadd.errors import CellCoaddRangeError, CellCoaddValueError


@numba.njit(cache=True, inline="always")
def _block_sums(
    n_planes: int,
    flat: np.ndarray,
    corner: int,
    row_stride: int,
    table: np.ndarray,
    col: int,
    sums: np.ndarray,
) -> None:
    """``sums[p, col]``: the 6x6 sums of output pixel ``col`` of the table, every plane."""
    if n_planes == 1:
        block_sums_1(flat, corner, row_stride, table, col, sums)
    elif n_planes == 2:
        block_sums_2(flat, corner, row_stride, table, col, sums)
    elif n_planes == 3:
        block_sums_3(flat, corner, row_stride, table, col, sums)
    elif n_planes == 4:
        block_sums_4(flat, corner, row_stride, table, col, sums)
    elif n_planes == 5:
        block_sums_5(flat, corner, row_stride, table, col, sums)
    elif n_planes == 6:
        block_sums_6(flat, corner, row_stride, table, col, sums)
    elif n_planes == 7:
        block_sums_7(flat, corner, row_stride, table, col, sums)
    elif n_planes == 8:
        block_sums_8(flat, corner, row_stride, table, col, sums)
    else:
        # groups of eight, the last overlapping the one before: same sums, same bits
        plane = 0
        while plane < n_planes:
            first = min(plane, n_planes - MAX_PLANES_AT_ONCE)
            block_sums_group(flat, corner, row_stride, n_planes, table, col, sums, first)
            plane += MAX_PLANES_AT_ONCE


# A footprint walks through the input along a line the hardware prefetchers do not
# follow; each row's leading edge is new to the caches. The footprint of the pixel
# _PREFETCH_AHEAD ahead is prefetched every _PREFETCH_EVERY pixels (footprints of
# neighbours overlap by most of their taps), long enough before it is read to hide the
# latency of memory. The next row's positions, scales and output values are prefetched
# during this row's sums: each is a short burst far from the last, which the hardware
# would fetch only after the first misses.
_PREFETCH_EVERY = 4
_PREFETCH_AHEAD = 8
_LINE = 8  # float64 per 64-byte cache line


@numba.njit(cache=True, inline="always")
def _prefetch_footprint(flat: np.ndarray, corner: int, row_stride: int, span: int) -> None:
    """Prefetch the six rows of ``span`` values of the footprint starting at ``corner``."""
    for a in range(N_TAPS):
        start = corner + a * row_stride
        for offset in range(0, span, _LINE):
            prefetch(flat, start + offset)
        prefetch(flat, start + span - 1)


@numba.njit(cache=True)
def resample_interleaved(
    flat_pixels: np.ndarray,
    input_width: int,
    origin: tuple[int, int],
    x_src: np.ndarray,
    y_src: np.ndarray,
    out: np.ndarray,
    plane_weights: np.ndarray,
    scales: np.ndarray,
    plane_scales: np.ndarray,
) -> None:
    """``out[p] += plane_weights[p] * scales[plane_scales[p]] * warp(plane p)``.

    ``flat_pixels`` is an ``(ny, input_width, P)`` C-ordered array raveled, whose pixel
    ``[0, 0]`` is input pixel ``origin`` (x, y); the positions must keep every tap inside
    it (checked by the callers). ``plane_scales[p] = -1`` means no scale for plane ``p``.
    """
    n_planes = plane_weights.shape[0]
    n_rows, n_cols = x_src.shape
    row_stride = input_width * n_planes
    table = np.empty((TABLE_ROWS, TABLE_WIDTH))
    corners = np.empty(TABLE_WIDTH, dtype=np.int64)
    sources = np.empty(TABLE_WIDTH, dtype=np.int64)
    sums = np.empty((n_planes, TABLE_WIDTH))
    span = N_TAPS * n_planes  # values in a row of a footprint
    plane_size = n_rows * n_cols
    n_scales = scales.shape[0] if scales.shape[1:] == (n_rows, n_cols) else 0
    for first_col in range(0, n_cols, TABLE_WIDTH):
        stop_col = min(first_col + TABLE_WIDTH, n_cols)
        n = stop_col - first_col
        for row in range(n_rows):
            fill_table(
                x_src[row, first_col:stop_col],
                y_src[row, first_col:stop_col],
                row_stride,
                n_planes,
                origin,
                table,
                corners,
                sources,
            )
            # flat index of the next run's first pixel in (rows, cols) and (planes, rows, cols)
            following = (row + 1) * n_cols + first_col if row + 1 < n_rows else -1
            for col in range(n):
                ahead = col + _PREFETCH_AHEAD
                if col % _PREFETCH_EVERY == 0 and ahead < n:
                    _prefetch_footprint(flat_pixels, corners[ahead], row_stride, span)
                if following >= 0 and col % _LINE == 0:
                    index = following + col
                    prefetch(x_src, index)
                    prefetch(y_src, index)
                    for p in range(n_planes):
                        prefetch(out, p * plane_size + index)
                    for scale_plane in range(n_scales):
                        prefetch(scales, scale_plane * plane_size + index)
                source = sources[col]
                if source >= 0:
                    # integral position: a copy, bit for bit and immune to non-finite
                    # neighbours
                    for p in range(n_planes):
                        sums[p, col] = flat_pixels[source + p]
                else:
                    _block_sums(n_planes, flat_pixels, corners[col], row_stride, table, col, sums)
            for p in range(n_planes):
                weight = plane_weights[p]
                which = plane_scales[p]
                target = out[p, row, first_col:stop_col]
                values = sums[p]
                if which >= 0:
                    scale = scales[which, row, first_col:stop_col]
                    for col in range(n):
                        target[col] += (weight * scale[col]) * values[col]
                else:
                    for col in range(n):
                        target[col] += weight * values[col]


def accumulate_warped(
    pixels: np.ndarray,
    x_src: np.ndarray,
    y_src: np.ndarray,
    out: np.ndarray,
    plane_weights: ArrayLike,
    scales: np.ndarray | None = None,
    plane_scales: ArrayLike | None = None,
) -> np.ndarray:
    """Warp planes stored pixel by pixel and add each with its own weight and scale.

    For every plane ``p`` this adds to ``out[p]`` exactly (bit for bit) what
    ``plane_weights[p] * scales[plane_scales[p]] * warp_planes(planes)[p]`` would add, or
    ``plane_weights[p] * warp_planes(planes)[p]`` when ``plane_scales[p]`` is -1. Storing
    the planes of one input pixel together lets one pass over each 6x6 block serve all of
    them, and accumulating in the kernel saves the temporaries. The value added at an
    output pixel depends only on its position, the input and the weights (not on the
    output's shape or the pixel's place in it), and a plane's on no other plane.

    Parameters
    ----------
    pixels : ndarray, shape (ny_in, nx_in, P), float64
        The ``P`` input planes, interleaved: ``pixels[y, x]`` holds every plane's value
        at input pixel ``(x, y)``.
    x_src, y_src : ndarray, shape (ny_out, nx_out), float64
        Output pixel centres in input pixel coordinates, as for
        :func:`~cellcoadd.builder.kernels.warp.warp_planes`.
    out : ndarray, shape (P, ny_out, nx_out), float64
        C-contiguous accumulator, updated in place (``out[p] += ...``).
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
        raise CellCoaddValueError(
            f"pixels must be a 3-D float64 array, got {pixels.dtype} {pixels.shape}",
            value=(pixels.dtype, pixels.shape),
        )
    n_planes = pixels.shape[2]
    x_src, y_src = check_positions(x_src, y_src, pixels.shape[:2])
    out_shape = (n_planes, *x_src.shape)
    if not isinstance(out, np.ndarray) or out.dtype != np.float64 or out.shape != out_shape:
        raise CellCoaddValueError(f"out must be a float64 array of shape {out_shape}")
    if not out.flags.c_contiguous or not out.flags.writeable:
        raise CellCoaddValueError("out must be C-contiguous and writeable")
    weights = np.asarray(plane_weights, dtype=np.float64)
    if weights.shape != (n_planes,) or not np.isfinite(weights).all():
        raise CellCoaddValueError(f"plane_weights must be {n_planes} finite numbers")
    if scales is None:
        scales = np.ones((1, 1, 1))
    scales = np.ascontiguousarray(scales, dtype=np.float64)
    which = np.full(n_planes, -1, dtype=np.int64)
    if plane_scales is not None:
        which = np.asarray(plane_scales, dtype=np.int64)
        if scales.shape[1:] != x_src.shape or which.shape != (n_planes,):
            raise CellCoaddValueError("scales must be (S, ny_out, nx_out) with one index per plane")
        if which.min() < -1 or which.max() >= scales.shape[0]:
            raise CellCoaddRangeError(
                f"plane_scales must lie in [-1, {scales.shape[0] - 1}]",
                low=-1,
                high=scales.shape[0] - 1,
            )
    if x_src.size and n_planes:
        flat_pixels = np.ascontiguousarray(pixels).reshape(-1)
        resample_interleaved(
            flat_pixels, int(pixels.shape[1]), (0, 0), x_src, y_src, out, weights, scales, which
        )
    return out
