"""Coadding cells: select, warp, accumulate, draw the PSF, finish (DESIGN "Building").

Cells of one tract are built together when they share inputs (a block of neighbours, or
one cell). Each exposure is mapped once onto the tract's pixel grid over the whole area
being built (:mod:`cellcoadd.builder.exposure_frame`); every cell selects it (edge-free:
it must cover the cell's outer box and the kernel's reach) from that mapping, and the
exposure is warped once over the bounding box of the cells that accept it, each cell
taking its part. A tract pixel therefore gets the same contribution from an exposure
whichever cell, block or process it is built in: two overlapping cells that accepted the
same inputs hold the same pixels, bit for bit. Image, noise realizations, variance and
masked fraction go through the same normalised Lanczos-3 weights; the PSF is drawn at each
cell centre and goes through the same mapping. Inputs are added one at a time, so memory
does not grow with their number.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence

import numpy as np

from cellcoadd.builder.cell_sums import (
    BlockSums,
    Contribution,
    cell_jacobian,
    coadd_psf_contribution,
    finish_cell,
    input_record,
)
from cellcoadd.builder.exposure_frame import ExposureFrame, exposure_frame
from cellcoadd.builder.exposure_planes import exposure_planes, translated_mask
from cellcoadd.builder.footprint import footprint_box
from cellcoadd.builder.kernels.accumulate import accumulate_warped
from cellcoadd.builder.kernels.mask_interpolation import DEFAULT_MAX_RADIUS
from cellcoadd.builder.kernels.mask_warp import warp_mask_or
from cellcoadd.builder.mapping import PixelMapping
from cellcoadd.builder.psf import PsfError, psf_moments
from cellcoadd.builder.select import Candidate, Rejection, rough_exposure_box, select_exposure
from cellcoadd.errors import InputError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.tract import Cell
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.inputs import InputRecord, InputStatus
from cellcoadd.model.mask_presets import fitting_presets
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.sources import (
    DescribedSource,
    ExposureHeader,
    ExposureSource,
    describe,
    header_of,
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
                f"{sorted(exposure.mask_bits.bits)}); {_preset_hint(exposure.mask_bits.bits)}"
                "map its bit names, or list them in BuildConfig.optional_mask_bits"
            )


def _preset_hint(defined: Iterable[str]) -> str:
    """Advice naming the survey presets whose bits an exposure defines, or ``""``."""
    names = fitting_presets(defined)
    if not names:
        return ""
    name = names[0]
    return (
        f"its bits fit the {name!r} preset: bad_mask_bits = {name!r} in the configuration "
        f"file or BuildConfig.for_survey({name!r}) (= {name.upper()}_BAD_MASK_BITS); else "
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


def warped_contribution(
    candidate: Candidate, pixels: np.ndarray, mask: np.ndarray, n_noise: int
) -> tuple[np.ndarray, np.ndarray]:
    """The weighted warped planes and the warped mask of one selected exposure.

    ``pixels`` are its planes over ``candidate.footprint`` (:func:`exposure_planes`),
    ``mask`` its mask there in the coadd's bit numbering. Image and noise get
    ``weight * area``, the variance ``weight^2 * area^2`` (the variance of a warped pixel
    is approximated by the warped variance; the noise realizations carry the exact
    correlated noise), the masked fraction ``weight``. The planes are warped into zeros and
    added to a cell's sums afterwards, so a pixel's sums do not depend on the box it was
    warped in.
    """
    box, mapping = candidate.footprint, candidate.mapping
    # without bad pixels the masked-fraction plane would be all zeros: it is left out
    with_mfrac = pixels.shape[2] == n_noise + 3
    x_local = mapping.x - box.x_start
    y_local = mapping.y - box.y_start
    weight, area = candidate.weight, mapping.area_ratio
    plane_weights = [weight] * (1 + n_noise) + [weight**2] + [weight] * with_mfrac
    plane_scales = [0] * (1 + n_noise) + [1] + [-1] * with_mfrac
    planes = np.zeros((pixels.shape[2], *x_local.shape))
    accumulate_warped(
        pixels, x_local, y_local, planes, plane_weights, np.stack([area, area**2]), plane_scales
    )
    return planes, warp_mask_or(mask, x_local, y_local)


class CellBlock:
    """Cells of one tract built together from the same candidate inputs.

    Parameters
    ----------
    cells : sequence of Cell
        The cells, all of one tract.
    config : BuildConfig
        Build settings.
    seed : int
        Seed of the noise realizations.
    mask_bits : MaskBits
        Bit definitions of the output masks.
    band : str or None
        The band of the coadds; inputs of another band are recorded as ``band_mismatch``.
    area : Box
        Tract pixels the exposures are mapped over (default: the cells' outer boxes'
        bounding box); a patch build passes the patch's, so every block of the patch
        uses the same mapping.
    record_distant : bool
        Record inputs whose projected valid box misses a cell as ``no_overlap`` (default);
        a patch build leaves them out of the cell's inputs instead.

    Attributes
    ----------
    current : Cell
        The cell being worked on (named when something fails).
    """

    def __init__(
        self,
        cells: Sequence[Cell],
        config: BuildConfig,
        seed: int,
        mask_bits: MaskBits,
        band: str | None,
        area: Box | None = None,
        *,
        record_distant: bool = True,
    ) -> None:
        if not cells:
            raise ValueError("a block needs at least one cell")
        if len({cell.tract for cell in cells}) > 1:
            raise ValueError("the cells of a block must belong to one tract")
        self.cells = list(cells)
        self.current = self.cells[0]
        for cell in self.cells:
            self.current = cell
            if config.psf_size > min(cell.outer_bbox.shape):
                raise ValueError(
                    f"psf_size {config.psf_size} exceeds the outer box {cell.outer_bbox} of "
                    f"cell {cell.index}"
                )
        self.config, self.seed, self.mask_bits, self.band = config, seed, mask_bits, band
        self.record_distant = record_distant
        self.area = area or Box.enclosing([cell.outer_bbox for cell in self.cells])
        self.sums = BlockSums(
            [cell.outer_bbox for cell in self.cells], config.n_noise, config.psf_size
        )
        self.records: list[list[InputRecord]] = [[] for _ in cells]
        self.jacobians = [cell_jacobian(cell) for cell in cells]
        self.grid_caches: list[dict] = [{} for _ in cells]  # cells mapping themselves

    def add(self, item: Exposure | DescribedSource, frame: ExposureFrame | None = None) -> None:
        """Consider one input for every cell: select, warp and add it where it is usable.

        ``frame``: the input's :func:`exposure_frame` over :attr:`area` (computed here by
        default). Each cell gets one input record.
        """
        header = header_of(item)
        if header.band != self.band:
            for records in self.records:
                records.append(input_record(header, InputStatus.BAND_MISMATCH))
            return
        if frame is None:
            frame = exposure_frame(
                self.cells[0].tract_wcs, self.area, header, self.config.mapping_tolerance
            )
        shared: list[int] = []  # cells inside the shared mapping
        alone: dict[int, Box] = {}  # cells mapping themselves: their rough exposure box
        for i, cell in enumerate(self.cells):
            self.current = cell
            box = cell.outer_bbox
            if frame.serves_nothing or not box.overlaps(frame.region):
                if self.record_distant:
                    self.records[i].append(input_record(header, InputStatus.NO_OVERLAP))
            elif frame.covers(box):
                shared.append(i)
            elif frame.mapping is not None:  # beyond the exposure's projected valid box
                self.records[i].append(_partial_record(frame, box, header))
            elif (near := rough_exposure_box(cell, header)) is not None:
                alone[i] = near
            elif self.record_distant:
                self.records[i].append(input_record(header, InputStatus.NO_OVERLAP))
        if not shared and not alone:
            return
        mapping = None
        loads = [near.grow(SOURCE_MARGIN) for near in alone.values()]
        if shared:
            assert frame.mapping is not None  # frame.covers says so
            mapping = frame.mapping.restricted(
                Box.enclosing([self.cells[i].outer_bbox for i in shared])
            )
            loads.append(footprint_box(mapping).grow(SOURCE_MARGIN))
        exposure = item if isinstance(item, Exposure) else item.load(Box.enclosing(loads))
        bad_bits = exposure.mask_bits.mask_of(
            name for name in self.config.bad_mask_bits if name in exposure.mask_bits.bits
        )
        contributions: list[Contribution] = []
        if mapping is not None:
            self._add_shared(exposure, item, shared, mapping, bad_bits, contributions)
        for i in alone:
            self.current = self.cells[i]
            found = select_exposure(
                self.cells[i], exposure, self.config, bad_bits, grid_cache=self.grid_caches[i]
            )
            self._use(i, exposure, found, bad_bits, contributions)
        self.sums.add(contributions)

    def _add_shared(
        self,
        exposure: Exposure,
        item: Exposure | DescribedSource,
        shared: list[int],
        mapping: PixelMapping,
        bad_bits: int,
        contributions: list[Contribution],
    ) -> None:
        """Select ``exposure`` for the ``shared`` cells from one mapping (over their
        bounding box, header pixels), and warp it once for all that accept it (appended
        to ``contributions``)."""
        # positions in the loaded pixels: a source's cutout starts at its origin
        dx, dy = (0, 0) if isinstance(item, Exposure) else exposure.origin
        x, y = mapping.x - dx, mapping.y - dy  # exact: integer shifts
        accepted: list[tuple[int, Candidate, np.ndarray]] = []
        for i in shared:
            cell = self.current = self.cells[i]
            rows, cols = cell.outer_bbox.slices_in(mapping.box)
            part = PixelMapping(
                cell.outer_bbox,
                x[rows, cols],
                y[rows, cols],
                mapping.area_ratio[rows, cols],
                mapping.max_error,
                mapping.grid_step,
            )
            found = select_exposure(cell, exposure, self.config, bad_bits, mapping=part)
            if isinstance(found, Rejection):
                self._reject(i, exposure, found)
                continue
            try:
                psf_stamp = coadd_psf_contribution(cell, found, self.config.psf_size)
            except PsfError:
                self._reject(i, exposure, Rejection(InputStatus.BAD_PSF, found.overlap_fraction))
                continue
            accepted.append((i, found, psf_stamp))
        if not accepted:
            return
        self.current = self.cells[accepted[0][0]]
        box = Box.enclosing([self.cells[i].outer_bbox for i, _, _ in accepted])
        rows, cols = box.slices_in(mapping.box)
        union = PixelMapping(
            box,
            x[rows, cols],
            y[rows, cols],
            mapping.area_ratio[rows, cols],
            mapping.max_error,
            mapping.grid_step,
        )
        warped = self._warp(accepted[0][1], union, exposure, bad_bits)
        if warped is None:  # the box of all holds something none of them needs
            for i, found, psf_stamp in accepted:
                self._use(i, exposure, found, bad_bits, contributions, psf_stamp)
            return
        for i, found, psf_stamp in accepted:
            self._accept(i, exposure, found, psf_stamp)
        contributions.append((box, *warped, [i for i, _, _ in accepted]))

    def _warp(
        self, found: Candidate, mapping: PixelMapping, exposure: Exposure, bad_bits: int
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """``exposure`` warped over ``mapping``'s box, with what selection gave ``found``
        (weight, flux scale); None if that box's footprint is not all usable (off the
        valid box, or a hole too large to interpolate)."""
        footprint = footprint_box(mapping)
        valid = exposure.valid_box
        assert valid is not None and exposure.mask is not None  # filled by Exposure
        if not valid.contains_box(footprint):
            return None
        candidate = dataclasses.replace(
            found,
            mapping=mapping,
            footprint=footprint,
            bad=(exposure.mask[footprint.slices] & bad_bits) != 0,
        )
        pixels = exposure_planes(candidate, self.config, self.seed, bad_bits)
        if pixels is None:
            return None
        mask = translated_mask(exposure, footprint, self.mask_bits)
        return warped_contribution(candidate, pixels, mask, self.config.n_noise)

    def _use(
        self,
        i: int,
        exposure: Exposure,
        found: Candidate | Rejection,
        bad_bits: int,
        contributions: list[Contribution],
        psf_stamp: np.ndarray | None = None,
    ) -> None:
        """Warp ``exposure`` for cell ``i`` alone, if selection accepted it (appended to
        ``contributions``)."""
        if isinstance(found, Rejection):
            self._reject(i, exposure, found)
            return
        pixels = exposure_planes(found, self.config, self.seed, bad_bits)
        if pixels is None:  # a hole too large to interpolate
            status = Rejection(InputStatus.MASKED_FRACTION, found.overlap_fraction)
            self._reject(i, exposure, status)
            return
        if psf_stamp is None:
            try:
                psf_stamp = coadd_psf_contribution(self.cells[i], found, self.config.psf_size)
            except PsfError:
                self._reject(i, exposure, Rejection(InputStatus.BAD_PSF, found.overlap_fraction))
                return
        mask = translated_mask(exposure, found.footprint, self.mask_bits)
        planes, warped_mask = warped_contribution(found, pixels, mask, self.config.n_noise)
        self._accept(i, exposure, found, psf_stamp)
        contributions.append((self.cells[i].outer_bbox, planes, warped_mask, [i]))

    def _accept(self, i: int, exposure: Exposure, found: Candidate, psf_stamp: np.ndarray) -> None:
        """Record ``exposure`` as used by cell ``i``, with its PSF (its pixels are added by
        :meth:`BlockSums.add`)."""
        self.sums.add_psf(i, psf_stamp, found.weight)
        moments = psf_moments(psf_stamp, self.jacobians[i])
        self.records[i].append(
            input_record(
                exposure,
                InputStatus.USED,
                weight=found.weight,
                overlap_fraction=found.overlap_fraction,
                **moments,
            )
        )

    def _reject(self, i: int, exposure: Exposure, rejection: Rejection) -> None:
        self.records[i].append(
            input_record(exposure, rejection.status, overlap_fraction=rejection.overlap_fraction)
        )

    def finish(self) -> list[CellCoadd]:
        """The coadds of the cells, in the order given."""
        results = []
        for i, (cell, records) in enumerate(zip(self.cells, self.records, strict=True)):
            self.current = cell
            sums = self.sums.cell(i)
            results.append(finish_cell(cell, sums, records, self.config, self.mask_bits))
        return results


def _partial_record(
    frame: ExposureFrame, box: Box, header: Exposure | ExposureHeader
) -> InputRecord:
    """The record of a cell reaching beyond the exposure's projected valid box: it cannot
    be covered (``edge``), or does not overlap at all (``no_overlap``)."""
    assert frame.mapping is not None and header.valid_box is not None
    part = frame.mapping.restricted(box.intersection(frame.region))
    inside = np.count_nonzero(header.valid_box.contains(part.x, part.y))
    fraction = inside / (box.nx * box.ny)
    status = InputStatus.EDGE if inside else InputStatus.NO_OVERLAP
    return input_record(header, status, overlap_fraction=fraction)


def build_cells(
    cells: Sequence[Cell],
    exposures: Sequence[Input],
    config: BuildConfig | None = None,
    seed: int = 0,
    *,
    mask_bits: MaskBits | None = None,
    band: str | None = None,
    area: Box | None = None,
    frames: Sequence[ExposureFrame | None] | None = None,
) -> list[CellCoadd]:
    """Coadd the exposures that fully cover each of ``cells`` (one tract) into cell coadds.

    Each exposure is mapped once over ``area`` and warped once over the cells that accept
    it (see the module notes); the result of a cell does not depend on which other cells
    are built with it. Parameters as for :func:`build_cell`, and:

    area : Box, optional
        Tract pixels the exposures are mapped over (default: the bounding box of the
        cells' outer boxes).
    frames : sequence of ExposureFrame or None, optional
        The exposures' frames over ``area`` (aligned with ``exposures``), if already
        computed (e.g. once per patch); None entries are computed here.

    Returns
    -------
    list of CellCoadd
        In the order of ``cells``.
    """
    config = config or BuildConfig()
    inputs = [describe(item) for item in exposures]
    headers = [header_of(item) for item in inputs]
    check_unique_inputs(headers)
    check_mask_bits(headers, config)
    mask_bits = mask_bits or MaskBits.union(header.mask_bits for header in headers)
    band = band if band is not None else (headers[0].band if headers else None)
    block = CellBlock(cells, config, seed, mask_bits, band, area)
    frames = frames if frames is not None else [None] * len(inputs)
    for item, frame in zip(inputs, frames, strict=True):
        block.add(item, frame)
    return block.finish()


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
    return build_cells([cell], exposures, config, seed, mask_bits=mask_bits, band=band)[0]


__all__ = [
    "SOURCE_MARGIN",
    "CellBlock",
    "build_cell",
    "build_cells",
    "check_mask_bits",
    "check_unique_inputs",
    "warped_contribution",
]
