"""Coadding one cell: select, warp, accumulate, draw the PSF, finish (DESIGN "Building").

The coadd is a weighted mean with one scalar weight per exposure (inverse background
variance at the common zero point), so it is linear and independent of the signal and
has a well-defined PSF (paper section 2). Image, noise realizations and masked fraction
go through the same normalised Lanczos-3 weights; the PSF goes through the same mapping.
Inputs are accumulated one at a time, so memory does not grow with their number.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from cellcoadd.builder.exposure_planes import exposure_planes, translated_mask
from cellcoadd.builder.kernels.accumulate import accumulate_warped
from cellcoadd.builder.kernels.mask_interpolation import DEFAULT_MAX_RADIUS
from cellcoadd.builder.kernels.mask_warp import warp_mask_or
from cellcoadd.builder.kernels.warp import warp_planes
from cellcoadd.builder.mapping import footprint_box
from cellcoadd.builder.psf import PsfError, draw_exposure_psf, psf_moments
from cellcoadd.builder.select import Candidate, Rejection, rough_exposure_box, select_exposure
from cellcoadd.errors import InputError
from cellcoadd.geometry.tract import Cell
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.inputs import InputRecord, InputStatus
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.sources import (
    DescribedSource,
    ExposureHeader,
    ExposureSource,
    describe,
    header_of,
)


class _Sums:
    """Running weighted sums of one cell's planes (float64 for exact accumulation).

    One array holds them all, in the order of
    :func:`~cellcoadd.builder.kernels.input_planes.input_planes` (image, K noise realizations,
    variance, masked fraction), so one kernel call adds an exposure.
    """

    def __init__(self, shape: tuple[int, int], n_noise: int, psf_size: int) -> None:
        self.planes = np.zeros((n_noise + 3, *shape))
        self.image = self.planes[0]
        self.noise = self.planes[1 : 1 + n_noise]
        self.variance = self.planes[1 + n_noise]
        self.mfrac = self.planes[2 + n_noise]
        self.psf = np.zeros((psf_size, psf_size))
        self.mask = np.zeros(shape, dtype=np.int32)
        self.weight = 0.0


def _add_exposure(
    sums: _Sums,
    candidate: Candidate,
    pixels: np.ndarray,
    mask: np.ndarray,
    psf_stamp: np.ndarray,
    n_noise: int,
) -> None:
    """Warp ``pixels`` (from :func:`exposure_planes`) and ``mask`` (coadd bit numbering)
    of one exposure into the cell's running sums."""
    box, mapping = candidate.footprint, candidate.mapping
    # without bad pixels the masked-fraction plane would be all zeros: it is left out
    with_mfrac = pixels.shape[2] == n_noise + 3
    x_local = mapping.x - box.x_start
    y_local = mapping.y - box.y_start
    weight, area = candidate.weight, mapping.area_ratio
    # image and noise: weight * area; variance: weight^2 * area^2 (the variance of a warped
    # pixel is approximated by the warped variance; the noise realizations carry the exact
    # correlated noise); masked fraction: weight
    plane_weights = [weight] * (1 + n_noise) + [weight**2] + [weight] * with_mfrac
    plane_scales = [0] * (1 + n_noise) + [1] + [-1] * with_mfrac
    accumulate_warped(
        pixels,
        x_local,
        y_local,
        sums.planes[: pixels.shape[2]],
        plane_weights,
        np.stack([area, area**2]),
        plane_scales,
    )
    sums.mask |= warp_mask_or(mask, x_local, y_local)
    sums.psf += weight * psf_stamp
    sums.weight += weight


def _coadd_psf_contribution(cell: Cell, candidate: Candidate, psf_size: int) -> np.ndarray:
    """The exposure PSF at the cell centre, warped like the image into the PSF stamp.

    The stamp is centred on the cell-centre pixel; its pixels map to the exposure through
    the same mapping as the image pixels, so the PSF has the image's sub-pixel phase.
    """
    mapping = candidate.mapping
    ny, nx = cell.outer_bbox.shape
    half = psf_size // 2
    rows = slice(ny // 2 - half, ny // 2 + half + 1)
    cols = slice(nx // 2 - half, nx // 2 + half + 1)
    x, y = mapping.x[rows, cols], mapping.y[rows, cols]
    x_center, y_center = float(mapping.x[ny // 2, nx // 2]), float(mapping.y[ny // 2, nx // 2])
    box = footprint_box(_SubMapping(x, y))
    stamp = draw_exposure_psf(candidate.exposure, x_center, y_center, box)
    warped = warp_planes(stamp[None], x - box.x_start, y - box.y_start)[0]
    return warped * mapping.area_ratio[rows, cols]


class _SubMapping:
    """Minimal stand-in exposing ``x`` and ``y`` for :func:`footprint_box`."""

    def __init__(self, x: np.ndarray, y: np.ndarray) -> None:
        self.x, self.y = x, y


def _record(
    exposure: Exposure | ExposureHeader, status: InputStatus, **fields: float
) -> InputRecord:
    return InputRecord(
        visit=exposure.visit,
        detector=exposure.detector,
        band=exposure.band,
        zero_point=exposure.zero_point,
        status=status,
        weight=fields.pop("weight", 0.0),
        overlap_fraction=fields.pop("overlap_fraction", 0.0),
        psf_fwhm=fields.pop("psf_fwhm", float("nan")),
        psf_e1=fields.pop("psf_e1", float("nan")),
        psf_e2=fields.pop("psf_e2", float("nan")),
        psf_T=fields.pop("psf_T", float("nan")),
    )


def check_mask_bits(exposures: Sequence[Exposure | ExposureHeader], config: BuildConfig) -> None:
    """Refuse exposures that do not define every required bad-mask bit by name.

    Raises
    ------
    InputError
        Naming the exposure and the missing bits (list them in
        ``BuildConfig.optional_mask_bits`` if the exposure really has no such pixels).
    """
    required = config.required_mask_bits()
    for exposure in exposures:
        missing = [name for name in required if name not in exposure.mask_bits.bits]
        if missing:
            raise InputError(
                f"exposure (visit={exposure.visit}, detector={exposure.detector}) does not "
                f"define the mask bits {missing} named in bad_mask_bits (it defines "
                f"{sorted(exposure.mask_bits.bits)}); map its bit names, or list them in "
                "BuildConfig.optional_mask_bits"
            )


def check_unique_inputs(exposures: Sequence[Exposure | ExposureHeader]) -> None:
    """Refuse duplicate ``(visit, detector)`` pairs (they would be coadded twice)."""
    seen: set[tuple[int, int]] = set()
    for exposure in exposures:
        if exposure.key in seen:
            raise ValueError(f"duplicate input (visit, detector) = {exposure.key}")
        seen.add(exposure.key)


Input = Exposure | ExposureSource | DescribedSource

#: Pixels loaded around a cell's footprint from an exposure source: the interpolation
#: of bad pixels reads this far, plus the kernel's reach and a margin for the rough box.
SOURCE_MARGIN = DEFAULT_MAX_RADIUS + 8


def build_cell(
    cell: Cell,
    exposures: Sequence[Input],
    config: BuildConfig | None = None,
    seed: int = 0,
    *,
    mask_bits: MaskBits | None = None,
    band: str | None = None,
) -> CellCoadd:
    """Coadd the exposures that fully cover ``cell`` into a :class:`CellCoadd`.

    Parameters
    ----------
    cell : Cell
        The cell to build (its outer box is the output array).
    exposures : sequence of Exposure or ExposureSource
        Candidate inputs; each gets an input record with its status. A source is loaded
        (cut to the cell's surroundings) only if it may overlap the cell, one at a time,
        so memory does not grow with the number of inputs.
    config : BuildConfig
        Build settings (default ``BuildConfig()``).
    seed : int
        Seed of the noise realizations (non-negative); with the same seed and inputs the
        result is bit-identical, in any process.
    mask_bits : MaskBits
        Bit definitions of the output mask; every exposure's bits are translated into it
        by name (default: :meth:`MaskBits.union` of the exposures' maps).
    band : str, optional
        The band of the coadd (default: that of the first exposure); exposures of another
        band are rejected with status ``band_mismatch``.

    Returns
    -------
    CellCoadd
        Image in ``config.units`` per coadd pixel: nJy, or counts at
        ``config.zero_point`` (surface brightness scaled by the pixel-area ratio, so
        fluxes are conserved). A cell with no usable
        input is returned with ``is_empty=True``, a NaN image and a NO_DATA mask.
    """
    config = config or BuildConfig()
    inputs = [describe(item) for item in exposures]
    headers = [header_of(item) for item in inputs]
    check_unique_inputs(headers)
    if config.psf_size > min(cell.outer_bbox.shape):
        raise ValueError(f"psf_size {config.psf_size} exceeds the cell outer box {cell.outer_bbox}")
    check_mask_bits(headers, config)
    mask_bits = mask_bits or MaskBits.union(header.mask_bits for header in headers)
    sums = _Sums(cell.outer_bbox.shape, config.n_noise, config.psf_size)
    records: list[InputRecord] = []
    context = _CellContext(cell, config, seed, mask_bits)
    band = band if band is not None else (headers[0].band if headers else None)
    for item, header in zip(inputs, headers, strict=True):
        if header.band != band:
            records.append(_record(header, InputStatus.BAND_MISMATCH))
            continue
        near = rough_exposure_box(cell, header)
        if near is None:
            records.append(_record(header, InputStatus.NO_OVERLAP))
            continue
        exposure = item if isinstance(item, Exposure) else item.load(near.grow(SOURCE_MARGIN))
        records.append(_contribute(context, exposure, sums))
    return _finish(cell, sums, records, config, mask_bits)


class _CellContext:
    """What every input of one cell shares: the cell, settings, seed, output bits, the
    cell's Jacobian (for PSF moments) and its mapping grids."""

    def __init__(self, cell: Cell, config: BuildConfig, seed: int, mask_bits: MaskBits):
        self.cell, self.config, self.seed, self.mask_bits = cell, config, seed, mask_bits
        self.jacobian = _cell_jacobian(cell)
        self.grid_cache: dict = {}  # mapping grids, the same for every exposure of the cell


def _contribute(context: _CellContext, exposure: Exposure, sums: _Sums) -> InputRecord:
    """Select ``exposure`` for the cell and, if it is usable, add it to ``sums``."""
    cell, config = context.cell, context.config
    bad_bits = exposure.mask_bits.mask_of(
        name for name in config.bad_mask_bits if name in exposure.mask_bits.bits
    )
    found = select_exposure(cell, exposure, config, bad_bits, grid_cache=context.grid_cache)
    if isinstance(found, Rejection):
        return _record(exposure, found.status, overlap_fraction=found.overlap_fraction)
    overlap = found.overlap_fraction
    pixels = exposure_planes(found, config, context.seed, bad_bits)
    if pixels is None:  # a hole too large to interpolate
        return _record(exposure, InputStatus.MASKED_FRACTION, overlap_fraction=overlap)
    try:
        psf_stamp = _coadd_psf_contribution(cell, found, config.psf_size)
    except PsfError:
        return _record(exposure, InputStatus.BAD_PSF, overlap_fraction=overlap)
    mask = translated_mask(exposure, found.footprint, context.mask_bits)
    _add_exposure(sums, found, pixels, mask, psf_stamp, config.n_noise)
    moments = psf_moments(psf_stamp, context.jacobian)
    return _record(
        exposure, InputStatus.USED, weight=found.weight, overlap_fraction=overlap, **moments
    )


def _cell_jacobian(cell: Cell) -> np.ndarray:
    from cellcoadd.geometry.wcs_utils import local_jacobian

    ny, nx = cell.outer_bbox.shape
    return local_jacobian(cell.wcs, nx // 2, ny // 2)


def _finish(
    cell: Cell,
    sums: _Sums,
    records: list[InputRecord],
    config: BuildConfig,
    mask_bits: MaskBits,
) -> CellCoadd:
    common = {
        "inputs": records,
        "tract": cell.tract,
        "index": cell.index,
        "inner_bbox": cell.inner_bbox,
        "outer_bbox": cell.outer_bbox,
        "wcs": cell.wcs,
    }
    if sums.weight <= 0.0:
        return CellCoadd.empty(
            n_noise=config.n_noise, psf_size=config.psf_size, mask_bits=mask_bits, **common
        )
    total = sums.weight
    psf = sums.psf / sums.psf.sum()
    planes = {
        "image": (sums.image / total).astype(np.float32),
        "variance": (sums.variance / total**2).astype(np.float32),
        "noise": (sums.noise / total).astype(np.float32),
    }
    _check_finite(cell, planes, sums.mask, mask_bits)
    return CellCoadd(
        **planes,
        mask=sums.mask,
        mfrac=np.clip(sums.mfrac / total, 0.0, 1.0).astype(np.float32),
        psf=psf,
        **common,
    )


def _check_finite(
    cell: Cell, planes: dict[str, np.ndarray], mask: np.ndarray, mask_bits: MaskBits
) -> None:
    """Refuse (FloatingPointError) a coadd with non-finite pixels outside ``NO_DATA``.

    Selection rejects inputs whose contribution could overflow float32 (``bad_pixels``),
    so this does not happen; if it did, the cell fails by name instead of being written.
    """
    no_data = mask_bits.value("NO_DATA") if "NO_DATA" in mask_bits.bits else 0
    covered = (mask & no_data) == 0
    for name, plane in planes.items():
        bad = ~np.isfinite(plane) & covered
        if bad.any():
            raise FloatingPointError(
                f"cell {cell.index} of tract {cell.tract}: {int(bad.sum())} non-finite "
                f"{name} pixels outside NO_DATA"
            )


__all__ = ["build_cell", "check_mask_bits", "check_unique_inputs"]
