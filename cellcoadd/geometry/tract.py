"""Tracts, patches and cells: one tangent-plane WCS and one cell grid per tract.

A tract's pixel box starts at (0, 0) and holds ``patches_per_tract`` x ``patches_per_tract``
patches; a patch's inner box holds ``cells_per_patch`` x ``cells_per_patch`` cell inner
boxes. Cells are indexed by tract-global ``(cx, cy)``; cell ``(cx, cy)`` has the inner box
``[cx * cell_inner, (cx + 1) * cell_inner)`` (same for y) and an outer box grown by
``cell_border`` on every side. A patch also lists ``patch_border_cells`` rings of its
neighbours' inner cells (the same :class:`Cell` objects), so at tract edges a patch can
list cells with indices just outside ``[0, cells_per_tract)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from astropy.wcs import WCS
from numpy.typing import ArrayLike

from cellcoadd.errors import CellCoaddIndexError, CellCoaddValueError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.geometry.regions import InnerRegion
from cellcoadd.geometry.wcs_utils import canonical_wcs, gnomonic_radec, gnomonic_uv, shifted_wcs


def tract_wcs(center: tuple[float, float], config: SkyMapConfig) -> WCS:
    """Gnomonic (TAN) WCS of a tract centred on ``center`` (deg), North up, East left.

    Tract pixel ``(0, 0)`` is the first pixel; the tangent point is at 0-based pixel
    ``config.tangent_center`` in x and y: by default the centre of the tract box,
    ``(n - 1) / 2``; Rubin's ring sky map puts it on a pixel centre.
    """
    ref = config.tangent_center
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = [center[0] % 360.0, center[1]]
    wcs.wcs.crpix = [ref + 1.0, ref + 1.0]  # FITS is 1-based
    scale = config.pixel_scale / 3600.0
    wcs.wcs.cd = [[-scale, 0.0], [0.0, scale]]
    wcs.wcs.cunit = ["deg", "deg"]
    wcs.wcs.radesys = "ICRS"
    wcs.wcs.set()
    return canonical_wcs(wcs)


@dataclass(frozen=True)
class Cell:
    """One cell: its identity, boxes (tract pixels) and WCS.

    Attributes
    ----------
    tract : int
        Tract id.
    index : tuple of int
        Tract-global ``(cx, cy)``.
    inner_bbox, outer_bbox : Box
        Inner (unique) and outer (inner + border) boxes in tract pixels.
    """

    tract: int
    index: tuple[int, int]
    inner_bbox: Box
    outer_bbox: Box
    tract_wcs: WCS = field(repr=False, compare=False)
    config: SkyMapConfig | None = field(default=None, repr=False, compare=False)

    @property
    def owner_patch(self) -> tuple[int, int]:
        """``(px, py)`` of the patch whose inner region holds this cell's inner box."""
        per_patch = self._config.cells_per_patch
        return (self.index[0] // per_patch, self.index[1] // per_patch)

    @property
    def rubin_index(self) -> tuple[int, int]:
        """Rubin's patch-local cell index ``(x, y)`` of this cell in the patch that owns it
        (:attr:`owner_patch`): counted from that patch's first border cell, so the inner
        cells of an ``lsst_cells_v1`` patch are 1 to 20 (``Index2D`` of lsst.skymap's
        ``CellInfo``, the ``cell_id`` of lsst.cell_coadds). In another patch that lists it
        as a border cell it has another index: :meth:`Patch.rubin_cell_index`."""
        return rubin_cell_index(self.index, self.owner_patch, self._config)

    @property
    def _config(self) -> SkyMapConfig:
        if self.config is None:
            raise CellCoaddValueError(
                f"cell {self.index} was made without its sky-map configuration (make it with "
                "Tract.cell)"
            )
        return self.config

    @property
    def center(self) -> tuple[int, int]:
        """Tract pixel of the cell-centre pixel (integers).

        For an even ``cell_inner`` this is the pixel just above/right of the geometric
        centre; in the outer-box array it is always ``(nx // 2, ny // 2)``.
        """
        return (
            self.outer_bbox.x_start + self.outer_bbox.nx // 2,
            self.outer_bbox.y_start + self.outer_bbox.ny // 2,
        )

    @cached_property
    def center_sky(self) -> tuple[float, float]:
        """``(ra, dec)`` in deg of the cell-centre pixel."""
        ra, dec = self.tract_wcs.wcs_pix2world([self.center[0]], [self.center[1]], 0)
        return (float(ra[0]), float(dec[0]))

    @cached_property
    def wcs(self) -> WCS:
        """WCS of the outer-box array: its pixel (0, 0) is tract pixel ``outer_bbox`` start.

        In canonical form (see :func:`~cellcoadd.geometry.wcs_utils.canonical_wcs`) as the
        tract's is, without a conversion: a shift of an
        :class:`~cellcoadd.geometry.exact_wcs.ExactWCS` is one."""
        box = self.outer_bbox
        return shifted_wcs(self.tract_wcs, box.x_start, box.y_start, canonical=False)

    def contains_inner(self, x: float | np.ndarray, y: float | np.ndarray) -> bool | np.ndarray:
        """Whether tract pixel position(s) lie in the inner (unique) region, half-open."""
        return self.inner_bbox.contains(x, y)


def rubin_patch_id(patch: tuple[int, int], config: SkyMapConfig) -> int:
    """Rubin's sequential id of patch ``(px, py)``: ``py * nx + px``, ``nx`` the patches
    per tract row (:attr:`Patch.rubin_id`)."""
    return int(patch[1]) * config.patches_per_tract + int(patch[0])


def rubin_cell_index(
    index: tuple[int, int], patch: tuple[int, int], config: SkyMapConfig
) -> tuple[int, int]:
    """Rubin's index ``(x, y)`` of tract-global cell ``index`` in patch ``patch``: counted
    from the patch's first border cell, ``c - (cells_per_patch * p - patch_border_cells)``
    along each axis (0 to ``cells_per_patch + 2 patch_border_cells - 1`` for the patch's
    cells)."""
    per_patch, border = config.cells_per_patch, config.patch_border_cells
    return (
        int(index[0]) - (per_patch * int(patch[0]) - border),
        int(index[1]) - (per_patch * int(patch[1]) - border),
    )


def cell_from_rubin_index(
    rubin_index: tuple[int, int], patch: tuple[int, int], config: SkyMapConfig
) -> tuple[int, int]:
    """Tract-global index of the cell with Rubin's index ``rubin_index`` in patch ``patch``
    (the inverse of :func:`rubin_cell_index`)."""
    per_patch, border = config.cells_per_patch, config.patch_border_cells
    return (
        int(rubin_index[0]) + per_patch * int(patch[0]) - border,
        int(rubin_index[1]) + per_patch * int(patch[1]) - border,
    )


@dataclass(frozen=True)
class Patch:
    """One patch of a tract: ``cells_per_patch`` squared inner cells plus border cells."""

    tract: Tract = field(repr=False, compare=False)
    index: tuple[int, int]

    @property
    def config(self) -> SkyMapConfig:
        return self.tract.config

    @property
    def rubin_id(self) -> int:
        """Rubin's sequential patch id, the data butler's ``patch``: ``y * nx + x`` with
        ``nx`` the patches per tract row (e.g. 34 for patch (4, 3) of ``lsst_cells_v1``).
        :meth:`Tract.patch_from_rubin_id` is the inverse."""
        return rubin_patch_id(self.index, self.config)

    def rubin_cell_index(self, index: tuple[int, int]) -> tuple[int, int]:
        """Rubin's index ``(x, y)`` in this patch of the cell of tract-global ``index`` (one
        of :attr:`cell_indices`; border cells included)."""
        self._check_cell(index)
        return rubin_cell_index(index, self.index, self.config)

    def cell_from_rubin_index(self, rubin_index: tuple[int, int]) -> tuple[int, int]:
        """Tract-global index of the cell with Rubin's index ``rubin_index`` in this patch."""
        index = cell_from_rubin_index(rubin_index, self.index, self.config)
        self._check_cell(index, given=rubin_index)
        return index

    def _check_cell(self, index: tuple[int, int], given: tuple[int, int] | None = None) -> None:
        xs, ys = self._cell_range(self.config.patch_border_cells)
        if index[0] not in xs or index[1] not in ys:
            what = f"Rubin cell index {given}" if given is not None else f"cell {index}"
            side = len(xs)
            raise CellCoaddIndexError(
                f"{what} is not a cell of patch {self.index} ({side} x {side} cells with "
                "its border)",
                value=given if given is not None else index,
            )

    @property
    def inner_bbox(self) -> Box:
        """Union of the inner cells' inner boxes (patch inner boxes tile the tract)."""
        size = self.config.patch_inner
        px, py = self.index
        return Box(
            x_start=px * size, x_stop=(px + 1) * size, y_start=py * size, y_stop=(py + 1) * size
        )

    @property
    def outer_bbox(self) -> Box:
        """Union of the outer boxes of all the patch's cells (border cells included)."""
        cfg = self.config
        return self.inner_bbox.grow(cfg.patch_border_cells * cfg.cell_inner + cfg.cell_border)

    def _cell_range(self, border: int) -> tuple[range, range]:
        cpp = self.config.cells_per_patch
        px, py = self.index
        return (
            range(px * cpp - border, (px + 1) * cpp + border),
            range(py * cpp - border, (py + 1) * cpp + border),
        )

    @property
    def inner_cell_indices(self) -> list[tuple[int, int]]:
        """Tract-global indices of the inner cells, row by row (y outer, x inner)."""
        xs, ys = self._cell_range(0)
        return [(cx, cy) for cy in ys for cx in xs]

    @property
    def cell_indices(self) -> list[tuple[int, int]]:
        """Tract-global indices of every cell of the patch, border cells included."""
        xs, ys = self._cell_range(self.config.patch_border_cells)
        return [(cx, cy) for cy in ys for cx in xs]

    @property
    def cells(self) -> list[Cell]:
        """Every cell of the patch (inner and border), row by row."""
        return [self.tract.cell(cx, cy) for cx, cy in self.cell_indices]

    @property
    def inner_cells(self) -> list[Cell]:
        return [self.tract.cell(cx, cy) for cx, cy in self.inner_cell_indices]

    def is_inner_cell(self, index: tuple[int, int]) -> bool:
        xs, ys = self._cell_range(0)
        return index[0] in xs and index[1] in ys

    def contains_inner(self, x: float | np.ndarray, y: float | np.ndarray) -> bool | np.ndarray:
        """Whether tract pixel position(s) lie in the patch inner region, half-open."""
        return self.inner_bbox.contains(x, y)


@dataclass(frozen=True)
class Tract:
    """A tract: a TAN projection and a pixel box holding an integer number of patches.

    Attributes
    ----------
    id : int
        Tract id within its sky map.
    center : tuple of float
        ``(ra, dec)`` tangent point, deg.
    config : SkyMapConfig
        Sizes of the hierarchy.
    inner_region : InnerRegion
        The part of the sky this tract owns (every position is owned by one tract).
    """

    id: int
    center: tuple[float, float]
    config: SkyMapConfig = field(repr=False)
    inner_region: InnerRegion = field(repr=False, compare=False)

    @cached_property
    def wcs(self) -> WCS:
        """The tract's gnomonic WCS (0-based pixels; shared by its patches and cells)."""
        return tract_wcs(self.center, self.config)

    @property
    def bbox(self) -> Box:
        n = self.config.tract_pixels
        return Box(x_start=0, x_stop=n, y_start=0, y_stop=n)

    @property
    def n_patches(self) -> tuple[int, int]:
        return (self.config.patches_per_tract, self.config.patches_per_tract)

    def patch(self, px: int, py: int) -> Patch:
        """Patch ``(px, py)``, each in ``[0, patches_per_tract)``."""
        n = self.config.patches_per_tract
        if not (0 <= px < n and 0 <= py < n):
            raise CellCoaddIndexError(
                f"patch ({px}, {py}) is outside tract {self.id} ({n} x {n} patches)",
                value=(px, py),
                allowed=(0, n),
            )
        return Patch(tract=self, index=(int(px), int(py)))

    def patch_from_rubin_id(self, patch_id: int) -> Patch:
        """The patch whose Rubin id (``y * nx + x``, :attr:`Patch.rubin_id`) is ``patch_id``."""
        n = self.config.patches_per_tract
        if isinstance(patch_id, bool) or not 0 <= int(patch_id) < n * n:
            raise CellCoaddIndexError(
                f"patch id {patch_id} is outside tract {self.id} (0 to {n * n - 1})",
                value=patch_id,
                allowed=(0, n * n),
            )
        py, px = divmod(int(patch_id), n)
        return self.patch(px, py)

    @property
    def patches(self) -> list[Patch]:
        n = self.config.patches_per_tract
        return [self.patch(px, py) for py in range(n) for px in range(n)]

    def cell(self, cx: int, cy: int) -> Cell:
        """Cell with tract-global index ``(cx, cy)``.

        Valid indices run from ``-patch_border_cells`` to
        ``cells_per_tract + patch_border_cells - 1`` (border cells of edge patches).
        """
        cfg = self.config
        lo, hi = -cfg.patch_border_cells, cfg.cells_per_tract + cfg.patch_border_cells
        if not (lo <= cx < hi and lo <= cy < hi):
            raise CellCoaddIndexError(
                f"cell ({cx}, {cy}) is outside tract {self.id} (range [{lo}, {hi}))",
                value=(cx, cy),
                allowed=(lo, hi),
            )
        size = cfg.cell_inner
        inner = Box(
            x_start=cx * size, x_stop=(cx + 1) * size, y_start=cy * size, y_stop=(cy + 1) * size
        )
        return Cell(
            tract=self.id,
            index=(int(cx), int(cy)),
            inner_bbox=inner,
            outer_bbox=inner.grow(cfg.cell_border),
            tract_wcs=self.wcs,
            config=cfg,
        )

    @property
    def _center_pixel(self) -> float:
        # the tangent point, as in :func:`tract_wcs`
        return self.config.tangent_center

    def sky_to_pixel(self, ra: np.ndarray, dec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tract pixel ``(x, y)`` (0-based) of ``(ra, dec)`` in deg; vectorised.

        The same gnomonic projection as :attr:`wcs`, computed directly (much faster than
        building the astropy object for every tract). Positions 90 deg or more from the
        tangent point have no projection: NaN.
        """
        u, v = gnomonic_uv(
            np.atleast_1d(np.asarray(ra, dtype=float)),
            np.atleast_1d(np.asarray(dec, dtype=float)),
            *self.center,
        )
        scale = self.config.pixel_scale
        return self._center_pixel + u / scale, self._center_pixel + v / scale

    def pixel_to_sky(self, x: ArrayLike, y: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """``(ra, dec)`` in deg, RA in [0, 360), of tract pixel(s) ``(x, y)``; vectorised."""
        scale = self.config.pixel_scale
        u = (np.atleast_1d(np.asarray(x, dtype=float)) - self._center_pixel) * scale
        v = (np.atleast_1d(np.asarray(y, dtype=float)) - self._center_pixel) * scale
        return gnomonic_radec(u, v, *self.center)

    def contains_inner(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        """Whether sky position(s) (deg) belong to this tract's inner region."""
        ra = np.atleast_1d(np.asarray(ra, dtype=float))
        dec = np.atleast_1d(np.asarray(dec, dtype=float))
        owned = self.inner_region.contains(ra, dec)
        x, y = self.sky_to_pixel(ra, dec)
        return owned & self.bbox.contains(x, y)

    def cell_of_pixel(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tract-global cell indices whose inner boxes hold tract pixel position(s)."""
        size = self.config.cell_inner
        return (
            np.floor((np.asarray(x) + 0.5) / size).astype(np.int64),
            np.floor((np.asarray(y) + 0.5) / size).astype(np.int64),
        )
