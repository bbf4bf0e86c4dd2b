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
* The value at an output pixel depends only on its position, the input and the weights
  (the same arithmetic for every pixel and plane: see
  :mod:`cellcoadd.builder.kernels.block_sums`), so warping a large region and cutting a
  box out of it gives the bits of warping the box.

The weights of a run of output pixels are computed first
(:mod:`cellcoadd.builder.kernels.lanczos`), then applied to every plane. The kernel
(:func:`cellcoadd.builder.kernels.accumulate.resample_interleaved`) reads the planes
interleaved, ``(ny, nx, P)``: :func:`warp_planes` interleaves its planes (stored one after
the other, ``(P, ny, nx)``) over the taps' bounding box first, and gives the bits of
:func:`cellcoadd.builder.kernels.accumulate.accumulate_warped`.
:func:`cellcoadd.builder.kernels.mask_warp.warp_mask_or` spreads mask bits over the same
footprints.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from cellcoadd.builder.kernels.accumulate import resample_interleaved
from cellcoadd.builder.kernels.lanczos import (
    KERNEL_HALF_WIDTH,
    N_TAPS,
    check_positions,
    checked_positions_and_taps,
)
from cellcoadd.errors import CellCoaddValueError

__all__ = [
    "KERNEL_HALF_WIDTH",
    "check_positions",
    "checked_positions_and_taps",
    "warp_planes",
]


@numba.njit(cache=True)
def _interleave(planes: np.ndarray, x0: int, y0: int, pixels: np.ndarray) -> None:
    """``pixels[y, x, p] = planes[p, y0 + y, x0 + x]`` (float64) over ``pixels``' shape."""
    for y in range(pixels.shape[0]):
        row = pixels[y]
        for p in range(planes.shape[0]):
            source = planes[p, y0 + y]  # read along rows
            for x in range(row.shape[0]):
                row[x, p] = source[x0 + x]


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

    Notes
    -----
    Several planes (or one in float32) are copied, interleaved and as float64 (exact for
    float32), over the bounding box of the taps the positions reach.
    """
    planes = np.asarray(planes)
    if planes.ndim != 3:
        raise CellCoaddValueError(
            f"planes must be 3-D (P, ny_in, nx_in), got shape {planes.shape}", value=planes.shape
        )
    if planes.dtype not in (np.float32, np.float64):
        raise CellCoaddValueError(
            f"planes must be float32 or float64, got {planes.dtype}", value=planes.dtype
        )
    x_src, y_src, (x_lo, x_hi, y_lo, y_hi) = checked_positions_and_taps(
        x_src, y_src, planes.shape[1:]
    )
    n_planes = planes.shape[0]
    out_shape = (n_planes, *x_src.shape)
    if out is None:
        out = np.zeros(out_shape, dtype=np.float64)
    elif not isinstance(out, np.ndarray) or out.dtype != np.float64 or out.shape != out_shape:
        raise CellCoaddValueError(f"out must be a float64 array of shape {out_shape}")
    elif not out.flags.c_contiguous or not out.flags.writeable:
        raise CellCoaddValueError("out must be C-contiguous and writeable")
    weight = float(weight)
    if not math.isfinite(weight):
        raise CellCoaddValueError(f"weight must be finite, got {weight}", value=weight)
    if scale is None:
        scales = np.ones((1, 1, 1))
        which = np.full(n_planes, -1, dtype=np.int64)
    else:
        scale_array = np.ascontiguousarray(scale, dtype=np.float64)
        if scale_array.shape != x_src.shape:
            raise CellCoaddValueError(
                f"scale has shape {scale_array.shape}, expected {x_src.shape}",
                value=scale_array.shape,
            )
        scales = scale_array[np.newaxis]
        which = np.zeros(n_planes, dtype=np.int64)
    if x_src.size == 0 or n_planes == 0:
        return out
    if n_planes == 1 and planes.dtype == np.float64 and planes.flags.c_contiguous:
        # one plane is its own interleaved layout
        flat, width, origin = planes.reshape(-1), planes.shape[2], (0, 0)
    else:
        # every tap lies in [lo, hi + N_TAPS) along each axis
        pixels = np.empty((y_hi + N_TAPS - y_lo, x_hi + N_TAPS - x_lo, n_planes))
        _interleave(planes, x_lo, y_lo, pixels)
        flat, width, origin = pixels.reshape(-1), pixels.shape[1], (x_lo, y_lo)
    resample_interleaved(
        flat,
        width,
        origin,
        x_src,
        y_src,
        out,
        np.full(n_planes, weight),
        scales,
        which,
    )
    return out
