"""What the rest of the builder needs to know of the resampling kernel: its name and reach.

The taps of an output pixel mapped to input position ``x`` are the input pixels
``floor(x) + first_offset .. floor(x) + last_offset``, ``taps`` of them per axis
(Lanczos-3: ``floor(x) - 2 .. floor(x) + 3``, six). Footprints, selection margins, the
loading margin of exposure sources and the numba kernels read these numbers from
:data:`WARP_KERNEL` rather than repeating them. The weights themselves are in
:mod:`cellcoadd.builder.kernels.lanczos`.

Conventions: 0-based pixel coordinates with pixel centres at integers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class KernelDescriptor:
    """A separable interpolation kernel of finite support.

    Attributes
    ----------
    name : str
        Its name, e.g. ``"lanczos3"``.
    half_width : int
        Pixels its support reaches on each side of a position: ``a`` of Lanczos-``a``
        (positive).
    """

    name: str
    half_width: int

    @property
    def taps(self) -> int:
        """Input pixels weighed per axis: ``2 * half_width``."""
        return 2 * self.half_width

    @property
    def first_offset(self) -> int:
        """The first tap of position ``x`` is ``floor(x) + first_offset`` (``1 - half_width``)."""
        return 1 - self.half_width

    @property
    def last_offset(self) -> int:
        """The last tap of position ``x`` is ``floor(x) + last_offset`` (``half_width``)."""
        return self.half_width

    def tap_range(self, low: float, high: float) -> tuple[int, int]:
        """Half-open range ``[start, stop)`` of the taps of every position in ``[low, high]``
        (finite), along one axis."""
        return math.floor(low) + self.first_offset, math.floor(high) + self.last_offset + 1


LANCZOS3 = KernelDescriptor("lanczos3", 3)
"""The Lanczos-3 kernel: ``sinc(t) sinc(t / 3)`` for ``|t| < 3``, six taps per axis."""

WARP_KERNEL = LANCZOS3
"""The kernel the builder warps images, noise, masks and PSFs with."""

__all__ = ["LANCZOS3", "WARP_KERNEL", "KernelDescriptor"]
