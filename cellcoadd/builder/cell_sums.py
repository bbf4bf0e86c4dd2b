"""One cell's running sums while it is built, and the finished :class:`CellCoadd`.

The coadd is a weighted mean with one scalar weight per exposure (inverse background
variance at the common zero point), so it is linear and independent of the signal and has
a well-defined PSF (paper section 2). Image, noise realizations, variance and masked
fraction are added one exposure at a time, as warped planes the builder has already
weighted (:mod:`cellcoadd.builder.cell`); the PSF of each exposure is drawn at the cell
centre and warped through the same mapping as the image.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from cellcoadd.builder.kernels.warp import warp_planes
from cellcoadd.builder.mapping import footprint_box
from cellcoadd.builder.psf import draw_exposure_psf
from cellcoadd.builder.select import Candidate
from cellcoadd.errors import CellCoaddFloatingPointError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.tract import Cell
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.inputs import InputRecord, InputStatus
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.planes import CORNER_ORDER
from cellcoadd.model.psf_phase import MAP_FIELDS, PHASE_SIDE
from cellcoadd.model.sources import ExposureHeader


class CellSums:
    """One cell's weighted sums (float64), as :func:`finish_cell` reads them.

    ``planes`` holds them all, in the order of
    :func:`~cellcoadd.builder.kernels.input_planes.input_planes` (image, K noise
    realizations, variance, masked fraction); ``psf`` the PSF stamps (centre, then the
    corners if drawn), ``(n_psf, n, n)``.
    """

    def __init__(
        self, planes: np.ndarray, mask: np.ndarray, psf: np.ndarray, weight: float
    ) -> None:
        n_noise = len(planes) - 3
        self.planes, self.mask, self.psf, self.weight = planes, mask, psf, weight
        self.image = planes[0]
        self.noise = planes[1 : 1 + n_noise]
        self.variance = planes[1 + n_noise]
        self.mfrac = planes[2 + n_noise]


#: One input's warped planes (P, ny, nx) and mask over a box, for some cells of a block
#: (indices; their outer boxes lie inside the box).
Contribution = tuple[Box, np.ndarray, np.ndarray, list[int]]


class BlockSums:
    """The running sums of a block of cells, in float64 for exact accumulation.

    Cells that have received the same inputs so far ("followers") share one array over
    the block's box: an input warped once over the block is added once, not once per
    cell. A cell gets its own copy the first time an input reaches the followers but not
    it (or reaches it alone). Both hold, bit for bit, what adding each input's warped
    planes to the cell's own zeroed sums would: the same additions in the same order.

    Parameters
    ----------
    boxes : sequence of Box
        The cells' outer boxes (tract pixels).
    n_noise : int
        Number of noise realizations (the sums hold ``n_noise + 3`` planes).
    psf_size : int
        Side of the PSF stamps, pixels.
    n_psf : int
        PSF stamps per cell: 1 (the centre), or 5 (the centre and the inner box's corners).
    """

    def __init__(self, boxes: Sequence[Box], n_noise: int, psf_size: int, n_psf: int = 1) -> None:
        self.boxes = list(boxes)
        self.box = Box.enclosing(self.boxes)
        self.n_planes = n_noise + 3
        self.shared = np.zeros((0, 0, 0))  # allocated by the first addition
        self.shared_mask = np.zeros((0, 0), dtype=np.int32)
        self.own: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(self.boxes)
        self.psf = [np.zeros((n_psf, psf_size, psf_size)) for _ in self.boxes]
        self.weight = [0.0] * len(self.boxes)

    def add_psf(self, i: int, stamp: np.ndarray, weight: float) -> None:
        """Add one input's PSF stamps (``(n_psf, n, n)``) and weight to cell ``i``."""
        self.psf[i] += weight * stamp
        self.weight[i] += weight

    def add(self, contributions: Sequence[Contribution]) -> None:
        """Add what one input gives the cells: every contribution of that input at once."""
        groups = [[i for i in cells if self.own[i] is None] for _, _, _, cells in contributions]
        best = max(range(len(groups)), key=lambda k: len(groups[k]), default=None)
        joining = set(groups[best]) if best is not None else set()
        if joining:  # the shared sums change: followers left out take their own copy first
            for i, own in enumerate(self.own):
                if own is None and i not in joining:
                    self._diverge(i)
        for k, (box, planes, mask, cells) in enumerate(contributions):
            for i in cells:
                if i in joining:
                    continue
                if self.own[i] is None:
                    self._diverge(i)
                own_planes, own_mask = self.own[i]  # type: ignore[misc]
                rows, cols = self.boxes[i].slices_in(box)
                own_planes[: len(planes)] += planes[:, rows, cols]
                own_mask |= mask[rows, cols]
            if k == best and joining:
                self._add_shared(box, planes, mask, Box.enclosing(self.boxes[i] for i in joining))

    def _add_shared(self, box: Box, planes: np.ndarray, mask: np.ndarray, region: Box) -> None:
        if not self.shared.size:
            self.shared = np.zeros((self.n_planes, *self.box.shape))
            self.shared_mask = np.zeros(self.box.shape, dtype=np.int32)
        rows, cols = region.slices_in(self.box)
        source_rows, source_cols = region.slices_in(box)
        self.shared[: len(planes), rows, cols] += planes[:, source_rows, source_cols]
        self.shared_mask[rows, cols] |= mask[source_rows, source_cols]

    def _diverge(self, i: int) -> None:
        """Give cell ``i`` its own copy of the sums it has shared so far."""
        if not self.shared.size:
            shape = self.boxes[i].shape
            self.own[i] = (np.zeros((self.n_planes, *shape)), np.zeros(shape, dtype=np.int32))
            return
        rows, cols = self.boxes[i].slices_in(self.box)
        self.own[i] = (self.shared[:, rows, cols].copy(), self.shared_mask[rows, cols].copy())

    def cell(self, i: int) -> CellSums:
        """Cell ``i``'s sums (its planes a view of the shared ones while it follows)."""
        own = self.own[i]
        if own is None and not self.shared.size:  # nothing was added to any follower
            self._diverge(i)
            own = self.own[i]
        if own is None:
            rows, cols = self.boxes[i].slices_in(self.box)
            own = (self.shared[:, rows, cols], self.shared_mask[rows, cols].copy())
        return CellSums(own[0], own[1], self.psf[i], self.weight[i])


def coadd_psf_contribution(
    cell: Cell, candidate: Candidate, psf_size: int, corners: bool = False
) -> np.ndarray:
    """The exposure PSF at the cell centre, warped like the image into the PSF stamp; with
    ``corners``, also at the 4 corner pixels of the inner box.

    Each stamp is centred on its pixel (the cell-centre pixel ``(nx // 2, ny // 2)`` of the
    outer box, the corners those of :attr:`CellCoadd.psf_corner_positions`); its pixels
    map to the exposure through the same mapping as the image pixels, so the PSF has the
    image's sub-pixel phase there. Returns shape ``(1, n, n)``, or ``(5, n, n)`` with
    ``corners`` (centre first, then the corners in the order of
    :data:`~cellcoadd.model.planes.CORNER_ORDER`).

    Raises
    ------
    PsfError
        When the PSF cannot be drawn at one of the positions: the input is then rejected
        for the whole cell, so the centre and corner PSFs average the same inputs.
    """
    ny, nx = cell.outer_bbox.shape
    centres = [(nx // 2, ny // 2)]
    if corners:
        centres += corner_pixels(cell)
    return np.stack([_psf_stamp(candidate, cx, cy, psf_size) for cx, cy in centres])


def corner_pixels(cell: Cell) -> list[tuple[int, int]]:
    """Outer-box array pixels ``(x, y)`` of the inner box's corner pixels, in the order of
    :data:`~cellcoadd.model.planes.CORNER_ORDER`."""
    rows, cols = cell.inner_bbox.slices_in(cell.outer_bbox)
    xs, ys = (cols.start, cols.stop - 1), (rows.start, rows.stop - 1)
    return [(xs[i], ys[j]) for i, j in CORNER_ORDER]


def _psf_stamp(candidate: Candidate, cx: int, cy: int, psf_size: int) -> np.ndarray:
    """The exposure PSF drawn at the exposure position of outer-box pixel ``(cx, cy)``
    and warped into the ``psf_size`` stamp centred there (which must lie in the box)."""
    mapping = candidate.mapping
    half = psf_size // 2
    rows = slice(cy - half, cy + half + 1)
    cols = slice(cx - half, cx + half + 1)
    x, y = mapping.x[rows, cols], mapping.y[rows, cols]
    x_center, y_center = float(mapping.x[cy, cx]), float(mapping.y[cy, cx])
    box = footprint_box(_Positions(x, y))
    stamp = draw_exposure_psf(candidate.exposure, x_center, y_center, box)
    warped = warp_planes(stamp[None], x - box.x_start, y - box.y_start)[0]
    warped *= mapping.area_ratio[rows, cols]
    # resampling changes the sum by up to ~1e-4 (more for undersampled PSFs): the warped
    # stamp is given the model's own flux over the stamp's area, so that what it lacks
    # of the unit flux (psf_flux_outside) is the model's flux beyond the stamp
    total = float(warped.sum())
    if total > 0.0:
        warped *= flux_inside(stamp, box, x, y) / total
    return warped


#: Sub-pixels per side that :func:`flux_inside` samples a pixel the stamp's edge crosses.
_EDGE_SUBPIXELS = 4


def flux_inside(stamp: np.ndarray, box: Box, x: np.ndarray, y: np.ndarray) -> float:
    """The flux of an exposure-frame ``stamp`` (drawn over ``box``) that falls inside the
    square of coadd pixels whose centres map to exposure positions ``x``, ``y``
    (``(n, n)``, odd ``n``), each drawn pixel counted by the fraction of it inside.

    The square is the coadd PSF stamp's area, mapped to the exposure by the affine map of
    ``x``, ``y`` through its centre and the ends of its middle row and column (over a few
    arcsec the mapping is affine to far below a pixel); pixels the square's edge crosses
    are sampled on :data:`_EDGE_SUBPIXELS` squared points.
    """
    n = x.shape[0]
    half = n // 2
    # the affine map from the centre and the middle row and column's ends
    columns = [(x[half, -1] - x[half, 0]) / (n - 1), (y[half, -1] - y[half, 0]) / (n - 1)]
    rows = [(x[-1, half] - x[0, half]) / (n - 1), (y[-1, half] - y[0, half]) / (n - 1)]
    inverse = np.linalg.inv(np.array([columns, rows]).T)  # exposure offsets -> (i, j)
    centre = (float(x[half, half]), float(y[half, half]))
    limit = half + 0.5
    ey, ex = np.mgrid[box.y_start : box.y_stop, box.x_start : box.x_stop].astype(np.float64)

    def depth(px: np.ndarray, py: np.ndarray) -> np.ndarray:
        """How far inside the square (stamp pixels; < 0: outside) exposure points lie."""
        u = inverse[0, 0] * (px - centre[0]) + inverse[0, 1] * (py - centre[1])
        v = inverse[1, 0] * (px - centre[0]) + inverse[1, 1] * (py - centre[1])
        return limit - np.maximum(np.abs(u), np.abs(v))

    at_centres = depth(ex, ey)
    # half a pixel's diagonal, in stamp pixels: pixels farther from the edge are whole
    reach = 0.5 * float(np.abs(inverse).sum(axis=1).max())
    fraction = (at_centres > 0.0).astype(np.float64)
    edge = np.abs(at_centres) <= reach
    if np.any(edge):
        s = _EDGE_SUBPIXELS
        offsets = (np.arange(s) + 0.5) / s - 0.5
        oy, ox = np.meshgrid(offsets, offsets, indexing="ij")
        sub = depth(ex[edge][:, None] + ox.ravel(), ey[edge][:, None] + oy.ravel())
        fraction[edge] = (sub > 0.0).mean(axis=1)
    return float(np.sum(stamp * fraction))


class _Positions:
    """Exposure positions ``x`` and ``y`` of some pixels, for :func:`footprint_box`."""

    def __init__(self, x: np.ndarray, y: np.ndarray) -> None:
        self.x, self.y = x, y


def input_record(
    exposure: Exposure | ExposureHeader, status: InputStatus, **fields: float
) -> InputRecord:
    """The record of one input of a cell (unset fields: 0, or NaN for PSF moments)."""
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
        psf_flux_outside=fields.pop("psf_flux_outside", float("nan")),
    )


def cell_jacobian(cell: Cell) -> np.ndarray:
    """The Jacobian (arcsec per pixel) of the cell's WCS at its centre pixel."""
    from cellcoadd.geometry.wcs_utils import local_jacobian

    ny, nx = cell.outer_bbox.shape
    return local_jacobian(cell.wcs, nx // 2, ny // 2)


def finish_cell(
    cell: Cell,
    sums: CellSums,
    records: list[InputRecord],
    config: BuildConfig,
    mask_bits: MaskBits,
    phase_terms: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
) -> CellCoadd:
    """The coadd of ``cell`` from its sums: weighted means as float32, the PSF (and each
    corner PSF) normalised to unit sum, the used inputs' ``phase_terms`` (oversampled
    core, ``psf_maps`` row; None: not built) stacked; an empty cell when no input was
    used."""
    cores: np.ndarray | None = None
    maps: np.ndarray | None = None
    if phase_terms is not None and phase_terms and sums.weight > 0.0:
        cores = np.stack([core for core, _ in phase_terms])
        maps = np.stack([row for _, row in phase_terms])
    elif phase_terms is not None:
        cores = np.zeros((0, PHASE_SIDE, PHASE_SIDE), dtype=np.float32)
        maps = np.zeros((0, len(MAP_FIELDS)))
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
            n_noise=config.n_noise,
            psf_size=config.stamp_size,
            mask_bits=mask_bits,
            psf_corners=config.psf_corners,
            psf_phase=config.psf_phase,
            **common,
        )
    total = sums.weight
    # each stamp normalised on its own (the same division as before for the centre's)
    psf = sums.psf[0] / sums.psf[0].sum()
    corners = None
    if len(sums.psf) > 1:
        corners = sums.psf[1:] / sums.psf[1:].sum(axis=(1, 2), keepdims=True)
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
        psf_corners=corners,
        psf_phase=cores,
        psf_maps=maps,
        **common,
    )


def _check_finite(
    cell: Cell, planes: dict[str, np.ndarray], mask: np.ndarray, mask_bits: MaskBits
) -> None:
    """Refuse (CellCoaddFloatingPointError) a coadd with non-finite pixels outside ``NO_DATA``.

    Selection rejects inputs whose contribution could overflow float32 (``bad_pixels``),
    so this does not happen; if it did, the cell fails by name instead of being written.
    """
    no_data = mask_bits.value("NO_DATA") if "NO_DATA" in mask_bits.bits else 0
    covered = (mask & no_data) == 0
    for name, plane in planes.items():
        bad = ~np.isfinite(plane) & covered
        if bad.any():
            raise CellCoaddFloatingPointError(
                f"cell {cell.index} of tract {cell.tract}: {int(bad.sum())} non-finite "
                f"{name} pixels outside NO_DATA",
                cell=cell.index,
            )


__all__ = [
    "BlockSums",
    "CellSums",
    "Contribution",
    "cell_jacobian",
    "coadd_psf_contribution",
    "corner_pixels",
    "finish_cell",
    "input_record",
]
