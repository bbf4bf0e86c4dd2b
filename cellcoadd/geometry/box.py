"""Half-open integer pixel boxes.

Conventions (used everywhere in cellcoadd):

* Pixel centres sit at integer coordinates; pixel ``i`` covers ``[i - 0.5, i + 0.5)``.
* A box covers pixels ``x_start <= i < x_stop`` (stop exclusive), so as a region of the
  continuous plane it is ``[x_start - 0.5, x_stop - 0.5)`` (same for y).
* Array shapes are ``(ny, nx)``; ``slices`` index a numpy array in absolute pixel
  coordinates ``[y, x]``.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from pydantic import BaseModel, ConfigDict, model_validator

from cellcoadd.errors import GeometryError


class Box(BaseModel):
    """A frozen, half-open integer pixel box.

    Parameters
    ----------
    x_start, x_stop : int
        First pixel and one past the last pixel along x (columns).
    y_start, y_stop : int
        First pixel and one past the last pixel along y (rows).

    Examples
    --------
    >>> box = Box(x_start=0, x_stop=150, y_start=0, y_stop=150)
    >>> box.shape
    (150, 150)
    >>> box.contains(149.49, 0.0), box.contains(149.5, 0.0)
    (True, False)
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    x_start: int
    x_stop: int
    y_start: int
    y_stop: int

    @model_validator(mode="after")
    def _check_order(self) -> Box:
        if self.x_stop < self.x_start or self.y_stop < self.y_start:
            raise GeometryError(
                f"box stops must not precede starts: x [{self.x_start}, {self.x_stop}), "
                f"y [{self.y_start}, {self.y_stop})"
            )
        return self

    @classmethod
    def from_shape(cls, shape: tuple[int, int], x_start: int = 0, y_start: int = 0) -> Box:
        """Box of array ``shape`` ``(ny, nx)`` whose first pixel is ``(x_start, y_start)``."""
        ny, nx = shape
        return cls(x_start=x_start, x_stop=x_start + nx, y_start=y_start, y_stop=y_start + ny)

    @property
    def nx(self) -> int:
        return self.x_stop - self.x_start

    @property
    def ny(self) -> int:
        return self.y_stop - self.y_start

    @property
    def shape(self) -> tuple[int, int]:
        """Array shape ``(ny, nx)``."""
        return (self.ny, self.nx)

    @property
    def is_empty(self) -> bool:
        return self.nx == 0 or self.ny == 0

    @property
    def slices(self) -> tuple[slice, slice]:
        """``(slice(y_start, y_stop), slice(x_start, x_stop))`` in absolute coordinates."""
        return (slice(self.y_start, self.y_stop), slice(self.x_start, self.x_stop))

    def slices_in(self, outer: Box) -> tuple[slice, slice]:
        """Slices of this box inside an array that covers ``outer`` (which must contain it)."""
        if not outer.contains_box(self):
            raise GeometryError(f"{self} is not inside {outer}", value=self, allowed=outer)
        return (
            slice(self.y_start - outer.y_start, self.y_stop - outer.y_start),
            slice(self.x_start - outer.x_start, self.x_stop - outer.x_start),
        )

    def contains(self, x: float | np.ndarray, y: float | np.ndarray) -> bool | np.ndarray:
        """Whether continuous position(s) ``(x, y)`` lie in the box's half-open area.

        ``x_start - 0.5 <= x < x_stop - 0.5`` and the same for y; accepts scalars or arrays.
        """
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        inside = (
            (x >= self.x_start - 0.5)
            & (x < self.x_stop - 0.5)
            & (y >= self.y_start - 0.5)
            & (y < self.y_stop - 0.5)
        )
        return bool(inside) if inside.ndim == 0 else inside

    def contains_box(self, other: Box) -> bool:
        """Whether every pixel of ``other`` is in this box (an empty box is contained)."""
        if other.is_empty:
            return True
        return (
            self.x_start <= other.x_start
            and other.x_stop <= self.x_stop
            and self.y_start <= other.y_start
            and other.y_stop <= self.y_stop
        )

    @classmethod
    def enclosing(cls, boxes: Iterable[Box]) -> Box:
        """The smallest box holding every one of ``boxes`` (at least one)."""
        boxes = list(boxes)
        if not boxes:
            raise GeometryError("no boxes to enclose")
        return cls(
            x_start=min(b.x_start for b in boxes),
            x_stop=max(b.x_stop for b in boxes),
            y_start=min(b.y_start for b in boxes),
            y_stop=max(b.y_stop for b in boxes),
        )

    def intersection(self, other: Box) -> Box:
        """The pixels in both boxes (an empty box when they do not overlap)."""
        x_start = max(self.x_start, other.x_start)
        y_start = max(self.y_start, other.y_start)
        x_stop = max(x_start, min(self.x_stop, other.x_stop))
        y_stop = max(y_start, min(self.y_stop, other.y_stop))
        return Box(x_start=x_start, x_stop=x_stop, y_start=y_start, y_stop=y_stop)

    def overlaps(self, other: Box) -> bool:
        return not self.intersection(other).is_empty

    def grow(self, n: int) -> Box:
        """Grow by ``n`` pixels on every side (shrink for negative ``n``)."""
        return Box(
            x_start=self.x_start - n,
            x_stop=self.x_stop + n,
            y_start=self.y_start - n,
            y_stop=self.y_stop + n,
        )

    def shifted(self, dx: int, dy: int) -> Box:
        """The same box moved by ``(dx, dy)`` pixels."""
        return Box(
            x_start=self.x_start + dx,
            x_stop=self.x_stop + dx,
            y_start=self.y_start + dy,
            y_stop=self.y_stop + dy,
        )

    def __repr__(self) -> str:
        return f"Box(x=[{self.x_start}, {self.x_stop}), y=[{self.y_start}, {self.y_stop}))"

    __str__ = __repr__
