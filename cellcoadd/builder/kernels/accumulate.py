"""Accumulating a warp straight into running sums, for inputs stored pixel by pixel.

The builder keeps an exposure's planes interleaved (all planes of a pixel together), so
each tap reads them in one go and they fill the lanes of SIMD vectors (up to eight planes
per pass over a 6x6 block: vectors of 4, 2 and 1 lanes); the kernel weights and the
order of the sums are those of :mod:`cellcoadd.builder.kernels.warp`, and the result equals
``warp_planes`` bit for bit. The footprints of pixels a few steps ahead are prefetched,
as a rotated footprint walks through memory in a pattern the hardware does not predict.
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic
from numpy.typing import ArrayLike

from cellcoadd.builder.kernels.lanczos import (
    N_TAPS,
    TABLE_ROWS,
    WEIGHT_Y,
    exact_source_index,
    fill_row_table,
    footprint_corner,
)
from cellcoadd.builder.kernels.warp import (
    LLVM_I32,
    LLVM_I64,
    block_sum_adjacent,
    check_positions,
    column_sums,
    is_flat_array,
    splat,
    table_weights,
    tree_sum,
)


def _make_block_sums(width: int) -> Callable:
    """Intrinsic ``(flat, corner, row_stride, tap_stride, table, col)`` -> ``width`` sums.

    The 6x6 weighted sums of ``width`` planes stored next to each other (interleaved
    layout): tap ``(a, b)`` of plane ``p`` is ``flat[corner + a row_stride + b tap_stride
    + p]``; weights as for :func:`block_sum_adjacent`. The planes are split into vectors
    of 4, 2 and 1 lanes that share one pass over the taps.
    """
    pieces = [4] * (width // 4) + [2] * (width % 4 // 2) + [1] * (width % 2)

    def typer(typingctx, flat, corner, row_stride, tap_stride, table, col):
        if not is_flat_array(flat):
            return None
        result = types.UniTuple(types.float64, width)
        signature = result(flat, corner, row_stride, tap_stride, table, col)

        def codegen(context, builder, signature, args):
            flat, corner, row_stride, tap_stride, table, col = args
            flat_type, table_type = signature.args[0], signature.args[4]
            weights_y = table_weights(context, builder, table_type, table, col, WEIGHT_Y)
            weights_x = table_weights(context, builder, table_type, table, col, 0)
            lanes = []
            first = 0
            for piece in pieces:
                splats = [splat(builder, weight, piece) for weight in weights_y]
                piece_corner = builder.add(corner, ir.Constant(LLVM_I64, first))
                xterms = []
                for b in range(N_TAPS):
                    offset = builder.mul(tap_stride, ir.Constant(LLVM_I64, b))
                    sums = column_sums(
                        context,
                        builder,
                        flat_type,
                        flat,
                        builder.add(piece_corner, offset),
                        row_stride,
                        splats,
                        piece,
                    )
                    xterms.append(builder.fmul(splat(builder, weights_x[b], piece), sums))
                total = tree_sum(builder, xterms)
                lanes += [
                    builder.extract_element(total, ir.Constant(LLVM_I32, k)) for k in range(piece)
                ]
                first += piece
            return context.make_tuple(builder, result, lanes)

        return signature, codegen

    return intrinsic(typer)


@intrinsic
def _prefetch(typingctx, flat, index):
    """Ask the processor to bring the cache line holding ``flat[index]`` into its caches."""
    signature = types.void(flat, index)

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        byte_pointer = ir.IntType(8).as_pointer()
        prefetch = builder.module.declare_intrinsic(
            "llvm.prefetch",
            [byte_pointer],
            fnty=ir.FunctionType(ir.VoidType(), [byte_pointer, LLVM_I32, LLVM_I32, LLVM_I32]),
        )
        pointer = builder.bitcast(builder.gep(data, [args[1]], inbounds=True), byte_pointer)
        # read, keep in all cache levels, data cache
        flags = [ir.Constant(LLVM_I32, value) for value in (0, 3, 1)]
        builder.call(prefetch, [pointer, *flags])
        return context.get_dummy_value()

    return signature, codegen


# Along an output row, the footprints of consecutive pixels overlap by most of their six
# input pixels, so the footprint of every fourth pixel, eight pixels ahead, covers what is
# about to be read: prefetching it hides the memory latency of lines not yet in cache.
_PREFETCH_EVERY = 4
_PREFETCH_AHEAD = 8
_LINE_ELEMENTS = 8  # float64 per 64-byte cache line


@numba.njit(cache=True, inline="always")
def _prefetch_footprint(
    flat: np.ndarray,
    table: np.ndarray,
    col: int,
    row_stride: np.uint64,
    tap_stride: np.uint64,
    span: int,
) -> None:
    """Prefetch the 6x6 footprint of output pixel ``col``: six rows of ``span`` elements
    from its first tap on (see :func:`cellcoadd.builder.kernels.lanczos.footprint_corner`)."""
    start = footprint_corner(table, col, row_stride, tap_stride)
    last = np.uint64(span - 1)
    for _ in range(N_TAPS):
        # numba intrinsic: mypy sees the typer's signature, with typingctx first
        for offset in range(0, span, _LINE_ELEMENTS):
            _prefetch(flat, start + np.uint64(offset))  # type: ignore[call-arg]
        _prefetch(flat, start + last)  # type: ignore[call-arg]
        start += row_stride


_MAX_PLANES_AT_ONCE = 8
(
    _block_sums2,
    _block_sums3,
    _block_sums4,
    _block_sums5,
    _block_sums6,
    _block_sums7,
    _block_sums8,
) = (_make_block_sums(width) for width in range(2, _MAX_PLANES_AT_ONCE + 1))


@numba.njit(cache=True, inline="always")
def _add_sums(
    out: np.ndarray,
    row: int,
    col: int,
    factors: np.ndarray,
    first_plane: int,
    sums: tuple[float, ...],
    skip: int,
) -> None:
    """``out[first_plane + k, row, col] += factors[first_plane + k, col] * sums[k]``,
    for ``k >= skip``."""
    for k in range(skip, len(sums)):
        plane = first_plane + k
        out[plane, row, col] += factors[plane, col] * sums[k]


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
    """Kernel of :func:`accumulate_warped`; ``flat_pixels`` is ``(ny_in, nx_in, P)`` raveled.

    Up to eight planes go in one pass over the taps; more go eight at a time, the last
    group overlapping planes already done (their sums are dropped), so every plane's
    arithmetic is the same whatever ``P``.
    """
    n_planes = plane_weights.shape[0]
    n_cols = x_src.shape[1]
    tap_stride = np.uint64(n_planes)
    row_stride = np.uint64(nx_in) * tap_stride
    table = np.empty((TABLE_ROWS, n_cols))
    factors = np.empty((n_planes, n_cols))
    span = N_TAPS * n_planes  # elements in one row of a footprint
    for row in range(x_src.shape[0]):
        fill_row_table(x_src, y_src, row, table)
        for p in range(n_planes):
            which = plane_scales[p]
            weight = plane_weights[p]
            for col in range(n_cols):
                factors[p, col] = weight * scales[which, row, col] if which >= 0 else weight
        for col in range(n_cols):
            ahead = col + _PREFETCH_AHEAD
            if col % _PREFETCH_EVERY == 0 and ahead < n_cols:
                _prefetch_footprint(flat_pixels, table, ahead, row_stride, tap_stride, span)
            source = exact_source_index(table, col, row_stride, tap_stride)
            if source >= 0:
                # Integral position: copy, as warp_planes does.
                for p in range(n_planes):
                    value = flat_pixels[np.uint64(source) + np.uint64(p)]
                    out[p, row, col] += factors[p, col] * value
                continue
            corner = footprint_corner(table, col, row_stride, tap_stride)
            args = (flat_pixels, corner, row_stride, tap_stride, table, col)
            if n_planes == 1:
                # A lone plane: its six taps along x are adjacent.
                # numba intrinsic: mypy sees the typer's signature, with typingctx first
                total = block_sum_adjacent(flat_pixels, corner, row_stride, table, col)  # type: ignore[call-arg, var-annotated]
                out[0, row, col] += factors[0, col] * total
            elif n_planes == 2:
                _add_sums(out, row, col, factors, 0, _block_sums2(*args), 0)
            elif n_planes == 3:
                _add_sums(out, row, col, factors, 0, _block_sums3(*args), 0)
            elif n_planes == 4:
                _add_sums(out, row, col, factors, 0, _block_sums4(*args), 0)
            elif n_planes == 5:
                _add_sums(out, row, col, factors, 0, _block_sums5(*args), 0)
            elif n_planes == 6:
                _add_sums(out, row, col, factors, 0, _block_sums6(*args), 0)
            elif n_planes == 7:
                _add_sums(out, row, col, factors, 0, _block_sums7(*args), 0)
            else:
                p = 0
                while p < n_planes:
                    first = min(p, n_planes - _MAX_PLANES_AT_ONCE)
                    sums = _block_sums8(
                        flat_pixels, corner + np.uint64(first), row_stride, tap_stride, table, col
                    )
                    _add_sums(out, row, col, factors, first, sums, p - first)
                    p += _MAX_PLANES_AT_ONCE


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
    x_src, y_src = check_positions(x_src, y_src, pixels.shape[:2])
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
