"""What Rubin's stitched cell coadds offer beside the pixels: a PSF at any position of the
patch and a mask plane marking the cells' edges.

Rubin's ``lsst.cell_coadds`` serves the PSF of a stitched patch cell by cell: at any
position, the PSF of the cell whose inner box holds it (``StitchedPsf``); its
``set_cell_edges`` flags the outermost pixels of every cell's inner box in a ``CELL_EDGE``
mask plane. :func:`psf_at` and :func:`cell_edge_mask` do the same for a
:class:`~cellcoadd.model.patch_coadd.PatchCoadd`.
"""

from __future__ import annotations

import math

import numpy as np

from cellcoadd.errors import CellCoaddIndexError, CellCoaddValueError, InvalidCoaddError
from cellcoadd.geometry.box import Box
from cellcoadd.model.patch_coadd import PatchCoadd

#: Name of the mask plane of :func:`cell_edge_mask` (Rubin's ``edge_mask_name`` default).
CELL_EDGE = "CELL_EDGE"


def cell_of_position(patch: PatchCoadd, x: float, y: float) -> tuple[int, int]:
    """Tract-global index of the cell of ``patch`` whose inner box holds tract pixel
    position ``(x, y)``; on the patch's outer border, beyond its outermost cells' inner
    boxes, the outermost cell (as Rubin's stitched coadds give those pixels from the edge
    cells' borders).

    Raises
    ------
    CellCoaddIndexError
        When ``(x, y)`` is not in the patch's outer box.
    """
    if not (math.isfinite(x) and math.isfinite(y)):
        raise CellCoaddValueError(f"position ({x}, {y}) is not finite", value=(x, y))
    meta = patch.metadata
    outer = meta.geometry.outer_bbox
    if not bool(outer.contains(x, y)):
        raise CellCoaddIndexError(
            f"tract pixel ({x}, {y}) is outside patch {meta.patch}'s outer box {outer}",
            value=(x, y),
        )
    side = meta.cell_inner
    cells = meta.all_cell_indices
    low = (min(c[0] for c in cells), min(c[1] for c in cells))
    high = (max(c[0] for c in cells), max(c[1] for c in cells))
    index = [math.floor((v + 0.5) / side) for v in (x, y)]
    return (
        min(max(index[0], low[0]), high[0]),
        min(max(index[1], low[1]), high[1]),
    )


def psf_at(patch: PatchCoadd, x: float, y: float) -> np.ndarray:
    """The coadd PSF of the stitched patch at tract pixel position ``(x, y)``.

    The cell of :func:`cell_of_position` gives it: interpolated to ``(x, y)`` by
    :meth:`CellCoadd.psf_at <cellcoadd.model.cell_coadd.CellCoadd.psf_at>` when the cell
    holds the planes it needs (``psf_corners`` or ``psf_phase``), otherwise the cell's
    PSF stamp (Rubin's ``StitchedPsf``: one PSF per cell). Unlike
    :meth:`PatchCoadd.psf_at <cellcoadd.model.patch_coadd.PatchCoadd.psf_at>` (pixels of
    the stitched inner-box arrays, cells with those planes only), it takes tract pixels
    anywhere in the patch's outer box, as Rubin's stitched coadds cover it, and serves
    every cell with data.

    Parameters
    ----------
    patch : PatchCoadd
        The patch.
    x, y : float
        Tract pixel position, pixels (pixel centres at integers), anywhere in the patch's
        outer box.

    Returns
    -------
    ndarray, float64
        A copy of the PSF image, ``psf_size`` square, centred on its central pixel.

    Raises
    ------
    CellCoaddIndexError
        Outside the patch's outer box.
    InvalidCoaddError
        When the cell there is missing or empty (no inputs, no PSF).
    """
    index = cell_of_position(patch, x, y)
    cell = patch.cells.get(index)
    if cell is None or cell.is_empty:
        what = "missing" if cell is None else "empty"
        raise InvalidCoaddError(
            f"no PSF at tract pixel ({x}, {y}): its cell {index} is {what}", value=index
        )
    local_x, local_y = x - cell.outer_bbox.x_start, y - cell.outer_bbox.y_start
    if (
        getattr(cell, "psf_corners", None) is not None
        or getattr(cell, "psf_phase", None) is not None
    ):
        inside = bool(cell.inner_bbox.contains(x, y))
        return np.array(cell.psf_at(local_x, local_y, extrapolate=not inside), dtype=np.float64)
    return np.array(cell.psf, dtype=np.float64)


def cell_edge_mask(patch: PatchCoadd, bbox: Box | None = None, width: int = 1) -> np.ndarray:
    """Boolean image of ``bbox`` (tract pixels; default the patch's inner box, the area of
    :meth:`PatchCoadd.stitch`): True on the ``width`` outermost pixels of every cell's
    inner box, as Rubin's ``set_cell_edges`` flags them in ``CELL_EDGE``."""
    if isinstance(width, bool) or not isinstance(width, int) or width < 1:
        raise CellCoaddValueError(f"width must be a positive integer, got {width!r}", value=width)
    meta = patch.metadata
    box = meta.patch_inner_bbox if bbox is None else bbox
    side = meta.cell_inner
    if 2 * width > side:
        raise CellCoaddValueError(
            f"width {width} covers more than the {side}-px cells",
            value=width,
            allowed=(1, side // 2),
        )

    def edges(start: int, stop: int) -> np.ndarray:
        offset = np.mod(np.arange(start, stop), side)
        return (offset < width) | (offset >= side - width)

    return (
        edges(box.y_start, box.y_stop)[:, np.newaxis]
        | edges(box.x_start, box.x_stop)[np.newaxis, :]
    )
