"""Per-cell selection of input exposures (paper sections 2 and 6: edge-free coadds).

An exposure is used for a cell only if its valid pixels cover the whole cell outer box
plus the resampling kernel's reach, its masked fraction there is small, and its weight
(one scalar per exposure, from the background noise only) is finite and positive. Every
exposure considered gets an :class:`InputRecord` saying what happened to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from astropy.wcs.wcs import NoConvergence

from cellcoadd.builder.mapping import PixelMapping, footprint_box, map_box
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.tract import Cell
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.inputs import InputStatus

# Range of scaled background variances the float32 coadd planes can represent.
_FLOAT32_TINY = float(np.finfo(np.float32).tiny)
_FLOAT32_MAX = float(np.finfo(np.float32).max)
#: Largest scaled input value (and, squared, variance) accepted: room for the Lanczos-3
#: kernel's negative lobes (sum of |weights| < 2 in 2-D), the pixel-area ratio and the
#: noise realizations' Gaussian tails, so that every warped contribution stays finite in
#: the float32 coadd planes.
_LARGEST_INPUT = _FLOAT32_MAX / 1024.0


# What evaluating a WCS far from its detector may raise (astropy's WCS errors are
# ValueErrors; the iterative SIP inverse raises NoConvergence; MappingError is a
# ValueError): anything else is a bug and propagates.
WCS_ERRORS = (ValueError, ArithmeticError, NoConvergence)


@dataclass(frozen=True)
class Rejection:
    """An exposure rejected for one cell: the reason and the record fields known so far."""

    status: InputStatus
    overlap_fraction: float = 0.0


@dataclass(frozen=True, eq=False)
class Candidate:
    """An exposure that passed selection for one cell, with what the warp needs."""

    exposure: Exposure
    mapping: PixelMapping
    footprint: Box
    flux_scale: float  # multiplies exposure counts into counts at the common zero point
    weight: float  # 1 / background variance at the common zero point
    bad: np.ndarray  # bool over footprint: pixels flagged with a bad mask bit
    overlap_fraction: float


def select_exposure(
    cell: Cell,
    exposure: Exposure,
    config: BuildConfig,
    bad_bits: int,
    *,
    grid_cache: dict | None = None,
    mapping: PixelMapping | None = None,
) -> Candidate | Rejection:
    """Decide whether ``exposure`` can be used for ``cell``.

    Returns a :class:`Candidate` (used) or a :class:`Rejection` with the reason and the
    overlap fraction when known. ``grid_cache``: a dict shared by the calls for one cell,
    reusing its mapping grids (see :func:`map_box`). Far exposures are best left out
    first with the cheap
    :func:`~cellcoadd.builder.exposure_frame.rough_exposure_box`, as
    :func:`cellcoadd.builder.cell.build_cell` does; here
    they end as ``no_overlap`` too, after the mapping. ``mapping``: the cell's pixels
    already mapped into ``exposure`` (e.g. a part of an exposure's mapping over a whole
    patch, see :mod:`cellcoadd.builder.exposure_frame`); by default they are mapped here.
    """
    if mapping is None:
        try:
            mapping = map_box(
                cell.wcs,
                Box.from_shape(cell.outer_bbox.shape),
                exposure.wcs,
                tolerance=config.mapping_tolerance,
                grid_cache=grid_cache,
            )
        except WCS_ERRORS:
            return Rejection(InputStatus.NO_OVERLAP)
    valid = exposure.valid_box
    assert valid is not None  # Exposure.__post_init__ fills it
    footprint = footprint_box(mapping) if mapping.is_complete else None
    if footprint is None or not valid.contains_box(footprint):
        overlap_fraction = float(np.mean(valid.contains(mapping.x, mapping.y)))
        if overlap_fraction == 0.0:
            return Rejection(InputStatus.NO_OVERLAP)
        # part of the cell (or the kernel's reach) falls off the valid box or the
        # exposure's projection: it cannot cover the cell
        return Rejection(InputStatus.EDGE, overlap_fraction)
    overlap_fraction = 1.0  # every pixel centre is inside the footprint, hence the box
    flux_scale = 10.0 ** (0.4 * (config.zero_point - exposure.zero_point))
    variance = flux_scale**2 * exposure.background_variance
    weight = 1.0 / variance if variance > 0.0 else float("nan")
    if not np.isfinite(weight) or weight <= 0.0:
        return Rejection(InputStatus.BAD_WEIGHT, overlap_fraction)
    if not _FLOAT32_TINY < variance < _FLOAT32_MAX:
        # the coadd stores float32 planes: this input's scaled noise would under/overflow
        return Rejection(InputStatus.BAD_WEIGHT, overlap_fraction)
    assert exposure.mask is not None  # Exposure.__post_init__ fills it
    bad = (exposure.mask[footprint.slices] & bad_bits) != 0
    if bad.mean() > config.max_mask_fraction:
        return Rejection(InputStatus.MASKED_FRACTION, overlap_fraction)
    pixels = exposure.image[footprint.slices]
    pixels = pixels[~bad] if bad.any() else pixels
    # NaN and infinities propagate to the extremes
    peak = max(float(pixels.max()), -float(pixels.min())) if pixels.size else 0.0
    if not np.isfinite(peak):
        return Rejection(InputStatus.BAD_PIXELS, overlap_fraction)
    area = float(np.max(mapping.area_ratio))
    if peak * flux_scale * area > _LARGEST_INPUT:
        # finite, but its warped value would overflow the float32 coadd
        return Rejection(InputStatus.BAD_PIXELS, overlap_fraction)
    if isinstance(exposure.variance, np.ndarray):  # else a float
        variance = exposure.variance[footprint.slices]
        variance = variance[~bad] if bad.any() else variance
        if not (np.all(np.isfinite(variance)) and np.all(variance > 0)):
            return Rejection(InputStatus.BAD_WEIGHT, overlap_fraction)
        if variance.size and float(np.max(variance)) * (flux_scale * area) ** 2 > _LARGEST_INPUT:
            # also the per-pixel variance of noise realizations with noise_variance="pixel"
            return Rejection(InputStatus.BAD_PIXELS, overlap_fraction)
    return Candidate(
        exposure=exposure,
        mapping=mapping,
        footprint=footprint,
        flux_scale=flux_scale,
        weight=weight,
        bad=bad,
        overlap_fraction=overlap_fraction,
    )
