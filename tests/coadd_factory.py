"""Small patch coadds for storage and reliability tests.

``make_patch`` fills every plane with arbitrary float32 bit patterns (NaN payloads,
infinities, -0.0, subnormals), deterministic in its seed, so that round trips are checked
bit for bit; ``assert_same`` compares two patches exactly. ``tiny_patch`` and
``tiny_exposures`` give a real build that takes well under a second.
"""

from __future__ import annotations

import dataclasses
import os

import galsim
import numpy as np
from astropy.wcs import WCS
from exposure_factory import make_exposure

from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.geometry.skymap import SkyMap
from cellcoadd.geometry.tract import Cell, Patch
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.inputs import REJECTION_REASONS, InputRecord
from cellcoadd.model.patch_coadd import PatchCoadd, PatchMetadata
from cellcoadd.model.psf_phase import MAP_FIELDS, PHASE_SIDE

SMALL = SkyMapConfig(
    cell_inner=8, cell_border=3, cells_per_patch=2, patch_border_cells=1, patches_per_tract=3
)
#: Cells of 80 x 80 pixels: a patch of a few MB.
MEDIUM = SkyMapConfig(cell_inner=60, cell_border=10, cells_per_patch=2, patches_per_tract=3)


def tract_wcs(config: SkyMapConfig, center: tuple[float, float]) -> WCS:
    """TAN WCS of a tract centred on ``center`` (deg), tract pixel (0, 0) at array (0, 0)."""
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = list(center)
    middle = (config.tract_pixels - 1) / 2.0
    wcs.wcs.crpix = [middle + 1.0, middle + 1.0]
    scale = config.pixel_scale / 3600.0
    wcs.wcs.cd = [[-scale, 0.0], [0.0, scale]]
    return wcs


def cell_wcs(tract: WCS, x_start: int, y_start: int) -> WCS:
    """The tract WCS shifted so that array pixel (0, 0) is tract pixel (x_start, y_start)."""
    wcs = tract.deepcopy()
    wcs.wcs.crpix = [tract.wcs.crpix[0] - x_start, tract.wcs.crpix[1] - y_start]
    return wcs


def make_metadata(
    config: SkyMapConfig = SMALL,
    *,
    n_noise: int = 2,
    psf_size: int = 5,
    band: str = "r",
    patch: tuple[int, int] = (1, 1),
    psf_corners: bool = False,
    psf_phase: bool = False,
) -> PatchMetadata:
    return PatchMetadata(
        skymap_config=config,
        tract=7,
        tract_center=(150.25, -2.5),
        patch=patch,
        band=band,
        units="nJy",
        build_config=BuildConfig(
            n_noise=n_noise, psf_size=psf_size, psf_corners=psf_corners, psf_phase=psf_phase
        ),
    )


def random_float_bits(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Arbitrary float32 bit patterns: NaN payloads, infinities, -0.0, subnormals included."""
    return rng.integers(0, 2**32, size=shape, dtype=np.uint64).astype(np.uint32).view(np.float32)


def make_records(rng: np.random.Generator, band: str, n_used: int, n_rejected: int) -> list:
    records = []
    for i in range(n_used + n_rejected):
        used = i < n_used
        nan_payload = np.array([0x7FF8_0000_DEAD_BEEF], dtype=np.uint64).view(np.float64)[0]
        records.append(
            InputRecord(
                visit=int(rng.integers(0, 10**6)) * 100 + i,
                detector=int(rng.integers(0, 189)),
                band=band if used or rng.random() < 0.5 else "g",
                weight=float(rng.uniform(0.1, 3.0)) if used else 0.0,
                status="used" if used else str(rng.choice(REJECTION_REASONS)),
                overlap_fraction=float(rng.uniform()),
                psf_fwhm=float(rng.uniform(0.6, 1.2)) if used else float("nan"),
                psf_e1=float(rng.normal(0, 0.01)),
                psf_e2=-0.0,
                psf_T=float(nan_payload) if not used else float(rng.uniform(0.2, 0.6)),
                zero_point=float(rng.uniform(27, 32)),
            )
        )
    return records


def make_cell(
    meta: PatchMetadata,
    index: tuple[int, int],
    rng: np.random.Generator,
    *,
    empty: bool = False,
    arbitrary_bits: bool = True,
) -> CellCoadd:
    inner, outer = meta.cell_boxes(index)
    wcs = cell_wcs(tract_wcs(meta.skymap_config, meta.tract_center), outer.x_start, outer.y_start)
    n_rejected = int(rng.integers(0, 3))
    if empty:
        return CellCoadd.empty(
            tract=meta.tract,
            index=index,
            inner_bbox=inner,
            outer_bbox=outer,
            wcs=wcs,
            n_noise=meta.n_noise,
            psf_size=meta.psf_size,
            inputs=make_records(rng, meta.band, 0, n_rejected),
            mask_bits=meta.mask_bits,
            psf_corners=meta.build_config.psf_corners,
            psf_phase=meta.build_config.psf_phase,
        )
    shape = outer.shape
    planes = ("image", "variance", "mfrac")
    if arbitrary_bits:
        values = {name: random_float_bits(rng, shape) for name in planes}
        noise = random_float_bits(rng, (meta.n_noise, *shape))
    else:
        values = {name: rng.standard_normal(shape, dtype=np.float32) for name in planes}
        noise = rng.standard_normal((meta.n_noise, *shape), dtype=np.float32)
    psf = rng.uniform(size=(meta.psf_size, meta.psf_size))
    corners = None
    if meta.build_config.psf_corners:
        corners = rng.uniform(size=(4, meta.psf_size, meta.psf_size))
        corners /= corners.sum(axis=(1, 2), keepdims=True)
    mask = rng.integers(0, 256, size=shape, dtype=np.int32)
    inputs = make_records(rng, meta.band, int(rng.integers(1, 4)), n_rejected)
    phase = {}
    if meta.build_config.psf_phase:  # drawn apart: the other planes keep their values
        n_used = sum(record.is_used for record in inputs)
        own = np.random.default_rng([abs(index[0]), abs(index[1]), n_used])
        phase = {
            "psf_phase": own.uniform(size=(n_used, PHASE_SIDE, PHASE_SIDE)).astype(np.float32),
            "psf_maps": own.uniform(size=(n_used, len(MAP_FIELDS))),
        }
    return CellCoadd(
        **values,
        mask=mask,
        noise=noise,
        psf=psf / psf.sum(),
        psf_corners=corners,
        **phase,
        inputs=inputs,
        tract=meta.tract,
        index=index,
        inner_bbox=inner,
        outer_bbox=outer,
        wcs=wcs,
    )


def make_patch(
    config: SkyMapConfig = SMALL,
    *,
    seed: int = 0,
    n_noise: int = 2,
    psf_size: int = 5,
    band: str = "r",
    patch: tuple[int, int] = (1, 1),
    empty: tuple[tuple[int, int], ...] = (),
    missing: tuple[tuple[int, int], ...] = (),
    arbitrary_bits: bool = True,
    psf_corners: bool = False,
    psf_phase: bool = False,
) -> PatchCoadd:
    """A patch with random contents (deterministic in ``seed``); ``psf_corners``: with
    random corner PSF stamps; ``psf_phase``: with random phase terms."""
    rng = np.random.default_rng(seed)
    meta = make_metadata(
        config,
        n_noise=n_noise,
        psf_size=psf_size,
        band=band,
        patch=patch,
        psf_corners=psf_corners,
        psf_phase=psf_phase,
    )
    cells = {
        index: make_cell(meta, index, rng, empty=index in empty, arbitrary_bits=arbitrary_bits)
        for index in meta.all_cell_indices
        if index not in missing
    }
    return PatchCoadd(meta, cells)


def assert_same(read: PatchCoadd, expected: PatchCoadd) -> None:
    assert read.metadata == expected.metadata
    assert list(read.cells) == list(expected.cells)
    for index, cell in expected.cells.items():
        assert read[index].equals(cell), f"cell {index} differs"


# ------------------------------------------------------------------ tiny builds from exposures

#: A tract of one patch of 2 x 2 cells (4 x 4 with the border cells), 32 px outer boxes.
TINY = SkyMapConfig(cell_inner=20, cell_border=6, cells_per_patch=2, patches_per_tract=1)
TINY_BUILD = BuildConfig(n_noise=2, psf_size=11)


def tiny_skymap() -> SkyMap:
    """A sky map of one tract with the :data:`TINY` geometry."""
    return SkyMap.from_centers([(30.0, -10.0)], TINY)


def tiny_patch() -> Patch:
    """The only patch of :func:`tiny_skymap`."""
    return tiny_skymap()[0].patch(0, 0)


def patch_center(patch: Patch) -> tuple[float, float]:
    """(ra, dec) in deg of the centre of the patch's inner box."""
    box = patch.inner_bbox
    ra, dec = patch.tract.pixel_to_sky(
        [(box.x_start + box.x_stop - 1) / 2.0], [(box.y_start + box.y_stop - 1) / 2.0]
    )
    return float(ra[0]), float(dec[0])


def tiny_exposures(patch: Patch, n: int = 2, *, first_visit: int = 0) -> list[Exposure]:
    """``n`` noisy exposures, each covering every cell of ``patch``, with varied WCSs."""
    return [
        make_exposure(
            patch_center(patch),
            shape=(110, 110),
            rotation_deg=25.0 * i,
            offset=(0.3 * i, -0.2 * i),
            noise_sigma=1.0,
            seed=first_visit + i,
            visit=first_visit + i,
        )
        for i in range(n)
    ]


def cell_sized_exposure(cell: Cell, visit: int, psf: object) -> Exposure:
    """A small exposure that fully covers ``cell`` only (its neighbours get ``edge``)."""
    exposure = make_exposure(cell.center_sky, shape=(40, 40), visit=visit)
    return dataclasses.replace(exposure, psf=psf)


class DyingPsf:
    """A PSF callable that kills the process calling it, unless that is ``parent_pid``
    (where it raises instead, so a mistake cannot kill the test run)."""

    def __init__(self, parent_pid: int) -> None:
        self.parent_pid = parent_pid

    def __call__(self, x: float, y: float) -> galsim.GSObject:
        if os.getpid() == self.parent_pid:
            raise RuntimeError("DyingPsf called in the parent process")
        os._exit(17)
