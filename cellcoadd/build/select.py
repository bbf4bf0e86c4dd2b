"""Per-cell selection of input exposures (paper sections 2 and 6: edge-free coadds).

An exposure is used for a cell only if its valid pixels cover the whole cell outer box
plus the resampling kernel's reach, its masked fraction there is small, and its weight
(one scalar per exposure, from the background noise only) is finite and positive. Every
exposure considered gets an :class:`InputRecord` saying what happened to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcoadd.build.mapping import PixelMapping, footprint_box, map_box
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.tract import Cell
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.exposure import Exposure


@dataclass
class Candidate:
    """An exposure that passed selection for one cell, with what the warp needs."""

    exposure: Exposure
    mapping: PixelMapping
    footprint: Box
    flux_scale: float  # multiplies exposure counts into counts at the common zero point
    weight: float  # 1 / background variance at the common zero point
    bad: np.ndarray  # bool over footprint: pixels flagged with a bad mask bit
    overlap_fraction: float


def rough_exposure_box(cell: Cell, exposure: Exposure) -> Box | None:
    """Exposure pixels near the cell's outer box, from 9 exactly mapped points (None: far)."""
    ny, nx = cell.outer_bbox.shape
    gx, gy = np.meshgrid([0.0, (nx - 1) / 2, nx - 1.0], [0.0, (ny - 1) / 2, ny - 1.0])
    ra, dec = cell.wcs.all_pix2world(gx.ravel(), gy.ravel(), 0)
    try:
        ex, ey = exposure.wcs.all_world2pix(ra, dec, 0, quiet=True)
    except Exception:  # distortion solutions can fail far from the detector
        return None
    if not (np.all(np.isfinite(ex)) and np.all(np.isfinite(ey))):
        return None
    found = Box(
        x_start=int(np.floor(ex.min())) - 3,
        x_stop=int(np.floor(ex.max())) + 5,
        y_start=int(np.floor(ey.min())) - 3,
        y_stop=int(np.floor(ey.max())) + 5,
    )
    return found if found.overlaps(Box.from_shape(exposure.shape)) else None


def select_exposure(
    cell: Cell, exposure: Exposure, config: BuildConfig, bad_bits: int
) -> tuple[str, Candidate | dict]:
    """Decide whether ``exposure`` can be used for ``cell``.

    Returns ``("used", Candidate)`` or ``(reason, details)`` with ``details`` the record
    fields known so far (``overlap_fraction``, ``weight``).
    """
    if rough_exposure_box(cell, exposure) is None:
        return "no_overlap", {"overlap_fraction": 0.0}
    outer = Box.from_shape(cell.outer_bbox.shape)
    try:
        mapping = map_box(cell.wcs, outer, exposure.wcs, tolerance=config.mapping_tolerance)
    except Exception:
        return "no_overlap", {"overlap_fraction": 0.0}
    valid = exposure.valid_box
    inside = valid.contains(mapping.x, mapping.y)
    overlap_fraction = float(np.mean(inside))
    if overlap_fraction == 0.0:
        return "no_overlap", {"overlap_fraction": 0.0}
    footprint = footprint_box(mapping)
    if not valid.contains_box(footprint):
        return "edge", {"overlap_fraction": overlap_fraction}
    flux_scale = 10.0 ** (0.4 * (config.zero_point - exposure.zero_point))
    variance = flux_scale**2 * exposure.background_variance
    weight = 1.0 / variance if variance > 0.0 else float("nan")
    if not np.isfinite(weight) or weight <= 0.0:
        return "bad_weight", {"overlap_fraction": overlap_fraction}
    bad = (exposure.mask[footprint.slices] & bad_bits) != 0
    if bad.mean() > config.max_mask_fraction:
        return "masked_fraction", {"overlap_fraction": overlap_fraction, "weight": 0.0}
    if not np.all(np.isfinite(exposure.image[footprint.slices][~bad])):
        return "bad_pixels", {"overlap_fraction": overlap_fraction}
    if not np.isscalar(exposure.variance):
        variance = exposure.variance[footprint.slices][~bad]
        if not (np.all(np.isfinite(variance)) and np.all(variance > 0)):
            return "bad_weight", {"overlap_fraction": overlap_fraction}
    return "used", Candidate(
        exposure=exposure,
        mapping=mapping,
        footprint=footprint,
        flux_scale=flux_scale,
        weight=weight,
        bad=bad,
        overlap_fraction=overlap_fraction,
    )
