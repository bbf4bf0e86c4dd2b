"""Normalised, separable Lanczos-3 resampling of several planes at once.

Conventions
-----------
* Coordinates are 0-based pixel coordinates of the *input* planes with pixel centres at
  integers (see :mod:`cellcoadd.geometry.box`).
* For an output pixel mapped to input position ``(x, y)`` the taps along x are the six
  input columns ``floor(x) - 2 .. floor(x) + 3`` (same for y), weighted by
  ``L3(x - tap)`` with ``L3(t) = sinc(t) sinc(t / 3)`` for ``|t| < 3``. Each 1-D set of
  six weights is divided by its sum, so the 2-D weights sum to one and a constant input
  is reproduced exactly (up to rounding).
* A fractional offset within ``1e-9`` px of an integer is treated as exactly integer
  (weights ``[0, 0, 1, 0, 0, 0]`` or ``[0, 0, 0, 1, 0, 0]``); an output pixel that is
  integral in both axes copies its input pixel bit for bit.
* The weights of an output pixel are computed once and applied to every plane, so
  image, noise realizations and masked-fraction planes are resampled identically.
* Non-finite input values propagate to every output pixel whose 6x6 footprint contains
  them; callers replace masked pixels before warping.

The weights of a whole output row are computed first (:mod:`cellcoadd.builder.kernels.lanczos`),
then applied to every plane. The 6x6 sums use SIMD vectors of up to
four doubles (AVX2), written out explicitly (see ``column_sums``).

Two layouts: :func:`warp_planes` takes the planes one after another ``(P, ny, nx)`` (the
six taps of a row are adjacent: one vector of 4 and one of 2 per input row);
:func:`accumulate_warped` takes them interleaved ``(ny, nx, P)``, so the values of all
planes at an input pixel share cache lines and fill the vector lanes (up to eight planes
per pass over the 6x6 block), and adds each plane with its own weight and scale straight
into the caller's sums. Both perform the same operations in the same order on every
plane: the results are identical bit for bit.
:func:`warp_mask_or` spreads mask bits over the same footprints (separably).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.core.base import BaseContext
from numba.extending import intrinsic

from cellcoadd.builder.kernels.lanczos import (
    KERNEL_HALF_WIDTH,
    N_TAPS,
    TABLE_ROWS,
    WEIGHT_Y,
    exact_source_index,
    fill_row_table,
    footprint_corner,
)

# The 6x6 sums. Every plane is summed the same way whatever the layout, which makes the
# two layouts' results identical: first the six column sums
#     c_b = ((wy_0 v[0, b] + wy_1 v[1, b]) + (wy_2 v[2, b] + wy_3 v[3, b]))
#           + (wy_4 v[4, b] + wy_5 v[5, b])
# then the same pairwise tree over wx_b c_b, with separate multiplications and additions
# (no fused multiply-add: the bits do not depend on the processor). The pairwise order
# shortens the dependency chains. The sums are written in LLVM IR with explicit SIMD
# vectors, as numba leaves LLVM's straight-line (SLP) vectoriser off and six-tap loops are
# unrolled before the loop vectoriser sees them. The lanes of a vector are either columns
# of one plane (planes stored one after the other) or planes of one input pixel (planes
# interleaved); lane-wise IEEE arithmetic gives the bits of the scalar formula. Every
# vector load covers taps only: nothing outside the 6x6 footprint is read.

LLVM_I32 = ir.IntType(32)
LLVM_I64 = ir.IntType(64)
_F64 = ir.DoubleType()


def is_flat_array(array_type: types.Type) -> bool:
    """Whether the sums can read ``array_type`` by flat index: 1-D, contiguous, floats."""
    return (
        isinstance(array_type, types.Array)
        and array_type.ndim == 1
        and array_type.layout == "C"
        and array_type.dtype in (types.float32, types.float64)
    )


def splat(builder: ir.IRBuilder, value: ir.Value, width: int) -> ir.Value:
    """``<width x double>`` with every lane equal to ``value``."""
    vector = builder.insert_element(
        ir.Constant(ir.VectorType(_F64, width), ir.Undefined), value, ir.Constant(LLVM_I32, 0)
    )
    lanes = ir.Constant(ir.VectorType(LLVM_I32, width), [0] * width)
    return builder.shuffle_vector(vector, vector, lanes)


def tree_sum(builder: ir.IRBuilder, terms: list[ir.Value]) -> ir.Value:
    """``((t0 + t1) + (t2 + t3)) + (t4 + t5)`` of six LLVM values."""
    return builder.fadd(
        builder.fadd(builder.fadd(terms[0], terms[1]), builder.fadd(terms[2], terms[3])),
        builder.fadd(terms[4], terms[5]),
    )


def column_sums(
    context: BaseContext,
    builder: ir.IRBuilder,
    flat_type: types.Array,
    flat: ir.Value,
    start: ir.Value,
    row_stride: ir.Value,
    weights_y: list[ir.Value],
    width: int,
) -> ir.Value:
    """``<width x double>``: ``sum_a weights_y[a] * flat[start + a row_stride + lane]``."""
    data = context.make_array(flat_type)(context, builder, flat).data
    element = context.get_data_type(flat_type.dtype)
    loaded_type = ir.VectorType(element, width)
    terms = []
    for a in range(N_TAPS):
        index = builder.add(start, builder.mul(row_stride, ir.Constant(LLVM_I64, a)))
        pointer = builder.bitcast(
            builder.gep(data, [index], inbounds=True), loaded_type.as_pointer()
        )
        # numba types Array.dtype as a plain Type; here it is always a Float with a bitwidth
        align = flat_type.dtype.bitwidth // 8  # type: ignore[attr-defined]
        values = builder.load(pointer, align=align, typ=loaded_type)
        if element != _F64:
            values = builder.fpext(values, ir.VectorType(_F64, width))
        terms.append(builder.fmul(weights_y[a], values))
    return tree_sum(builder, terms)


def table_weights(
    context: BaseContext,
    builder: ir.IRBuilder,
    table_type: types.Array,
    table: ir.Value,
    col: ir.Value,
    first_row: int,
) -> list[ir.Value]:
    """LLVM values of ``table[first_row + j, col]`` for the six taps ``j``.

    Loaded inside each sum: as memory operands of broadcasts they cost no registers.
    """
    array = context.make_array(table_type)(context, builder, table)
    rows = [ir.Constant(LLVM_I64, first_row + j) for j in range(N_TAPS)]
    return [
        builder.load(
            cgutils.get_item_pointer(context, builder, table_type, array, [row, col]), typ=_F64
        )
        for row in rows
    ]


@intrinsic
def block_sum_adjacent(typingctx, flat, corner, row_stride, table, col):
    """6x6 weighted sum of one plane whose taps along x are adjacent in ``flat``.

    ``flat[corner]`` is the first tap; rows of taps are ``row_stride`` apart; the weights
    are those of output pixel ``col`` in ``table`` (see
    :func:`cellcoadd.builder.kernels.lanczos.fill_row_table`).
    """
    if not is_flat_array(flat):
        return None
    signature = types.float64(flat, corner, row_stride, table, col)

    def codegen(context, builder, signature, args):
        flat, corner, row_stride, table, col = args
        flat_type, table_type = signature.args[0], signature.args[3]
        weights_y = table_weights(context, builder, table_type, table, col, WEIGHT_Y)
        weights_x = table_weights(context, builder, table_type, table, col, 0)
        columns = []
        for first, width in ((0, 4), (4, 2)):
            start = builder.add(corner, ir.Constant(LLVM_I64, first))
            splats = [splat(builder, weight, width) for weight in weights_y]
            sums = column_sums(context, builder, flat_type, flat, start, row_stride, splats, width)
            columns += [
                builder.extract_element(sums, ir.Constant(LLVM_I32, k)) for k in range(width)
            ]
        return tree_sum(builder, [builder.fmul(weights_x[b], columns[b]) for b in range(N_TAPS)])

    return signature, codegen


@numba.njit(cache=True)
def _warp_row(
    flat_planes: np.ndarray,
    plane_shape: tuple[int, int],
    x_src: np.ndarray,
    y_src: np.ndarray,
    out: np.ndarray,
    weight: float,
    scale: np.ndarray,
    use_scale: bool,
    row: int,
    table: np.ndarray,
) -> None:
    """Accumulate ``weight * scale * warp(planes)`` into output row ``row`` of ``out``.

    ``flat_planes`` is the C-ordered ``(P, ny_in, nx_in)`` stack raveled; unsigned flat
    indices spare numba the negative-index wrap-around test on every tap. ``table`` is
    scratch space of shape ``(TABLE_ROWS, nx_out)``.
    """
    n_planes = out.shape[0]
    ny_in, nx_in = plane_shape
    row_stride = np.uint64(nx_in)
    plane_stride = np.uint64(ny_in * nx_in)
    one = np.uint64(1)
    fill_row_table(x_src, y_src, row, table)
    for col in range(x_src.shape[1]):
        factor = weight * scale[row, col] if use_scale else weight
        source = exact_source_index(table, col, row_stride, one)
        if source >= 0:
            # Integral position: copy (bit for bit, and immune to non-finite neighbours).
            for p in range(n_planes):
                value = flat_planes[np.uint64(p) * plane_stride + np.uint64(source)]
                out[p, row, col] += factor * value
            continue
        corner = footprint_corner(table, col, row_stride, one)
        for p in range(n_planes):
            start = np.uint64(p) * plane_stride + corner
            # numba intrinsic: mypy sees the typer's signature, with typingctx first
            total = block_sum_adjacent(flat_planes, start, row_stride, table, col)  # type: ignore[call-arg, var-annotated]
            out[p, row, col] += factor * total


@numba.njit(cache=True)
def _warp_serial(
    flat_planes: np.ndarray,
    plane_shape: tuple[int, int],
    x_src: np.ndarray,
    y_src: np.ndarray,
    out: np.ndarray,
    weight: float,
    scale: np.ndarray,
    use_scale: bool,
) -> None:
    table = np.empty((TABLE_ROWS, x_src.shape[1]))
    for row in range(x_src.shape[0]):
        _warp_row(flat_planes, plane_shape, x_src, y_src, out, weight, scale, use_scale, row, table)


def check_positions(
    x_src: np.ndarray, y_src: np.ndarray, input_shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Validate the output->input positions; return them as C-contiguous float64 arrays."""
    x_src, y_src, _ = checked_positions_and_taps(x_src, y_src, input_shape)
    return x_src, y_src


def checked_positions_and_taps(
    x_src: np.ndarray, y_src: np.ndarray, input_shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int, int]]:
    """:func:`check_positions`, and the range of first taps ``(x_lo, x_hi, y_lo, y_hi)``
    (all zero for an empty output)."""
    x_src = np.asarray(x_src)
    y_src = np.asarray(y_src)
    for name, values in (("x_src", x_src), ("y_src", y_src)):
        if values.ndim != 2:
            raise ValueError(f"{name} must be 2-D (ny_out, nx_out), got shape {values.shape}")
        if values.dtype != np.float64:
            raise ValueError(f"{name} must be float64, got {values.dtype}")
    if x_src.shape != y_src.shape:
        raise ValueError(f"x_src {x_src.shape} and y_src {y_src.shape} differ in shape")
    if x_src.size == 0:
        return np.ascontiguousarray(x_src), np.ascontiguousarray(y_src), (0, 0, 0, 0)
    # min and max propagate NaN and expose infinities: one pass each checks both.
    ranges = [(float(values.min()), float(values.max())) for values in (x_src, y_src)]
    if not all(math.isfinite(bound) for bounds in ranges for bound in bounds):
        raise ValueError("x_src and y_src must be finite")
    ny_in, nx_in = input_shape
    taps = []
    for axis, (low, high), size in (("x", ranges[0], nx_in), ("y", ranges[1], ny_in)):
        first_tap = math.floor(low) - (KERNEL_HALF_WIDTH - 1)
        last_tap = math.floor(high) + KERNEL_HALF_WIDTH
        if first_tap < 0 or last_tap > size - 1:
            raise ValueError(
                f"kernel taps along {axis} span input pixels [{first_tap}, {last_tap}] "
                f"but the input has pixels [0, {size - 1}]"
            )
        taps += [first_tap, last_tap - (2 * KERNEL_HALF_WIDTH - 1)]
    x_lo, x_hi, y_lo, y_hi = taps
    return np.ascontiguousarray(x_src), np.ascontiguousarray(y_src), (x_lo, x_hi, y_lo, y_hi)


def warp_planes(
    planes: np.ndarray,
    x_src: np.ndarray,
    y_src: np.ndarray,
    out: np.ndarray | None = None,
    weight: float = 1.0,
    scale: np.ndarray | None = None,
) -> np.ndarray:
    """Resample several planes with one normalised Lanczos-3 kernel and accumulate.

    Parameters
    ----------
    planes : ndarray, shape (P, ny_in, nx_in), float32 or float64
        Input planes sharing one pixel grid (image, noise realizations, masked fraction...).
    x_src, y_src : ndarray, shape (ny_out, nx_out), float64
        Position of each output pixel centre in input pixel coordinates (0-based, centres
        at integers). Every tap ``floor(.) - 2 .. floor(.) + 3`` must lie inside the input.
    out : ndarray, shape (P, ny_out, nx_out), float64, optional
        C-contiguous accumulator, updated in place as ``out += weight * scale * warped``.
        A zeroed array is created when omitted.
    weight : float
        Scalar weight of this input (e.g. inverse background variance).
    scale : ndarray, shape (ny_out, nx_out), optional
        Per-output-pixel factor, e.g. the pixel-area ratio that converts surface
        brightness per input pixel into per output pixel. ``None`` means one.

    Returns
    -------
    ndarray, shape (P, ny_out, nx_out), float64
        ``out`` (the same object when given).

    Raises
    ------
    ValueError
        Bad shapes or dtypes, non-finite positions or weight, or taps outside the input.
    """
    planes = np.asarray(planes)
    if planes.ndim != 3:
        raise ValueError(f"planes must be 3-D (P, ny_in, nx_in), got shape {planes.shape}")
    if planes.dtype not in (np.float32, np.float64):
        raise ValueError(f"planes must be float32 or float64, got {planes.dtype}")
    x_src, y_src = check_positions(x_src, y_src, planes.shape[1:])
    out_shape = (planes.shape[0], *x_src.shape)
    if out is None:
        out = np.zeros(out_shape, dtype=np.float64)
    elif not isinstance(out, np.ndarray) or out.dtype != np.float64 or out.shape != out_shape:
        raise ValueError(f"out must be a float64 array of shape {out_shape}")
    elif not out.flags.c_contiguous or not out.flags.writeable:
        raise ValueError("out must be C-contiguous and writeable")
    weight = float(weight)
    if not math.isfinite(weight):
        raise ValueError(f"weight must be finite, got {weight}")
    if scale is None:
        use_scale = False
        scale_array = np.ones((1, 1), dtype=np.float64)
    else:
        use_scale = True
        scale_array = np.ascontiguousarray(scale, dtype=np.float64)
        if scale_array.shape != x_src.shape:
            raise ValueError(f"scale has shape {scale_array.shape}, expected {x_src.shape}")
    if x_src.size == 0:
        return out
    flat_planes = np.ascontiguousarray(planes).reshape(-1)
    plane_shape = (int(planes.shape[1]), int(planes.shape[2]))
    _warp_serial(flat_planes, plane_shape, x_src, y_src, out, weight, scale_array, use_scale)
    return out
