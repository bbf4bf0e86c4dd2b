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

Every input has one shape (:class:`~cellcoadd.builder.inputs.BuildInput`: an in-memory
exposure is a source that loads itself), and every build starts with the same set-up
(:func:`~cellcoadd.builder.inputs.prepare`), whose settings every block shares. A cell
outside any shared mapping (part of the area off the exposure's projection) maps itself,
and its pixels go through the same warp (:meth:`CellBlock._contribute`), as does each
cell of a group whose common box holds pixels none of them could use.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from cellcoadd.builder.cell_sums import (
    BlockSums,
    Contribution,
    cell_jacobian,
    coadd_psf_contribution,
    corner_pixels,
    finish_cell,
    input_record,
)
from cellcoadd.builder.exposure_frame import ExposureFrame, rough_exposure_box
from cellcoadd.builder.exposure_planes import exposure_planes, translated_mask
from cellcoadd.builder.inputs import BuildInput, BuildSettings, prepare
from cellcoadd.builder.kernels.accumulate import accumulate_warped
from cellcoadd.builder.kernels.descriptor import WARP_KERNEL
from cellcoadd.builder.kernels.mask_interpolation import DEFAULT_MAX_RADIUS
from cellcoadd.builder.kernels.mask_warp import warp_mask_or
from cellcoadd.builder.mapping import PixelMapping, footprint_box
from cellcoadd.builder.psf import (
    PsfError,
    core_stencil,
    draw_exposure_core,
    input_map,
    local_map,
    node_position,
    psf_moments,
    render_cores,
    stencil_weights,
    warn_truncated_psfs,
)
from cellcoadd.builder.select import Candidate, Rejection, select_exposure
from cellcoadd.errors import CellCoaddValueError, ConfigError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.tract import Cell
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.inputs import InputRecord, InputStatus
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.psf_phase import prefiltered
from cellcoadd.model.sources import DescribedSource, ExposureHeader, ExposureSource

#: Pixels loaded around a cell's footprint from an exposure source: the interpolation
#: of bad pixels reads this far, plus the kernel's reach and a margin for the rough box.
SOURCE_MARGIN = DEFAULT_MAX_RADIUS + WARP_KERNEL.half_width + 5


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
    # the area and its square, made in place (the same values as np.stack([area, area**2])
    # without the temporary of the square and the copy of both)
    scales = np.empty((2, *area.shape))
    scales[0] = area
    np.multiply(area, area, out=scales[1])
    accumulate_warped(pixels, x_local, y_local, planes, plane_weights, scales, plane_scales)
    return planes, warp_mask_or(mask, x_local, y_local)


class CellBlock:
    """Cells of one tract built together from the same candidate inputs.

    Parameters
    ----------
    cells : sequence of Cell
        The cells, all of one tract, inside ``settings.area``.
    settings : BuildSettings
        What every block of the build shares (:func:`~cellcoadd.builder.inputs.prepare`).

    Attributes
    ----------
    current : Cell
        The cell being worked on (named when something fails).
    """

    def __init__(self, cells: Sequence[Cell], settings: BuildSettings) -> None:
        if not cells:
            raise CellCoaddValueError("a block needs at least one cell")
        if len({cell.tract for cell in cells}) > 1:
            raise CellCoaddValueError("the cells of a block must belong to one tract")
        self.cells = list(cells)
        self.current = self.cells[0]
        config = settings.config
        for cell in self.cells:
            self.current = cell
            if config.stamp_size > min(cell.outer_bbox.shape):
                raise ConfigError(
                    f"psf_size {config.stamp_size} exceeds the outer box {cell.outer_bbox} of "
                    f"cell {cell.index}",
                    value=config.stamp_size,
                    cell=cell.index,
                )
            border = min(cell.inner_bbox.x_start - cell.outer_bbox.x_start,
                         cell.inner_bbox.y_start - cell.outer_bbox.y_start,
                         cell.outer_bbox.x_stop - cell.inner_bbox.x_stop,
                         cell.outer_bbox.y_stop - cell.inner_bbox.y_stop)  # fmt: skip
            if config.psf_corners and config.stamp_size // 2 > border:
                raise ConfigError(
                    f"psf_corners: a {config.stamp_size}-pixel PSF stamp centred on a corner "
                    f"pixel of the inner box of cell {cell.index} reaches beyond its "
                    f"{border}-pixel border; use psf_size <= {2 * border + 1}",
                    value=config.stamp_size,
                    allowed=(3, 2 * border + 1),
                    cell=cell.index,
                )
        self.settings, self.config = settings, config
        self.sums = BlockSums(
            [cell.outer_bbox for cell in self.cells],
            config.n_noise,
            config.stamp_size,
            n_psf=5 if config.psf_corners else 1,
        )
        self.records: list[list[InputRecord]] = [[] for _ in cells]
        self.jacobians = [cell_jacobian(cell) for cell in cells]
        self.grid_caches: list[dict] = [{} for _ in cells]  # cells mapping themselves
        # per cell, the used inputs' phase terms (psf_phase), in the order of their records
        self.phase_terms: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in cells]
        self.cores: dict[_NodeKey, np.ndarray | None] = {}  # see _cores
        self.splines: dict[_NodeKey, np.ndarray] = {}
        # a varying model's stencils: their nodes' cores and spline coefficients, stacked
        self.stencils: dict[_NodeKey, tuple[np.ndarray, np.ndarray]] = {}

    def add(self, item: BuildInput, frame: ExposureFrame | None) -> None:
        """Consider one input for every cell: select, warp and add it where it is usable.

        ``frame``: the input's frame over the build's area
        (:func:`~cellcoadd.builder.exposure_frame.exposure_frame`), as
        :func:`~cellcoadd.builder.inputs.prepare` gives it (None for an input of another
        band, which is not mapped). Each cell gets at most one input record.
        """
        header = item.header
        if header.band != self.settings.band:
            for records in self.records:
                records.append(input_record(header, InputStatus.BAND_MISMATCH))
            return
        assert frame is not None  # prepare maps every input of the band
        shared, alone = self._near_cells(header, frame)
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
        exposure, origin = item.load(Box.enclosing(loads))
        bad_bits = exposure.mask_bits.mask_of(
            name for name in self.config.bad_mask_bits if name in exposure.mask_bits.bits
        )
        contributions: list[Contribution] = []
        if mapping is not None:
            self._add_shared(exposure, origin, shared, mapping, bad_bits, contributions)
        for i in alone:
            self.current = self.cells[i]
            found = select_exposure(
                self.cells[i], exposure, self.config, bad_bits, grid_cache=self.grid_caches[i]
            )
            if isinstance(found, Rejection):
                self._reject(i, exposure, found)
                continue
            # its PSF is drawn once the warp succeeded
            self._contribute(exposure, [(i, found, None)], found.mapping, bad_bits, contributions)
        self.sums.add(contributions)

    def _near_cells(
        self, header: Exposure | ExposureHeader, frame: ExposureFrame
    ) -> tuple[list[int], dict[int, Box]]:
        """Which cells the input may serve: those inside its shared mapping, and those
        that map themselves (no shared mapping) with their rough exposure box. The other
        cells get their record here: ``edge`` or ``no_overlap`` when they reach beyond
        the input's projected valid box, ``no_overlap`` (if recorded) when far."""
        shared: list[int] = []
        alone: dict[int, Box] = {}
        record_distant = self.settings.record_distant
        for i, cell in enumerate(self.cells):
            self.current = cell
            box = cell.outer_bbox
            if not frame.may_serve(box):
                if record_distant:
                    self.records[i].append(input_record(header, InputStatus.NO_OVERLAP))
            elif frame.covers(box):
                shared.append(i)
            elif frame.mapping is not None:  # beyond the exposure's projected valid box
                self.records[i].append(_partial_record(frame, box, header))
            elif (near := rough_exposure_box(cell, header)) is not None:
                alone[i] = near
            elif record_distant:
                self.records[i].append(input_record(header, InputStatus.NO_OVERLAP))
        return shared, alone

    def _add_shared(
        self,
        exposure: Exposure,
        origin: tuple[int, int],
        shared: list[int],
        mapping: PixelMapping,
        bad_bits: int,
        contributions: list[Contribution],
    ) -> None:
        """Select ``exposure`` for the ``shared`` cells from one mapping (over their
        bounding box, header pixels; ``origin``: the header pixel of the loaded pixels'
        first), and warp it once for all that accept it (appended to ``contributions``)."""
        dx, dy = origin
        x, y = mapping.x - dx, mapping.y - dy  # exact: integer shifts
        accepted: list[_Member] = []
        for i in shared:
            cell = self.current = self.cells[i]
            part = _part(mapping, x, y, cell.outer_bbox)
            found = select_exposure(cell, exposure, self.config, bad_bits, mapping=part)
            if isinstance(found, Rejection):
                self._reject(i, exposure, found)
                continue
            try:
                psf_stamp = self._input_psf(i, found)
            except PsfError:
                self._reject(i, exposure, Rejection(InputStatus.BAD_PSF, found.overlap_fraction))
                continue
            accepted.append((i, found, psf_stamp))
        if accepted:
            box = Box.enclosing([self.cells[i].outer_bbox for i, _, _ in accepted])
            union = _part(mapping, x, y, box)
            self._contribute(exposure, accepted, union, bad_bits, contributions)

    def _contribute(
        self,
        exposure: Exposure,
        members: list[_Member],
        mapping: PixelMapping,
        bad_bits: int,
        contributions: list[Contribution],
    ) -> None:
        """Warp ``exposure`` once over the cells of ``members`` (selected for it, each with
        its PSF stamp, or None to draw it after the warp) through ``mapping``, positions of
        the bounding box of their outer boxes; append the result to ``contributions`` and
        record the cells that use it.

        When that box's footprint is not all usable (off the valid box, or a hole too
        large to interpolate), several cells are warped one by one instead, each through
        its own selection mapping; a single cell is rejected (``masked_fraction``).
        """
        self.current = self.cells[members[0][0]]
        warped = self._warp(members[0][1], mapping, exposure, bad_bits)
        if warped is None:
            if len(members) > 1:  # the box of all holds something none of them needs
                for member in members:
                    self._contribute(exposure, [member], member[1].mapping, bad_bits, contributions)
            else:
                i, found, _ = members[0]
                status = Rejection(InputStatus.MASKED_FRACTION, found.overlap_fraction)
                self._reject(i, exposure, status)
            return
        used = []
        for i, found, psf_stamp in members:
            if psf_stamp is None:
                try:
                    psf_stamp = self._input_psf(i, found)
                except PsfError:
                    status = Rejection(InputStatus.BAD_PSF, found.overlap_fraction)
                    self._reject(i, exposure, status)
                    continue
            self._accept(i, exposure, found, psf_stamp)
            used.append(i)
        if used:
            box = Box.enclosing([self.cells[i].outer_bbox for i, _, _ in members])
            contributions.append((box, *warped, used))

    def _input_psf(self, i: int, found: Candidate) -> _InputPsf:
        """What an input gives cell ``i``'s PSF: its warped stamps and, with
        ``BuildConfig.psf_phase``, its phase term (the oversampled PSF core at the cell
        centre and its ``psf_maps`` row, :mod:`cellcoadd.model.psf_phase`).

        The centre stamp is the exposure's PSF drawn at the centre and warped
        (:func:`coadd_psf_contribution`). Each corner stamp (``psf_corners``) is the
        centre's plus what changes between the two positions, rendered from the
        exposure's oversampled cores (:meth:`_cores`) at each position's exposure phase,
        local map and area ratio (:func:`~cellcoadd.builder.psf.render_cores`): the PSF
        model's own change across the cell (the cores interpolated there) and the
        resampling's (the phase), within the cores' +-8 exposure pixels, where they
        change the moments; the wings beyond are the centre's.

        Raises
        ------
        PsfError
            When one of them cannot be drawn (the input is rejected for the whole cell).
        """
        cell, config = self.cells[i], self.config
        stamps = coadd_psf_contribution(cell, found, config.stamp_size)
        if not (config.psf_phase or config.psf_corners):
            return stamps, None
        mapping = found.mapping
        ny, nx = cell.outer_bbox.shape
        pixels = [(nx // 2, ny // 2)] + (corner_pixels(cell) if config.psf_corners else [])
        points = [(float(mapping.x[cy, cx]), float(mapping.y[cy, cx])) for cx, cy in pixels]
        core, coefficients = self._cores(found.exposure, points, config.psf_corners)
        if config.psf_corners:
            maps = [local_map(mapping.x, mapping.y, mapping.area_ratio, *p) for p in pixels]
            renders = render_cores(coefficients, maps, config.stamp_size)
            stamps = np.concatenate([stamps, stamps[0] + (renders[1:] - renders[0])])
        if not config.psf_phase:
            return stamps, None
        inner = cell.inner_bbox.slices_in(cell.outer_bbox)
        row = input_map(mapping.x, mapping.y, mapping.area_ratio, inner, found.weight)
        return stamps, (core, row)

    def _warp(
        self, found: Candidate, mapping: PixelMapping, exposure: Exposure, bad_bits: int
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """``exposure`` warped over ``mapping``'s pixels, with what selection gave ``found``
        (weight, flux scale); None if their footprint is not all usable (off the valid
        box, or a hole too large to interpolate)."""
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
        pixels = exposure_planes(candidate, self.config, self.settings.seed, bad_bits)
        if pixels is None:
            return None
        mask = translated_mask(exposure, footprint, self.settings.mask_bits)
        return warped_contribution(candidate, pixels, mask, self.config.n_noise)

    def _cores(
        self, exposure: Exposure, points: Sequence[tuple[float, float]], corners: bool
    ) -> tuple[np.ndarray, list[np.ndarray]]:
        """The exposure's oversampled PSF core at the first of ``points`` (exposure pixels:
        the cell centre; float32, as stored in ``psf_phase``) and, with ``corners``, the
        cubic B-spline coefficients of the cores at every point (for
        :func:`~cellcoadd.builder.psf.render_cores`; else ``[]``).

        The cores are drawn once per exposure at the nodes of a grid
        (:func:`~cellcoadd.builder.psf.core_stencil`) and kept for the block's other
        cells. For the corners, a varying model's are interpolated at the points with the
        stencil's Lagrange weights (drawing and the spline's prefilter are linear, so the
        coefficients are interpolated as the cores are); without them (the phase terms
        alone only carry how resampling changes with the phase) the node of the cell's
        square serves. A node depends on the exposure and its position alone, so a cell
        gets the same cores in any block. Where the model fails at a node of the
        stencil, the cell's own cores are drawn at the points.
        """
        stencil = core_stencil(exposure, *points[0], interpolate=corners)
        step, first, side = stencil
        keys = [
            (exposure.visit, exposure.detector, step, first[0] + a, first[1] + b)
            for b in range(side)
            for a in range(side)
        ]
        nodes = [self._node(exposure, key) for key in keys]
        if any(node is None for node in nodes):
            drawn = [
                draw_exposure_core(exposure, x, y)
                for x, y in points[: len(points) if corners else 1]
            ]
            return drawn[0], [prefiltered(core) for core in drawn] if corners else []
        found = [node for node in nodes if node is not None]
        if len(found) == 1:
            return found[0], [self._spline(keys[0])] * len(points) if corners else []
        stacked = self.stencils.get(keys[0])
        if stacked is None:  # the stencil's nodes, kept for the block's other cells
            splines = np.stack([self._spline(key) for key in keys])
            stacked = self.stencils[keys[0]] = (np.stack(found).astype(np.float64), splines)
        weights = stencil_weights(exposure, stencil, points)
        # einsum's own loops, not BLAS: the same sums in the same order on any machine
        core = np.einsum("k,kij->ij", weights[0], stacked[0])
        coefficients = np.einsum("pk,kij->pij", weights, stacked[1])
        return core.astype(np.float32), list(coefficients)

    def _node(self, exposure: Exposure, key: _NodeKey) -> np.ndarray | None:
        """The exposure's core at node ``key[3:]`` of spacing ``key[2]``, drawn once per block
        (None where the model fails there)."""
        if key not in self.cores:
            try:
                self.cores[key] = draw_exposure_core(exposure, *node_position(exposure, *key[2:]))
            except PsfError:
                self.cores[key] = None
        return self.cores[key]

    def _spline(self, key: _NodeKey) -> np.ndarray:
        """The cubic B-spline coefficients of a drawn node's core, computed once."""
        spline = self.splines.get(key)
        if spline is None:
            core = self.cores[key]
            assert core is not None  # only drawn nodes are asked for
            spline = self.splines[key] = prefiltered(core)
        return spline

    def _accept(self, i: int, exposure: Exposure, found: Candidate, psf: _InputPsf) -> None:
        """Record ``exposure`` as used by cell ``i``, with its PSF stamps (centre first; its
        pixels are added by :meth:`BlockSums.add`) and phase term. The record's PSF
        moments are the centre's."""
        psf_stamp, phase = psf
        self.sums.add_psf(i, psf_stamp, found.weight)
        if phase is not None:
            self.phase_terms[i].append(phase)
        psf_stamp = psf_stamp[0]
        moments = psf_moments(psf_stamp, self.jacobians[i])
        # the model was drawn with unit flux: what the stamp lacks lies outside it
        moments["psf_flux_outside"] = float(1.0 - psf_stamp.sum())
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
            terms = self.phase_terms[i] if self.config.psf_phase else None
            results.append(
                finish_cell(cell, sums, records, self.config, self.settings.mask_bits, terms)
            )
        return results


#: What an input gives a cell's PSF: its warped stamps ``(n_psf, n, n)`` and its phase
#: term (oversampled core, ``psf_maps`` row), None without ``psf_phase``.
_InputPsf = tuple[np.ndarray, "tuple[np.ndarray, np.ndarray] | None"]


#: A node of an exposure's grid of PSF cores: its visit, detector, the grid's spacing and
#: the node ``(bx, by)`` (:class:`~cellcoadd.builder.psf.Stencil`).
_NodeKey = tuple[int, int, int, int, int]


#: A cell selected for an input: its index in the block, the selection, its PSF (None:
#: not drawn yet).
_Member = tuple[int, Candidate, "_InputPsf | None"]


def _part(mapping: PixelMapping, x: np.ndarray, y: np.ndarray, box: Box) -> PixelMapping:
    """The mapping of the pixels of ``box`` (inside ``mapping.box``) at positions ``x``,
    ``y`` (``mapping``'s, shifted)."""
    rows, cols = box.slices_in(mapping.box)
    return PixelMapping(
        box,
        x[rows, cols],
        y[rows, cols],
        mapping.area_ratio[rows, cols],
        mapping.max_error,
        mapping.grid_step,
    )


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
    exposures: Sequence[Exposure | ExposureSource | DescribedSource | BuildInput],
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
    build = prepare(
        cells,
        exposures,
        config or BuildConfig(),
        seed,
        mask_bits=mask_bits,
        band=band,
        area=area,
        frames=frames,
    )
    block = CellBlock(cells, build.settings)
    for item, frame in zip(build.inputs, build.frames, strict=True):
        block.add(item, frame)
    coadds = block.finish()
    warn_truncated_psfs(coadds)
    return coadds


def build_cell(
    cell: Cell,
    exposures: Sequence[Exposure | ExposureSource | DescribedSource],
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
    "warped_contribution",
]
