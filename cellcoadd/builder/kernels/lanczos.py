"""Normalised Lanczos-3 weights, computed for a run of output pixels at a time.

Conventions (see :mod:`cellcoadd.builder.kernels.warp`): 0-based input pixel coordinates with
pixel centres at integers; the taps of a position ``x`` are the input pixels
``floor(x) - 2 .. floor(x) + 3``; each 1-D set of six weights is divided by its sum; an
offset within ``1e-9`` px of an integer is taken as exactly integral.

Cost: per output pixel and axis one ``sin``/``cos`` pair of a small angle (a short
series) and one division. ``sin(pi (d - k)) = (-1)^k sin(pi d)`` is common to all taps
and cancels in the normalisation; ``sin(pi (d - k) / 3)`` follows from ``sin(pi d / 3)``
and ``cos(pi d / 3)`` by angle addition with the constants ``cos(k pi/3)``, ``sin(k pi/3)``.
The weights of a run of output pixels go into a table (:func:`fill_table`) in branch-free
loops that the compiler vectorises.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from cellcoadd.builder.kernels.descriptor import LANCZOS3
from cellcoadd.errors import CellCoaddValueError

KERNEL_HALF_WIDTH = LANCZOS3.half_width
"""Taps reach ``KERNEL_HALF_WIDTH`` pixels each side: ``floor(x) - 2`` to ``floor(x) + 3``."""

N_TAPS = LANCZOS3.taps
"""Taps per axis; numba takes module-level ints as compile-time constants."""

_FIRST_OFFSET = LANCZOS3.first_offset
_INTEGER_TOLERANCE = 1e-9  # px; closer offsets are taken as exact integers
_PI_OVER_3 = math.pi / 3.0
# Taylor coefficients of sin(a) / a and of sqrt(3) cos(a) in powers of a^2, applied as
# multiplications (a division by a constant is not turned into one).
_S1, _S2, _S3, _S4, _S5, _S6 = ((-1.0) ** k / math.factorial(2 * k + 1) for k in range(1, 7))
_R0, _R1, _R2, _R3, _R4, _R5, _R6, _R7 = (
    math.sqrt(3.0) * (-1.0) ** k / math.factorial(2 * k) for k in range(8)
)


@numba.njit(cache=True, inline="always")
def _sin_sqrt3_cos(angle: float) -> tuple[float, float]:
    """``(sin(angle), sqrt(3) cos(angle))`` for ``0 <= angle <= pi/6``, to double precision.

    Taylor series (truncation below 1e-16 on this range), summed in independent pieces
    (powers of ``angle^2``) rather than by Horner's rule for a shorter dependency chain;
    unlike ``math.sin`` it lets the per-row weight loop vectorise.
    """
    z = angle * angle
    z2 = z * z
    z4 = z2 * z2
    sin_series = (1.0 + z * _S1) + z2 * (_S2 + z * _S3) + z4 * ((_S4 + z * _S5) + z2 * _S6)
    cos_series = (
        (_R0 + z * _R1) + z2 * (_R2 + z * _R3) + z4 * ((_R4 + z * _R5) + z2 * (_R6 + z * _R7))
    )
    return angle * sin_series, cos_series


@numba.njit(cache=True, inline="always")
def lanczos_taps(
    position: float,
) -> tuple[float, float, float, float, float, float, float, float]:
    """Normalised Lanczos-3 weights of the six taps of one position, its floor, exact tap.

    Returns ``(w0, ..., w5, floor(position), exact)``: ``w_j`` weighs input pixel
    ``floor(position) - 2 + j``; ``exact`` is the input pixel the position is taken to
    coincide with, or -1.

    With ``d = position - floor(position)`` the weight of tap ``k = -2..3`` is
    proportional to ``(-1)^k sin(pi d) sin(pi (d - k) / 3) / (d - k)^2``; the common
    factor ``sin(pi d)`` cancels in the normalisation. The kernel is symmetric, so the
    weights for ``d > 1/2`` are those for ``1 - d`` in reverse order; working with
    ``min(d, 1 - d)`` keeps ``2 sin(pi (d - k) / 3) = 2 cos(k pi/3) sin(a) - 2 sin(k pi/3)
    cos(a)`` (``a = pi d / 3``) free of cancellation. Branch-free and in floating point
    only (AVX2 has no packed float -> int64 conversion), so loops over positions vectorise.
    """
    floor_position = np.floor(position)
    offset = position - floor_position
    mirrored = offset > 0.5
    near = 1.0 - offset if mirrored else offset
    sin_a, sqrt3_cos_a = _sin_sqrt3_cos(_PI_OVER_3 * near)
    # Numerators 2 sin(pi (d - k) / 3) up to the sign (-1)^k, for k = -2..3 (period 3).
    s0 = sqrt3_cos_a - sin_a
    s1 = -(sin_a + sqrt3_cos_a)
    s2 = sin_a + sin_a
    # Squared distances (d - k)^2. Dividing by each costs six divisions; multiplying
    # every numerator by the product of the *other* five squares instead gives the same
    # ratios, which is all the normalisation needs, with one division in total.
    q0 = (near + 2.0) * (near + 2.0)
    q1 = (near + 1.0) * (near + 1.0)
    q2 = near * near
    q3 = (near - 1.0) * (near - 1.0)
    q4 = (near - 2.0) * (near - 2.0)
    q5 = (near - 3.0) * (near - 3.0)
    q01 = q0 * q1
    q23 = q2 * q3
    q45 = q4 * q5
    q0123 = q01 * q23
    q2345 = q23 * q45
    q0145 = q01 * q45
    v0 = s0 * (q1 * q2345)
    v1 = s1 * (q0 * q2345)
    v2 = s2 * (q3 * q0145)
    v3 = s0 * (q2 * q0145)
    v4 = s1 * (q5 * q0123)
    v5 = s2 * (q4 * q0123)
    inverse_total = 1.0 / ((v0 + v1) + (v2 + v3) + (v4 + v5))
    integral = near < _INTEGER_TOLERANCE
    # For an integral position the expressions above are 0/0; the selects drop them.
    v0 = 0.0 if integral else v0 * inverse_total
    v1 = 0.0 if integral else v1 * inverse_total
    v2 = 1.0 if integral else v2 * inverse_total
    v3 = 0.0 if integral else v3 * inverse_total
    v4 = 0.0 if integral else v4 * inverse_total
    v5 = 0.0 if integral else v5 * inverse_total
    coincident = floor_position + 1.0 if mirrored else floor_position
    return (
        v5 if mirrored else v0,
        v4 if mirrored else v1,
        v3 if mirrored else v2,
        v2 if mirrored else v3,
        v1 if mirrored else v4,
        v0 if mirrored else v5,
        floor_position,
        coincident if integral else -1.0,
    )


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
            raise CellCoaddValueError(
                f"{name} must be 2-D (ny_out, nx_out), got shape {values.shape}", value=values.shape
            )
        if values.dtype != np.float64:
            raise CellCoaddValueError(
                f"{name} must be float64, got {values.dtype}", value=values.dtype
            )
    if x_src.shape != y_src.shape:
        raise CellCoaddValueError(f"x_src {x_src.shape} and y_src {y_src.shape} differ in shape")
    if x_src.size == 0:
        return np.ascontiguousarray(x_src), np.ascontiguousarray(y_src), (0, 0, 0, 0)
    # min and max propagate NaN and expose infinities: one pass each checks both.
    ranges = [(float(values.min()), float(values.max())) for values in (x_src, y_src)]
    if not all(math.isfinite(bound) for bounds in ranges for bound in bounds):
        raise CellCoaddValueError("x_src and y_src must be finite")
    ny_in, nx_in = input_shape
    taps = []
    for axis, (low, high), size in (("x", ranges[0], nx_in), ("y", ranges[1], ny_in)):
        first_tap, stop_tap = LANCZOS3.tap_range(low, high)
        if first_tap < 0 or stop_tap > size:
            raise CellCoaddValueError(
                f"kernel taps along {axis} span input pixels [{first_tap}, {stop_tap - 1}] "
                f"but the input has pixels [0, {size - 1}]",
                value=(first_tap, stop_tap - 1),
                allowed=(0, size - 1),
            )
        # the first taps of the lowest and of the highest position
        taps += [first_tap, stop_tap - N_TAPS]
    x_lo, x_hi, y_lo, y_hi = taps
    return np.ascontiguousarray(x_src), np.ascontiguousarray(y_src), (x_lo, x_hi, y_lo, y_hi)


# The table of a run of up to TABLE_WIDTH output pixels along a row (one column each):
# rows 0-5 the x weights, 6 floor(x), 7 the exact x tap (or -1), rows 8-15 the same for y.
TABLE_ROWS = 16
TABLE_WIDTH = 256
"""Output pixels per table: the kernels resample rows in runs of this many pixels."""
WEIGHT_X = 0
_FLOOR_X, _EXACT_X = N_TAPS, N_TAPS + 1
WEIGHT_Y = 8
_FLOOR_Y, _EXACT_Y = WEIGHT_Y + N_TAPS, WEIGHT_Y + N_TAPS + 1


@numba.njit(cache=True, error_model="numpy")
def _axis_table(positions: np.ndarray, table: np.ndarray, base: int) -> None:
    """``table[base + j, i]``: the ``j``-th value of ``lanczos_taps(positions[i])``."""
    for i in range(positions.shape[0]):
        w0, w1, w2, w3, w4, w5, floor_position, exact = lanczos_taps(positions[i])
        table[base, i] = w0
        table[base + 1, i] = w1
        table[base + 2, i] = w2
        table[base + 3, i] = w3
        table[base + 4, i] = w4
        table[base + 5, i] = w5
        table[base + 6, i] = floor_position
        table[base + 7, i] = exact


@numba.njit(cache=True)
def fill_table(
    x_src: np.ndarray,
    y_src: np.ndarray,
    row_stride: int,
    tap_stride: int,
    origin: tuple[int, int],
    table: np.ndarray,
    corners: np.ndarray,
    sources: np.ndarray,
) -> None:
    """Weights and input indices of a run of output pixels at input positions ``(x_src,
    y_src)`` (1-D, at most ``TABLE_WIDTH`` long).

    Fills ``table`` (``(TABLE_ROWS, TABLE_WIDTH)``: rows 0-5 the x weights of
    :func:`lanczos_taps`, 6 floor(x), 7 the exact x tap or -1; 8-15 the same for y) and,
    for input pixel ``(x, y)`` stored at flat index ``(y - origin[1]) row_stride + (x -
    origin[0]) tap_stride``, ``corners[i]``: the index of the first tap (top left of the
    6x6 footprint); ``sources[i]``: the index of the input pixel the output pixel
    coincides with, or -1. Loops over pixels without branches: they vectorise.
    """
    n = x_src.shape[0]
    _axis_table(x_src, table, WEIGHT_X)
    _axis_table(y_src, table, WEIGHT_Y)
    x0, y0 = origin
    for i in range(n):
        first_x = np.int64(table[_FLOOR_X, i]) + _FIRST_OFFSET - x0
        first_y = np.int64(table[_FLOOR_Y, i]) + _FIRST_OFFSET - y0
        corners[i] = first_y * row_stride + first_x * tap_stride
        exact_x = table[_EXACT_X, i]
        exact_y = table[_EXACT_Y, i]
        source = (np.int64(exact_y) - y0) * row_stride + (np.int64(exact_x) - x0) * tap_stride
        sources[i] = source if (exact_x >= 0.0) & (exact_y >= 0.0) else -1
