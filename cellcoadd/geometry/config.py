"""Sky map configuration: the sizes of tracts, patches and cells."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, model_serializer, model_validator

from cellcoadd.errors import ConfigError

#: Fields added after format 1.2; left out of the JSON when unset, so that files without
#: them are written byte for byte as before and older readers still accept them.
_OPTIONAL_FIELDS = ("tangent_pixel", "name")


#: Bounds of the sizes, generous for real surveys and checked before any work (a patch of
#: 10,000 x 10,000 cells died of MemoryError; at 1e-9 arcsec/pixel a tract's corners are
#: no longer distinct points). Rubin's ``lsst_cells_v1``: 0.2"/px, 150-px cells, 20 x 20
#: cells per patch (3,400 px with borders); DES tiles: 10,000 px at 0.263"/px; the finest
#: survey pixels are tens of milliarcseconds (HST, JWST), the coarsest tens of arcsec.
MIN_PIXEL_SCALE = 0.001
MAX_PIXEL_SCALE = 60.0
MAX_CELL_INNER = 4096
MAX_CELLS_PER_PATCH = 200
#: Side of a patch's outer region (inner and border cells, cell borders), pixels.
MAX_PATCH_PIXELS = 65536
#: The bounded sizes: (lowest, highest, unit), for messages naming the allowed range.
_RANGES: dict[str, tuple[float, float, str]] = {
    "pixel_scale": (MIN_PIXEL_SCALE, MAX_PIXEL_SCALE, "arcsec/pixel"),
    "cell_inner": (1, MAX_CELL_INNER, "pixels"),
    "cells_per_patch": (1, MAX_CELLS_PER_PATCH, "cells"),
}


class SkyMapConfig(BaseModel):
    """Sizes that define the tract -> patch -> cell hierarchy (frozen, stored in every file).

    Defaults follow LSST: 0.2 arcsec/pixel, 150-pixel cell inner regions (30 arcsec) with a
    50-pixel border (250 x 250 outer cells), 20 x 20 inner cells per patch with one border
    cell on each side, and 10 x 10 patches per tract (1.67 deg).

    Parameters
    ----------
    pixel_scale : float
        Coadd pixel scale, arcsec/pixel (0.001 to 60).
    cell_inner : int
        Side of a cell's inner region, pixels (1 to 4096).
    cell_border : int
        Buffer added on each side of the inner region to make the outer region, pixels.
    cells_per_patch : int
        Inner cells along each side of a patch (1 to 200; a patch's outer region, border
        cells included, at most 65,536 pixels on a side).
    patch_border_cells : int
        Border cells on each side of a patch (they are the neighbours' inner cells).
    patches_per_tract : int
        Patches along each side of a tract.
    n_rings : int
        Declination rings of the full-sky ring tessellation (``SkyMap.rings``), not counting
        the two polar caps.
    tract_overlap : float
        Minimum margin, deg, by which a ring tract's pixel box must extend beyond its inner
        region on the sky (so objects near tract boundaries are fully imaged). In Rubin's
        ring sky map (``SkyMap.lsst``) the margin added to half a ring's width.
    tangent_pixel : int or None
        0-based tract pixel, in x and in y, of every tract's tangent point; None for the
        centre of the tract box, ``(tract_pixels - 1) / 2``. Rubin's ring sky map puts it
        on a pixel centre (14999 in ``lsst_cells_v1``).
    name : str or None
        Name of the sky map this geometry belongs to, as Rubin's data butler knows it
        (e.g. ``"lsst_cells_v1"``); None for our own sky maps.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    pixel_scale: float = Field(0.2, gt=0, le=60, description="arcsec/pixel")
    cell_inner: int = Field(150, gt=0, description="pixels")
    cell_border: int = Field(50, ge=0, description="pixels")
    cells_per_patch: int = Field(20, gt=0)
    patch_border_cells: int = Field(1, ge=0)
    patches_per_tract: int = Field(10, gt=0)
    n_rings: int = Field(120, gt=0)
    tract_overlap: float = Field(1.0 / 60.0, ge=0, description="deg")
    tangent_pixel: int | None = Field(
        None, ge=0, description="0-based tract pixel of the tangent point (None: box centre)"
    )
    name: str | None = Field(None, min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.\-]+$")

    @model_serializer(mode="wrap")
    def _drop_unset_optional(self, handler: Any) -> dict[str, Any]:
        data = handler(self)
        for key in _OPTIONAL_FIELDS:
            if data.get(key) is None:
                data.pop(key, None)
        return data

    @model_validator(mode="after")
    def _check_consistency(self) -> SkyMapConfig:
        for name, (low, high, unit) in _RANGES.items():
            value = getattr(self, name)
            if not low <= value <= high:  # NaN too
                raise ConfigError(
                    f"{name} = {value} {unit} is outside the allowed range [{low:g}, {high:g}]",
                    value=value,
                    allowed=(low, high),
                )
        if self.cell_border > self.cell_inner:
            raise ConfigError(
                f"cell_border ({self.cell_border} px) must not exceed cell_inner "
                f"({self.cell_inner} px): a cell would overlap beyond its nearest neighbours",
                value=self.cell_border,
                allowed=(0, self.cell_inner),
            )
        if self.patch_border_cells > self.cells_per_patch:
            raise ConfigError(
                f"patch_border_cells ({self.patch_border_cells}) must not exceed "
                f"cells_per_patch ({self.cells_per_patch})"
            )
        if self.patch_outer > MAX_PATCH_PIXELS:
            raise ConfigError(
                f"a patch of {self.patch_outer} pixels on a side (cells_per_patch "
                f"{self.cells_per_patch} + 2 x patch_border_cells {self.patch_border_cells} "
                f"cells of cell_inner {self.cell_inner} px, + 2 x cell_border "
                f"{self.cell_border} px) is larger than the {MAX_PATCH_PIXELS} accepted",
                value=self.patch_outer,
                allowed=(1, MAX_PATCH_PIXELS),
            )
        if self.tangent_pixel is not None and self.tangent_pixel >= self.tract_pixels:
            raise ConfigError(
                f"tangent_pixel {self.tangent_pixel} is outside the tract's "
                f"{self.tract_pixels} pixels"
            )
        if self.tract_pixels > 2_000_000:
            raise ConfigError(
                f"a tract of {self.tract_pixels} pixels on a side is implausibly large",
                value=self.tract_pixels,
                allowed=(1, 2_000_000),
            )
        return self

    @property
    def tangent_center(self) -> float:
        """0-based tract pixel (x = y) of the tangent point."""
        if self.tangent_pixel is None:
            return (self.tract_pixels - 1) / 2.0
        return float(self.tangent_pixel)

    @property
    def cell_outer(self) -> int:
        """Side of a cell's outer region, pixels."""
        return self.cell_inner + 2 * self.cell_border

    @property
    def patch_inner(self) -> int:
        """Side of a patch's inner region, pixels."""
        return self.cell_inner * self.cells_per_patch

    @property
    def patch_outer(self) -> int:
        """Side of a patch's outer region (its border cells and their borders), pixels."""
        return (
            self.cells_per_patch + 2 * self.patch_border_cells
        ) * self.cell_inner + 2 * self.cell_border

    @property
    def tract_pixels(self) -> int:
        """Side of a tract, pixels."""
        return self.patch_inner * self.patches_per_tract

    @property
    def cells_per_tract(self) -> int:
        return self.cells_per_patch * self.patches_per_tract

    @property
    def tract_size_deg(self) -> float:
        """Side of a tract, deg."""
        return self.tract_pixels * self.pixel_scale / 3600.0
