"""The smallest and largest values of two arrays of positions, in one pass over each.

:func:`~cellcoadd.builder.mapping.footprint_box` needs the extremes of an exposure
mapping's ``x`` and ``y`` (a block's mapping holds millions of pixels); numpy's ``min`` and
``max`` read each array twice.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def extremes_2d(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float, float]:
    """``(x.min(), x.max(), y.min(), y.max())`` of two 2-D float64 arrays (any strides).

    A NaN anywhere in an array makes both of its extremes NaN, as numpy's do; infinities
    are extremes like any value. The arrays must not be empty.
    """
    return _extremes(x) + _extremes(y)


@numba.njit(cache=True, inline="always")
def _extremes(values: np.ndarray) -> tuple[float, float]:
    low = high = values[0, 0]
    n_rows, n_cols = values.shape
    for row in range(n_rows):
        for col in range(n_cols):
            value = values[row, col]
            if value < low:
                low = value
            elif value > high:
                high = value
            elif value != value:  # NaN: numpy's min and max are NaN too
                return np.nan, np.nan
    if low != low:  # the first value was NaN
        return np.nan, np.nan
    return low, high
