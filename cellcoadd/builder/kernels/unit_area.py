"""Snapping pixel-area ratios within a tolerance of 1 to exactly 1, in one pass.

WCS round trips leave ~1e-9 relative noise on an area ratio that is exactly 1 for equal
pixel scales (:mod:`cellcoadd.builder.mapping`); the mapping of a block of cells holds
millions of ratios, and numpy's ``a[np.abs(a - 1.0) < tolerance] = 1.0`` passes over them
four times with three temporaries.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def snap_unit_area(area_ratio: np.ndarray, tolerance: float) -> None:
    """Set, in place, every value ``v`` of the C-contiguous ``area_ratio`` with
    ``abs(v - 1.0) < tolerance`` to 1.0 (the same test in float64 as numpy's; NaN stays)."""
    flat = area_ratio.reshape(-1)
    for i in range(flat.size):
        if abs(flat[i] - 1.0) < tolerance:
            flat[i] = 1.0
