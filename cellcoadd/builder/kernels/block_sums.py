"""The 6x6 weighted sums of the Lanczos-3 warp, written in LLVM IR with explicit SIMD vectors.

Every plane ``p`` of an output pixel is summed the same way, whatever the number of planes
and wherever the pixel lies in the output:

* column sums ``c_b = ((wy_0 v[0, b] + wy_1 v[1, b]) + (wy_2 v[2, b] + wy_3 v[3, b]))
  + (wy_4 v[4, b] + wy_5 v[5, b])`` for the six taps ``b`` along x,
* then ``((wx_0 c_0 + wx_1 c_1) + (wx_2 c_2 + wx_3 c_3)) + (wx_4 c_4 + wx_5 c_5)``,

with separate multiplications and additions (no fused multiply-add, so the bits do not
depend on the processor). Vector lanes only ever hold independent values and IEEE
arithmetic is lane-wise, so a value's bits do not depend on the lane that computes it.

The planes are interleaved: tap ``(a, b)`` of plane ``p`` is ``flat[corner + a * row_stride
+ b * P + p]``, so one row of a footprint is ``6 P`` adjacent values. For ``P <= 8`` the
column sums run over whole footprint rows cut into vectors of four doubles (AVX2; nine
vectors per row for six planes instead of twelve of four plus two lanes, whose half-empty
vectors would cost the same as full ones), then lane shuffles regroup the column sums per
plane for the second stage. More planes go eight at a time, tap by tap. Each load covers
taps only: nothing outside the 6x6 footprint is read.

numba leaves LLVM's straight-line (SLP) vectoriser off and unrolls six-tap loops before
its loop vectoriser sees them, hence the explicit IR.

The weights come from a table of ``TABLE_ROWS`` rows of ``TABLE_WIDTH`` doubles
(:mod:`cellcoadd.builder.kernels.lanczos`); the sums go to ``sums[plane, col]``, an array of
``TABLE_WIDTH`` columns. Both widths are compile-time constants, so each weight is one
load at a fixed offset.

numba's on-disk cache of a function is keyed by its own source file only: after changing
this file, clear the cache (``__pycache__/*.nbi``, ``*.nbc`` next to the kernels) or
touch :mod:`cellcoadd.builder.kernels.accumulate`.
"""

from __future__ import annotations

from collections.abc import Callable

from llvmlite import ir
from numba.core import types
from numba.core.base import BaseContext
from numba.extending import intrinsic

from cellcoadd.builder.kernels.lanczos import N_TAPS, TABLE_WIDTH, WEIGHT_X, WEIGHT_Y

_I32 = ir.IntType(32)
_I64 = ir.IntType(64)
_F64 = ir.DoubleType()
_LANES = 4  # doubles per vector (AVX2; on Zen 4 AVX-512 vectors are no faster here)
MAX_PLANES_AT_ONCE = 8
"""Planes summed in one pass over a footprint; more go in groups of this many."""


def _int(value: int) -> ir.Constant:
    return ir.Constant(_I64, value)


def _tree(builder: ir.IRBuilder, terms: list[ir.Value]) -> ir.Value:
    """The sum of ``terms`` in the order of every tap sum: adjacent pairs, repeatedly (an
    odd last term waits for the next round); for six taps
    ``((t0 + t1) + (t2 + t3)) + (t4 + t5)``, as
    :func:`cellcoadd.builder.kernels.reference.tap_sum`."""
    while len(terms) > 1:
        pairs = [builder.fadd(terms[k], terms[k + 1]) for k in range(0, len(terms) - 1, 2)]
        terms = pairs + terms[len(pairs) * 2 :]
    return terms[0]


def _splat(builder: ir.IRBuilder, value: ir.Value, width: int) -> ir.Value:
    """``<width x double>`` with every lane ``value`` (``value`` itself for one lane)."""
    if width == 1:
        return value
    vector_type = ir.VectorType(_F64, width)
    vector = builder.insert_element(
        ir.Constant(vector_type, ir.Undefined), value, ir.Constant(_I32, 0)
    )
    return builder.shuffle_vector(
        vector, vector, ir.Constant(ir.VectorType(_I32, width), [0] * width)
    )


def _load(builder: ir.IRBuilder, data: ir.Value, index: ir.Value, width: int) -> ir.Value:
    """``width`` doubles from ``data[index]`` on (a scalar for one)."""
    pointer = builder.gep(data, [index], inbounds=True)
    if width == 1:
        return builder.load(pointer, align=8)
    vector_pointer = builder.bitcast(pointer, ir.VectorType(_F64, width).as_pointer())
    return builder.load(vector_pointer, align=8)


def _table_weights(
    builder: ir.IRBuilder, table: ir.Value, col: ir.Value, first_row: int
) -> list[ir.Value]:
    """The six weights ``table[first_row + j, col]``; as memory operands of broadcasts
    they cost no registers."""
    return [
        builder.load(
            builder.gep(table, [builder.add(col, _int((first_row + j) * TABLE_WIDTH))]),
            align=8,
        )
        for j in range(N_TAPS)
    ]


def _lanes(builder: ir.IRBuilder, vectors: list[ir.Value], start: int, width: int) -> ir.Value:
    """Elements ``start .. start + width - 1`` of the concatenated four-lane ``vectors``
    (the last may be shorter), as one vector (a scalar for one element)."""
    first, lane = divmod(start, _LANES)
    last = (start + width - 1) // _LANES
    if width == 1:
        return builder.extract_element(vectors[first], ir.Constant(_I32, lane))
    if lane == 0 and width == vectors[first].type.count:
        return vectors[first]

    def widened(vector: ir.Value) -> ir.Value:
        if vector.type.count == _LANES:
            return vector
        indices = list(range(vector.type.count)) + [0] * (_LANES - vector.type.count)
        return builder.shuffle_vector(
            vector, vector, ir.Constant(ir.VectorType(_I32, _LANES), indices)
        )

    low = widened(vectors[first])
    high = widened(vectors[last]) if last != first else low
    # lanes of `high` are numbered _LANES.. in a two-operand shuffle
    indices = [lane + j for j in range(width)]
    return builder.shuffle_vector(low, high, ir.Constant(ir.VectorType(_I32, width), indices))


def _plane_pieces(n_planes: int) -> list[tuple[int, int]]:
    """``(first plane, lanes)`` of the vectors that hold the planes in the second stage."""
    widths = [_LANES] * (n_planes // _LANES) + ([n_planes % _LANES] if n_planes % _LANES else [])
    pieces, first = [], 0
    for width in widths:
        pieces.append((first, width))
        first += width
    return pieces


def _store_transposed(
    builder: ir.IRBuilder,
    sums: ir.Value,
    col: ir.Value,
    first_plane: ir.Value,
    total: ir.Value,
    width: int,
) -> None:
    """``sums[first_plane + k, col] = total[k]`` for the ``width`` lanes of ``total``."""
    for k in range(width):
        value = total if width == 1 else builder.extract_element(total, ir.Constant(_I32, k))
        row = builder.mul(builder.add(first_plane, _int(k)), _int(TABLE_WIDTH))
        builder.store(value, builder.gep(sums, [builder.add(row, col)]), align=8)


def _is_flat(array_type: types.Type) -> bool:
    return (
        isinstance(array_type, types.Array)
        and array_type.ndim == 1
        and array_type.layout == "C"
        and array_type.dtype == types.float64
    )


def _is_table(array_type: types.Type) -> bool:
    return (
        isinstance(array_type, types.Array)
        and array_type.ndim == 2
        and array_type.layout == "C"
        and array_type.dtype == types.float64
    )


def _data(context: BaseContext, builder: ir.IRBuilder, array_type: types.Array, array: ir.Value):
    return context.make_array(array_type)(context, builder, array).data


def _make_whole_rows(n_planes: int) -> Callable:
    """Intrinsic ``(flat, corner, row_stride, table, col, sums)`` for ``n_planes`` planes.

    Column sums over whole footprint rows of ``6 n_planes`` values, regrouped per plane.
    """
    row_length = N_TAPS * n_planes
    chunks = [_LANES] * (row_length // _LANES)
    if row_length % _LANES:
        chunks.append(row_length % _LANES)
    pieces = _plane_pieces(n_planes)

    def typer(typingctx, flat, corner, row_stride, table, col, sums):
        if not (_is_flat(flat) and _is_table(table) and _is_table(sums)):
            return None
        signature = types.void(flat, corner, row_stride, table, col, sums)

        def codegen(context, builder, signature, args):
            flat, corner, row_stride, table, col, sums = args
            flat_type, _, _, table_type, _, sums_type = signature.args
            data = _data(context, builder, flat_type, flat)
            weights = _data(context, builder, table_type, table)
            output = _data(context, builder, sums_type, sums)
            weights_y = _table_weights(builder, weights, col, WEIGHT_Y)
            weights_x = _table_weights(builder, weights, col, WEIGHT_X)
            rows = [builder.add(corner, builder.mul(row_stride, _int(a))) for a in range(N_TAPS)]
            columns = []
            for k, width in enumerate(chunks):
                splats = [_splat(builder, weight, width) for weight in weights_y]
                offset = _int(_LANES * k)
                terms = [
                    builder.fmul(
                        splats[a], _load(builder, data, builder.add(rows[a], offset), width)
                    )
                    for a in range(N_TAPS)
                ]
                columns.append(_tree(builder, terms))
            for first, width in pieces:
                terms = [
                    builder.fmul(
                        _splat(builder, weights_x[b], width),
                        _lanes(builder, columns, b * n_planes + first, width),
                    )
                    for b in range(N_TAPS)
                ]
                total = _tree(builder, terms)
                _store_transposed(builder, output, col, _int(first), total, width)
            return context.get_dummy_value()

        return signature, codegen

    return intrinsic(typer)


def _make_plane_groups() -> Callable:
    """Intrinsic ``(flat, corner, row_stride, tap_stride, table, col, sums, first_plane)``:
    planes ``first_plane .. first_plane + 7`` of a footprint of ``tap_stride`` planes."""
    pieces = _plane_pieces(MAX_PLANES_AT_ONCE)

    def typer(typingctx, flat, corner, row_stride, tap_stride, table, col, sums, first_plane):
        if not (_is_flat(flat) and _is_table(table) and _is_table(sums)):
            return None
        signature = types.void(flat, corner, row_stride, tap_stride, table, col, sums, first_plane)

        def codegen(context, builder, signature, args):
            flat, corner, row_stride, tap_stride, table, col, sums, first_plane = args
            flat_type, table_type, sums_type = (
                signature.args[0],
                signature.args[4],
                signature.args[6],
            )
            data = _data(context, builder, flat_type, flat)
            weights = _data(context, builder, table_type, table)
            output = _data(context, builder, sums_type, sums)
            weights_y = _table_weights(builder, weights, col, WEIGHT_Y)
            weights_x = _table_weights(builder, weights, col, WEIGHT_X)
            start = builder.add(corner, first_plane)
            rows = [builder.add(start, builder.mul(row_stride, _int(a))) for a in range(N_TAPS)]
            for first, width in pieces:
                splats = [_splat(builder, weight, width) for weight in weights_y]
                terms_x = []
                for b in range(N_TAPS):
                    offset = builder.add(builder.mul(tap_stride, _int(b)), _int(first))
                    terms = [
                        builder.fmul(
                            splats[a], _load(builder, data, builder.add(rows[a], offset), width)
                        )
                        for a in range(N_TAPS)
                    ]
                    terms_x.append(
                        builder.fmul(_splat(builder, weights_x[b], width), _tree(builder, terms))
                    )
                total = _tree(builder, terms_x)
                plane = builder.add(first_plane, _int(first))
                _store_transposed(builder, output, col, plane, total, width)
            return context.get_dummy_value()

        return signature, codegen

    return intrinsic(typer)


def _make_prefetch() -> Callable:
    """Intrinsic ``(array, index)``: ask the processor to bring the cache line holding
    element ``index`` (in memory order) of the C-contiguous float64 ``array`` into its
    caches (a hint: no fault, no effect on any value)."""

    def typer(typingctx, array, index):
        if not (
            isinstance(array, types.Array) and array.layout == "C" and array.dtype == types.float64
        ):
            return None
        signature = types.void(array, index)

        def codegen(context, builder, signature, args):
            data = _data(context, builder, signature.args[0], args[0])
            byte_pointer = ir.IntType(8).as_pointer()
            function = builder.module.declare_intrinsic(
                "llvm.prefetch",
                [byte_pointer],
                fnty=ir.FunctionType(ir.VoidType(), [byte_pointer, _I32, _I32, _I32]),
            )
            pointer = builder.bitcast(builder.gep(data, [args[1]]), byte_pointer)
            # read, keep in all cache levels, data cache
            flags = [ir.Constant(_I32, value) for value in (0, 3, 1)]
            builder.call(function, [pointer, *flags])
            return context.get_dummy_value()

        return signature, codegen

    return intrinsic(typer)


prefetch = _make_prefetch()

(
    block_sums_1,
    block_sums_2,
    block_sums_3,
    block_sums_4,
    block_sums_5,
    block_sums_6,
    block_sums_7,
    block_sums_8,
) = (_make_whole_rows(n) for n in range(1, MAX_PLANES_AT_ONCE + 1))
block_sums_group = _make_plane_groups()
