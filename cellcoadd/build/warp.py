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

Cost: per output pixel and axis one ``sin``/``cos`` pair of a small angle (a short
series) and one division. ``sin(pi (d - k)) = (-1)^k sin(pi d)`` is common to all taps
and cancels in the normalisation; ``sin(pi (d - k) / 3)`` follows from ``sin(pi d / 3)``
and ``cos(pi d / 3)`` by angle addition with the constants ``cos(k pi/3)``, ``sin(k pi/3)``.
The weights of a whole output row are computed first in a branch-free loop that the
compiler vectorises, then applied to every plane.

Two layouts: :func:`warp_planes` takes the planes one after another ``(P, ny, nx)``;
:func:`accumulate_warped` takes them interleaved ``(ny, nx, P)``, so the values of all
planes at an input pixel share cache lines and each 6x6 block is read once for four
planes, and adds each plane with its own weight and scale straight into the caller's
sums. Both perform the same operations in the same order: the results are identical.
:func:`warp_mask_or` spreads mask bits over the same footprints (separably).
"""

from __future__ import annotations

import math

import numba
import numpy as np

KERNEL_HALF_WIDTH = 3
"""Taps reach ``KERNEL_HALF_WIDTH`` pixels each side: ``floor(x) - 2 .. floor(x) + 3``."""

_N_TAPS = 2 * KERNEL_HALF_WIDTH
_INTEGER_TOLERANCE = 1e-9  # px; closer offsets are taken as exact integers
_HALF_SQRT3 = 0.5 * math.sqrt(3.0)
_PI_OVER_3 = math.pi / 3.0


@numba.njit(cache=True, inline="always")
def _sin_cos_small(angle: float) -> tuple[float, float]:
    """``(sin(angle), cos(angle))`` for ``0 <= angle <= pi/6`` to double precision.

    Taylor series (truncation below 1e-16 on this range); unlike ``math.sin`` it lets the
    per-row weight loop vectorise.
    """
    z = angle * angle
    sin_value = angle * (
        1.0
        + z
        * (
            -1.0 / 6.0
            + z
            * (
                1.0 / 120.0
                + z
                * (
                    -1.0 / 5040.0
                    + z * (1.0 / 362880.0 + z * (-1.0 / 39916800.0 + z / 6227020800.0))
                )
            )
        )
    )
    cos_value = 1.0 + z * (
        -0.5
        + z
        * (
            1.0 / 24.0
            + z
            * (
                -1.0 / 720.0
                + z
                * (
                    1.0 / 40320.0
                    + z * (-1.0 / 3628800.0 + z * (1.0 / 479001600.0 - z / 87178291200.0))
                )
            )
        )
    )
    return sin_value, cos_value


@numba.njit(cache=True, error_model="numpy")
def _axis_weights(
    positions: np.ndarray, weights: np.ndarray, first_tap: np.ndarray, exact_tap: np.ndarray
) -> None:
    """Normalised Lanczos-3 weights along one axis for a row of output pixels.

    Parameters
    ----------
    positions : ndarray, shape (n,)
        Input pixel coordinates of the output pixels.
    weights : ndarray, shape (6, n)
        Filled with the weight of tap ``first_tap + j`` in ``weights[j]``.
    first_tap : ndarray of uint64, shape (n,)
        Filled with ``floor(position) - 2`` (validated to be non-negative).
    exact_tap : ndarray of int64, shape (n,)
        Filled with the input pixel a position is taken to coincide with, or -1.

    Notes
    -----
    With ``d = position - floor(position)`` the weight of tap ``k = -2..3`` is
    proportional to ``(-1)^k sin(pi d) sin(pi (d - k) / 3) / (d - k)^2``; the common
    factor ``sin(pi d)`` cancels in the normalisation. The kernel is symmetric, so the
    weights for ``d > 1/2`` are those for ``1 - d`` in reverse order; working with
    ``min(d, 1 - d)`` keeps ``sin(pi (d - k) / 3) = sin(a) cos(k pi/3) - cos(a) sin(k pi/3)``
    (``a = pi d / 3``) free of cancellation. The loop is branch-free so it vectorises.
    """
    for i in range(positions.shape[0]):
        floor_position = math.floor(positions[i])
        offset = positions[i] - floor_position
        mirrored = offset > 0.5
        near = 1.0 - offset if mirrored else offset
        sin_a, cos_a = _sin_cos_small(_PI_OVER_3 * near)
        # Numerators sin(pi (d - k) / 3) up to the sign (-1)^k, for k = -2..3.
        s0 = _HALF_SQRT3 * cos_a - 0.5 * sin_a
        s1 = -(0.5 * sin_a + _HALF_SQRT3 * cos_a)
        s2 = sin_a
        s3 = _HALF_SQRT3 * cos_a - 0.5 * sin_a
        s4 = -(0.5 * sin_a + _HALF_SQRT3 * cos_a)
        s5 = sin_a
        # Squared distances (d - k)^2. Dividing by each costs six divisions; multiplying
        # every numerator by the product of the *other* five squares instead gives the
        # same ratios, which is all the normalisation needs, with one division in total.
        q0 = (near + 2.0) * (near + 2.0)
        q1 = (near + 1.0) * (near + 1.0)
        q2 = near * near
        q3 = (near - 1.0) * (near - 1.0)
        q4 = (near - 2.0) * (near - 2.0)
        q5 = (near - 3.0) * (near - 3.0)
        q01 = q0 * q1
        q012 = q01 * q2
        q45 = q4 * q5
        q345 = q3 * q45
        v0 = s0 * (q1 * q2 * q345)
        v1 = s1 * (q0 * q2 * q345)
        v2 = s2 * (q01 * q345)
        v3 = s3 * (q012 * q45)
        v4 = s4 * (q012 * q3 * q5)
        v5 = s5 * (q012 * q3 * q4)
        inverse_total = 1.0 / (v0 + v1 + v2 + v3 + v4 + v5)
        integral = near < _INTEGER_TOLERANCE
        # For an integral position the expressions above are 0/0; the selects drop them.
        v0 = 0.0 if integral else v0 * inverse_total
        v1 = 0.0 if integral else v1 * inverse_total
        v2 = 1.0 if integral else v2 * inverse_total
        v3 = 0.0 if integral else v3 * inverse_total
        v4 = 0.0 if integral else v4 * inverse_total
        v5 = 0.0 if integral else v5 * inverse_total
        weights[0, i] = v5 if mirrored else v0
        weights[1, i] = v4 if mirrored else v1
        weights[2, i] = v3 if mirrored else v2
        weights[3, i] = v2 if mirrored else v3
        weights[4, i] = v1 if mirrored else v4
        weights[5, i] = v0 if mirrored else v5
        floor_index = np.int64(floor_position)
        first_tap[i] = np.uint64(floor_index - 2)
        coincident = floor_index + 1 if mirrored else floor_index
        exact_tap[i] = coincident if integral else -1


@numba.njit(cache=True, inline="always")
def _tap_row(
    flat: np.ndarray,
    start: np.uint64,
    tap_stride: np.uint64,
    wx0: float,
    wx1: float,
    wx2: float,
    wx3: float,
    wx4: float,
    wx5: float,
) -> float:
    """Six x-taps of one input row, summed left to right (the order fixes the bits)."""
    return (
        wx0 * flat[start]
        + wx1 * flat[start + tap_stride]
        + wx2 * flat[start + np.uint64(2) * tap_stride]
        + wx3 * flat[start + np.uint64(3) * tap_stride]
        + wx4 * flat[start + np.uint64(4) * tap_stride]
        + wx5 * flat[start + np.uint64(5) * tap_stride]
    )


@numba.njit(cache=True, inline="always")
def _block_sum(
    flat: np.ndarray,
    corner: np.uint64,
    row_stride: np.uint64,
    tap_stride: np.uint64,
    wx: tuple[float, float, float, float, float, float],
    weights_y: np.ndarray,
    col: int,
) -> float:
    """The 6x6 weighted sum of one plane: rows of taps accumulated from the first."""
    wx0, wx1, wx2, wx3, wx4, wx5 = wx
    total = 0.0
    for a in range(_N_TAPS):
        start = corner + np.uint64(a) * row_stride
        total += weights_y[a, col] * _tap_row(flat, start, tap_stride, wx0, wx1, wx2, wx3, wx4, wx5)
    return total


@numba.njit(cache=True, inline="always")
def _block_sums4(
    flat: np.ndarray,
    corner: np.uint64,
    row_stride: np.uint64,
    tap_stride: np.uint64,
    wx: tuple[float, float, float, float, float, float],
    weights_y: np.ndarray,
    col: int,
) -> tuple[float, float, float, float]:
    """:func:`_block_sum` of four interleaved planes at once (same operations per plane).

    Their values of one input pixel share a cache line, so one pass over the 6x6 block
    serves all four.
    """
    wx0, wx1, wx2, wx3, wx4, wx5 = wx
    one, two, three = np.uint64(1), np.uint64(2), np.uint64(3)
    total0 = total1 = total2 = total3 = 0.0
    for a in range(_N_TAPS):
        start = corner + np.uint64(a) * row_stride
        wy = weights_y[a, col]
        total0 += wy * _tap_row(flat, start, tap_stride, wx0, wx1, wx2, wx3, wx4, wx5)
        total1 += wy * _tap_row(flat, start + one, tap_stride, wx0, wx1, wx2, wx3, wx4, wx5)
        total2 += wy * _tap_row(flat, start + two, tap_stride, wx0, wx1, wx2, wx3, wx4, wx5)
        total3 += wy * _tap_row(flat, start + three, tap_stride, wx0, wx1, wx2, wx3, wx4, wx5)
    return total0, total1, total2, total3


@numba.njit(cache=True, inline="always")
def _block_sums2(
    flat: np.ndarray,
    corner: np.uint64,
    row_stride: np.uint64,
    tap_stride: np.uint64,
    wx: tuple[float, float, float, float, float, float],
    weights_y: np.ndarray,
    col: int,
) -> tuple[float, float]:
    """:func:`_block_sums4` for two interleaved planes."""
    wx0, wx1, wx2, wx3, wx4, wx5 = wx
    one = np.uint64(1)
    total0 = total1 = 0.0
    for a in range(_N_TAPS):
        start = corner + np.uint64(a) * row_stride
        wy = weights_y[a, col]
        total0 += wy * _tap_row(flat, start, tap_stride, wx0, wx1, wx2, wx3, wx4, wx5)
        total1 += wy * _tap_row(flat, start + one, tap_stride, wx0, wx1, wx2, wx3, wx4, wx5)
    return total0, total1


@numba.njit(cache=True, inline="always")
def _row_weights(
    x_src: np.ndarray, y_src: np.ndarray, row: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Axis weights, first taps and exact taps of output row ``row`` (see _axis_weights)."""
    n_cols = x_src.shape[1]
    weights_x = np.empty((_N_TAPS, n_cols))
    weights_y = np.empty((_N_TAPS, n_cols))
    first_x = np.empty(n_cols, dtype=np.uint64)
    first_y = np.empty(n_cols, dtype=np.uint64)
    exact_x = np.empty(n_cols, dtype=np.int64)
    exact_y = np.empty(n_cols, dtype=np.int64)
    _axis_weights(x_src[row], weights_x, first_x, exact_x)
    _axis_weights(y_src[row], weights_y, first_y, exact_y)
    return weights_x, weights_y, first_x, first_y, exact_x, exact_y


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
) -> None:
    """Accumulate ``weight * scale * warp(planes)`` into output row ``row`` of ``out``.

    ``flat_planes`` is the C-ordered ``(P, ny_in, nx_in)`` stack raveled; unsigned flat
    indices spare numba the negative-index wrap-around test on every tap.
    """
    n_planes = out.shape[0]
    ny_in, nx_in = plane_shape
    row_stride = np.uint64(nx_in)
    plane_stride = np.uint64(ny_in * nx_in)
    one = np.uint64(1)
    weights_x, weights_y, first_x, first_y, exact_x, exact_y = _row_weights(x_src, y_src, row)
    for col in range(x_src.shape[1]):
        factor = weight * scale[row, col] if use_scale else weight
        if exact_x[col] >= 0 and exact_y[col] >= 0:
            # Integral position: copy (bit for bit, and immune to non-finite neighbours).
            source = np.uint64(exact_y[col]) * row_stride + np.uint64(exact_x[col])
            for p in range(n_planes):
                out[p, row, col] += factor * flat_planes[np.uint64(p) * plane_stride + source]
            continue
        wx = (
            weights_x[0, col],
            weights_x[1, col],
            weights_x[2, col],
            weights_x[3, col],
            weights_x[4, col],
            weights_x[5, col],
        )
        corner = first_y[col] * row_stride + first_x[col]
        for p in range(n_planes):
            start = np.uint64(p) * plane_stride + corner
            total = _block_sum(flat_planes, start, row_stride, one, wx, weights_y, col)
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
    for row in range(x_src.shape[0]):
        _warp_row(flat_planes, plane_shape, x_src, y_src, out, weight, scale, use_scale, row)


@numba.njit(cache=True, parallel=True)
def _warp_parallel(
    flat_planes: np.ndarray,
    plane_shape: tuple[int, int],
    x_src: np.ndarray,
    y_src: np.ndarray,
    out: np.ndarray,
    weight: float,
    scale: np.ndarray,
    use_scale: bool,
) -> None:
    # Rows are independent, so results do not depend on the number of threads.
    for row in numba.prange(x_src.shape[0]):
        _warp_row(flat_planes, plane_shape, x_src, y_src, out, weight, scale, use_scale, row)


def _check_positions(
    x_src: np.ndarray, y_src: np.ndarray, input_shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Validate the output->input positions; return them as C-contiguous float64 arrays."""
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
        return np.ascontiguousarray(x_src), np.ascontiguousarray(y_src)
    if not (np.isfinite(x_src).all() and np.isfinite(y_src).all()):
        raise ValueError("x_src and y_src must be finite")
    ny_in, nx_in = input_shape
    for axis, values, size in (("x", x_src, nx_in), ("y", y_src, ny_in)):
        first_tap = int(np.floor(values.min())) - (KERNEL_HALF_WIDTH - 1)
        last_tap = int(np.floor(values.max())) + KERNEL_HALF_WIDTH
        if first_tap < 0 or last_tap > size - 1:
            raise ValueError(
                f"kernel taps along {axis} span input pixels [{first_tap}, {last_tap}] "
                f"but the input has pixels [0, {size - 1}]"
            )
    return np.ascontiguousarray(x_src), np.ascontiguousarray(y_src)


def warp_planes(
    planes: np.ndarray,
    x_src: np.ndarray,
    y_src: np.ndarray,
    out: np.ndarray | None = None,
    weight: float = 1.0,
    scale: np.ndarray | None = None,
    *,
    parallel: bool = False,
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
    parallel : bool
        Spread output rows over numba threads; results are identical either way.

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
    x_src, y_src = _check_positions(x_src, y_src, planes.shape[1:])
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
    kernel = _warp_parallel if parallel else _warp_serial
    flat_planes = np.ascontiguousarray(planes).reshape(-1)
    plane_shape = (int(planes.shape[1]), int(planes.shape[2]))
    kernel(flat_planes, plane_shape, x_src, y_src, out, weight, scale_array, use_scale)
    return out
