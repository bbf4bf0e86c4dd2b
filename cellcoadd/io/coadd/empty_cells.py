"""Cells without data stored without pixels (format 1.6).

A cell no input covers holds what :meth:`~cellcoadd.model.cell_coadd.CellCoadd.empty`
gives it: NaN in every float plane (the one NaN bit pattern numpy writes, ``0x7FC00000``
in float32), ``NO_DATA`` in every mask pixel. Both layouts store such a plane as a marker
instead of its pixels, and readers make it again bit for bit from the cell's geometry:

* FITS: an image HDU without data (``NAXIS = 0``, ``BITPIX = 16``) with ``CCEMPTY = T``;
* HDF5: a dataset of shape ``(0,)`` with the attribute ``empty = "no data"``.

Only an empty cell's planes that hold exactly these values are stored so (anything else,
e.g. a foreign file's empty cell with other fill values, is stored pixel for pixel), and a
reader accepts the marker only in a cell without used inputs. A plane with one layer per
used input has no layer in an empty cell: FITS stores it with the same marker (files
before 1.6 store one zero layer), HDF5 as its zero-size shape.
"""

from __future__ import annotations

import numpy as np

from cellcoadd.model import planes as cell_planes
from cellcoadd.model.cell_coadd import CellCoadd

#: FITS keyword and HDF5 attribute marking a plane stored without pixels.
EMPTY_KEY = "CCEMPTY"
EMPTY_ATTRIBUTE = "empty"
EMPTY_VALUE = "no data"


def empty_plane(spec: cell_planes.PlaneSpec, shape: tuple[int, ...], no_data: int) -> np.ndarray:
    """The plane ``spec`` of an empty cell, of ``shape``: NaN floats, or ``no_data`` (the
    ``NO_DATA`` bit's value) in an integer mask."""
    if spec.dtype.kind == "f":
        return np.full(shape, np.nan, dtype=spec.dtype)
    return np.full(shape, no_data, dtype=spec.dtype)


def planes_without_pixels(cell: CellCoadd, no_data: int) -> frozenset[str]:
    """The planes of ``cell`` stored without pixels: none unless the cell is empty; then
    its per-input planes (no layer) and every other plane holding exactly
    :func:`empty_plane`'s bits."""
    if not cell.is_empty:
        return frozenset()
    names = []
    for spec in cell_planes.PLANES:
        data = getattr(cell, spec.name)
        if data is None:
            continue
        if spec.per_input:
            names.append(spec.name)
        elif data.size and _same_bits(data, empty_plane(spec, (), no_data)):
            names.append(spec.name)
    return frozenset(names)


def _same_bits(data: np.ndarray, fill: np.ndarray) -> bool:
    """Whether every element of ``data`` has the bits of the scalar ``fill``."""
    if data.dtype != fill.dtype:
        return False
    unsigned = np.dtype(f"u{data.dtype.itemsize}")
    return bool(np.all(data.view(unsigned) == fill.view(unsigned)))
