"""Where one exposure lands on the tract's pixel grid, mapped once for a whole area.

All cells of a tract share its pixel grid, so the position in an exposure of a tract pixel
does not depend on the cell that pixel is seen from. :func:`exposure_frame` projects the
exposure's valid box into tract pixels once, and maps the part of an area (a patch) it
may serve onto the exposure with one verified interpolation grid
(:func:`~cellcoadd.builder.mapping.grid_mapping`). Every cell then takes its pixels from
that one mapping (:meth:`~cellcoadd.builder.mapping.PixelMapping.restricted`), so
overlapping cells see the same positions bit for bit, whichever process builds them, and
no WCS is evaluated per cell.

Whether an exposure is near a cell is decided here, once: near when the cell's outer box
overlaps the frame's region (:meth:`ExposureFrame.may_serve`; a patch build sends a block
only the exposures near one of its cells, and a block asks again per cell). A cell near
an exposure without a shared mapping then maps itself if
:func:`rough_exposure_box` finds it near too.

Conventions: 0-based tract pixels with centres at integers, half-open boxes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from astropy.wcs import WCS

from cellcoadd.builder.kernels.descriptor import WARP_KERNEL
from cellcoadd.builder.mapping import PixelMapping, grid_mapping
from cellcoadd.builder.select import WCS_ERRORS
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.tract import Cell
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.sources import ExposureHeader

#: Points sampled along each side of the valid box when it is projected into the tract.
_POINTS_PER_SIDE = 33
#: Tract pixels added around the projected valid box: the bulge of a distorted edge
#: between samples is far below this.
_REGION_MARGIN = 4

_EMPTY = Box(x_start=0, x_stop=0, y_start=0, y_stop=0)

#: Exposure pixels by which the kernel's footprint of the nine exactly mapped points of a
#: cell's outer box is grown to decide whether an exposure is near the cell
#: (:func:`rough_exposure_box`), for the mapping between the points, which they do not
#: sample.
NEAR_TOLERANCE = 1


@dataclass(frozen=True, eq=False)
class ExposureFrame:
    """One exposure's place on the tract grid within an area.

    Attributes
    ----------
    region : Box
        Tract pixels of the area that may map into the exposure's valid box (empty: the
        exposure serves none of the area).
    mapping : PixelMapping or None
        Exposure pixel positions (in the header's frame) of the pixels of ``region``,
        deferred: a part is interpolated only when asked for. None when no verified grid
        covers the region (part of it off the exposure's projection); cells then map
        themselves, one at a time.
    """

    region: Box
    mapping: PixelMapping | None

    @property
    def serves_nothing(self) -> bool:
        """Whether no pixel of the area can map into the exposure."""
        return self.region.is_empty

    def may_serve(self, box: Box) -> bool:
        """Whether some pixel of ``box`` (tract pixels) may map into the exposure's valid
        box: the exposure is near ``box``. False means it certainly serves none of it."""
        return not self.serves_nothing and box.overlaps(self.region)

    def covers(self, box: Box) -> bool:
        """Whether ``box`` (tract pixels) lies inside the shared mapping."""
        return self.mapping is not None and self.region.contains_box(box)


def projected_valid_box(tract_wcs: WCS, exposure: Exposure | ExposureHeader) -> Box | None:
    """Tract pixels around the exposure's valid box, from points along its edges.

    Returns None when some edge point has no tract position (a WCS failure): the caller
    then maps cell by cell; an empty box when none has (the exposure is on the far side
    of the sky from the tract).
    """
    valid = exposure.valid_box
    assert valid is not None  # both Exposure and ExposureHeader fill it
    # pixel edges of the valid box: centres at integers, so edges at -0.5 offsets
    xs = np.linspace(valid.x_start - 0.5, valid.x_stop - 0.5, _POINTS_PER_SIDE)
    ys = np.linspace(valid.y_start - 0.5, valid.y_stop - 0.5, _POINTS_PER_SIDE)
    x = np.concatenate([xs, xs, np.full_like(ys, xs[0]), np.full_like(ys, xs[-1])])
    y = np.concatenate([np.full_like(xs, ys[0]), np.full_like(xs, ys[-1]), ys, ys])
    try:
        ra, dec = exposure.wcs.all_pix2world(x, y, 0)
        tx, ty = tract_wcs.all_world2pix(ra, dec, 0)
    except WCS_ERRORS:
        return None
    finite = np.isfinite(tx) & np.isfinite(ty)
    if not finite.any():
        return _EMPTY
    if not finite.all():
        return None
    return Box(
        x_start=int(np.floor(tx.min())) - _REGION_MARGIN,
        x_stop=int(np.ceil(tx.max())) + _REGION_MARGIN + 1,
        y_start=int(np.floor(ty.min())) - _REGION_MARGIN,
        y_stop=int(np.ceil(ty.max())) + _REGION_MARGIN + 1,
    )


def _rough_points(cell: Cell) -> tuple[np.ndarray, np.ndarray]:
    """Corners, edge midpoints and centre of the cell's outer box (cell pixels)."""
    ny, nx = cell.outer_bbox.shape
    gx, gy = np.meshgrid([0.0, (nx - 1) / 2, nx - 1.0], [0.0, (ny - 1) / 2, ny - 1.0])
    return gx.ravel(), gy.ravel()


def rough_exposure_box(cell: Cell, exposure: Exposure | ExposureHeader) -> Box | None:
    """Exposure pixels near the cell's outer box, from 9 exactly mapped points (None: far).

    The kernel's footprint of the points, grown by :data:`NEAR_TOLERANCE`: the decision
    whether an exposure is near a cell that has no shared mapping of it. Near exposures
    are then selected on the cell's full mapping (:func:`select_exposure`).
    """
    ra, dec = cell.wcs.all_pix2world(*_rough_points(cell), 0)
    try:
        ex, ey = exposure.wcs.all_world2pix(ra, dec, 0, quiet=True)
    except WCS_ERRORS:  # distortion solutions can fail far from the detector
        return None
    if not (np.all(np.isfinite(ex)) and np.all(np.isfinite(ey))):
        return None
    x_start, x_stop = WARP_KERNEL.tap_range(ex.min(), ex.max())
    y_start, y_stop = WARP_KERNEL.tap_range(ey.min(), ey.max())
    found = Box(x_start=x_start, x_stop=x_stop, y_start=y_start, y_stop=y_stop)
    found = found.grow(NEAR_TOLERANCE)
    return found if found.overlaps(Box.from_shape(exposure.shape)) else None


def exposure_frame(
    tract_wcs: WCS,
    area: Box,
    exposure: Exposure | ExposureHeader,
    tolerance: float,
    grid_cache: dict | None = None,
) -> ExposureFrame:
    """Map the part of ``area`` (tract pixels) that ``exposure`` may serve, once.

    Parameters
    ----------
    tract_wcs : astropy.wcs.WCS
        The tract's WCS (0-based tract pixels).
    area : Box
        Tract pixels to be built (e.g. the union of a patch's cell outer boxes). The
        mapping depends on ``area`` and the exposure only: every cell of the area gets
        the same positions from it.
    exposure : Exposure or ExposureHeader
        Its WCS and valid box are used.
    tolerance : float
        Position tolerance of the mapping, exposure px (``BuildConfig.mapping_tolerance``).
    grid_cache : dict, optional
        Interpolation grids shared by the frames of several exposures (see
        :func:`~cellcoadd.builder.mapping.map_box`): exposures covering the same part of
        the area then hold one copy of the per-pixel interpolation weights between them.
    """
    projected = projected_valid_box(tract_wcs, exposure)
    if projected is None:
        return ExposureFrame(area, None)
    if not projected.overlaps(area):
        return ExposureFrame(_EMPTY, None)
    region = projected.intersection(area)
    try:
        mapping = grid_mapping(tract_wcs, region, exposure.wcs, tolerance, grid_cache=grid_cache)
    except WCS_ERRORS:
        mapping = None
    return ExposureFrame(region, mapping)


__all__ = [
    "NEAR_TOLERANCE",
    "ExposureFrame",
    "exposure_frame",
    "projected_valid_box",
    "rough_exposure_box",
]
