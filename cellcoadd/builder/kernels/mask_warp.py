"""Spreading mask bits through the resampling: the OR over each output pixel's footprint.

The companion of :mod:`cellcoadd.builder.kernels.warp`: an output pixel carries every bit set in
the 6 x 6 input pixels its Lanczos-3 taps reach (``floor(x) - 2 .. floor(x) + 3``),
whatever the kernel weights there.
"""

from __future__ import annotations

import numba
import numpy as np

from cellcoadd.builder.kernels.descriptor import WARP_KERNEL
from cellcoadd.builder.kernels.warp import checked_positions_and_taps
from cellcoadd.errors import CellCoaddValueError

_TAPS = WARP_KERNEL.taps
_FIRST_OFFSET = WARP_KERNEL.first_offset


@numba.njit(cache=True)
def _window_or(mask: np.ndarray, x_first: int, y_first: int, nx: int, ny: int) -> np.ndarray:
    """``result[j, i]``: OR of ``mask`` over the 6x6 block whose first pixel is
    ``(x_first + i, y_first + j)``; separable, as OR is associative. The inner loops run
    along rows, so they vectorise."""
    rows = np.zeros((ny + _TAPS - 1, nx), dtype=np.int32)
    for j in range(ny + _TAPS - 1):
        source = mask[y_first + j, x_first : x_first + nx + _TAPS - 1]
        target = rows[j]
        for b in range(_TAPS):
            for i in range(nx):
                target[i] |= source[i + b]
    blocks = np.zeros((ny, nx), dtype=np.int32)
    for j in range(ny):
        target = blocks[j]
        for a in range(_TAPS):
            source = rows[j + a]
            for i in range(nx):
                target[i] |= source[i]
    return blocks


@numba.njit(cache=True)
def _mask_or(
    mask: np.ndarray,
    x_src: np.ndarray,
    y_src: np.ndarray,
    first_taps: tuple[int, int, int, int],
    out: np.ndarray,
) -> None:
    x_lo, x_hi, y_lo, y_hi = first_taps
    blocks = _window_or(mask, x_lo, y_lo, x_hi - x_lo + 1, y_hi - y_lo + 1)
    # Validated positions have their first tap >= 0, hence are >= 0: truncation is floor.
    for row in range(x_src.shape[0]):
        for col in range(x_src.shape[1]):
            i = np.uint64(np.int64(x_src[row, col]) + _FIRST_OFFSET - x_lo)
            j = np.uint64(np.int64(y_src[row, col]) + _FIRST_OFFSET - y_lo)
            out[row, col] = blocks[j, i]


def warp_mask_or(mask: np.ndarray, x_src: np.ndarray, y_src: np.ndarray) -> np.ndarray:
    """OR of the input mask bits over each output pixel's 6x6 kernel footprint.

    Parameters
    ----------
    mask : ndarray, shape (ny_in, nx_in), int32
        Input bit mask.
    x_src, y_src : ndarray, shape (ny_out, nx_out), float64
        Output pixel centres in input pixel coordinates, as for :func:`warp_planes`.

    Returns
    -------
    ndarray, shape (ny_out, nx_out), int32
        Bits set anywhere in input pixels ``floor(x) - 2 .. floor(x) + 3`` (and in y),
        regardless of the kernel weights there.
    """
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype != np.int32:
        raise CellCoaddValueError(
            f"mask must be a 2-D int32 array, got {mask.dtype} {mask.shape}",
            value=(mask.dtype, mask.shape),
        )
    x_src, y_src, first_taps = checked_positions_and_taps(x_src, y_src, mask.shape)
    out = np.zeros(x_src.shape, dtype=np.int32)
    # Most exposures have no flagged pixel near a cell: nothing to spread then.
    if x_src.size and mask.any():
        _mask_or(np.ascontiguousarray(mask), x_src, y_src, first_taps, out)
    return out
