"""One cell's running sums while it is built, and the finished :class:`CellCoadd`.

The coadd is a weighted mean with one scalar weight per exposure (inverse background
variance at the common zero point), so it is linear and independent of the signal and has
a well-defined PSF (paper section 2). Image, noise realizations, variance and masked
fraction are added one exposure at a time, as warped planes the builder has already
weighted (:mod:`cellcoadd.builder.cell`); the PSF of each exposure is drawn at the cell
centre and warped through the same mapping as the image.
"""

from __future__ import annotations

import numpy as np

from cellcoadd.builder.kernels.warp import warp_planes
from cellcoadd.builder.mapping import footprint_box
from cellcoadd.builder.psf import draw_exposure_psf
from cellcoadd.builder.select import Candidate
from cellcoadd.geometry.tract import Cell
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.inputs import InputRecord, InputStatus
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.sources import ExposureHeader


class CellSums:
    """Running weighted sums of one cell's planes (float64 for exact accumulation).

    One array holds them all, in the order of
    :func:`~cellcoadd.builder.kernels.input_planes.input_planes` (image, K noise
    realizations, variance, masked fraction), so one addition adds an exposure.
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

    def add(
        self, planes: np.ndarray, mask: np.ndarray, psf_stamp: np.ndarray, weight: float
    ) -> None:
        """Add one exposure: its weighted warped ``planes`` (the first ``len(planes)``
        planes of the sums), its warped ``mask`` (ORed) and its PSF stamp with ``weight``."""
        self.planes[: len(planes)] += planes
        self.mask |= mask
        self.psf += weight * psf_stamp
        self.weight += weight


def coadd_psf_contribution(cell: Cell, candidate: Candidate, psf_size: int) -> np.ndarray:
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
    box = footprint_box(_Positions(x, y))
    stamp = draw_exposure_psf(candidate.exposure, x_center, y_center, box)
    warped = warp_planes(stamp[None], x - box.x_start, y - box.y_start)[0]
    return warped * mapping.area_ratio[rows, cols]


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
) -> CellCoadd:
    """The coadd of ``cell`` from its sums: weighted means as float32, the PSF normalised
    to unit sum; an empty cell when no input was used."""
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


__all__ = [
    "CellSums",
    "cell_jacobian",
    "coadd_psf_contribution",
    "finish_cell",
    "input_record",
]
