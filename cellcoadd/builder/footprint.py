"""The exposure pixels a resampling kernel reads for a set of mapped coadd pixels.

Conventions: 0-based pixel coordinates with pixel centres at integers, half-open boxes
(see :mod:`cellcoadd.geometry.box`).
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from cellcoadd.builder.kernels.warp import KERNEL_HALF_WIDTH
from cellcoadd.errors import MappingError
from cellcoadd.geometry.box import Box


class PixelPositions(Protocol):
    """Exposure pixel positions ``x`` and ``y`` of some coadd pixels: a
    :class:`~cellcoadd.builder.mapping.PixelMapping` or a subset of its pixels."""

    @property
    def x(self) -> np.ndarray: ...

    @property
    def y(self) -> np.ndarray: ...


def footprint_box(mapping: PixelPositions, half_width: int = KERNEL_HALF_WIDTH) -> Box:
    """Exposure pixels touched by the resampling kernel taps of all mapped pixels.

    Taps run from ``floor(x) - (half_width - 1)`` to ``floor(x) + half_width`` (Lanczos-3:
    ``floor(x) - 2 .. floor(x) + 3``), so the box is
    ``[min floor(x) - half_width + 1, max floor(x) + half_width + 1)`` and likewise in y.
    An exposure can be resampled without edge effects iff its valid box contains this.

    Parameters
    ----------
    mapping : PixelMapping
        Or any object with exposure pixel coordinate arrays ``x`` and ``y`` (e.g. a
        subset of a mapping's pixels).
    half_width : int
        Kernel half-width in pixels.

    Raises
    ------
    MappingError
        If there are no pixels or some do not map into the exposure (non-finite).
    """
    x = np.asarray(mapping.x, dtype=np.float64)
    y = np.asarray(mapping.y, dtype=np.float64)
    if x.size == 0:
        raise MappingError("an empty mapping has no footprint")
    # floor is monotonic: the floor of the extremes is the extreme of the floors; a NaN
    # propagates to the extremes, an infinity stays one
    x_min, x_max, y_min, y_max = x.min(), x.max(), y.min(), y.max()
    if not np.isfinite([x_min, x_max, y_min, y_max]).all():
        raise MappingError("some pixels do not map into the exposure")
    return Box(
        x_start=math.floor(x_min) - (half_width - 1),
        x_stop=math.floor(x_max) + half_width + 1,
        y_start=math.floor(y_min) - (half_width - 1),
        y_stop=math.floor(y_max) + half_width + 1,
    )
