"""Sky map configuration: the sizes of tracts, patches and cells."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator

from cellcoadd.errors import ConfigError


class SkyMapConfig(BaseModel):
    """Sizes that define the tract -> patch -> cell hierarchy (frozen, stored in every file).

    Defaults follow LSST: 0.2 arcsec/pixel, 150-pixel cell inner regions (30 arcsec) with a
    50-pixel border (250 x 250 outer cells), 20 x 20 inner cells per patch with one border
    cell on each side, and 10 x 10 patches per tract (1.67 deg).

    Parameters
    ----------
    pixel_scale : float
        Coadd pixel scale, arcsec/pixel.
    cell_inner : int
        Side of a cell's inner region, pixels.
    cell_border : int
        Buffer added on each side of the inner region to make the outer region, pixels.
    cells_per_patch : int
        Inner cells along each side of a patch.
    patch_border_cells : int
        Border cells on each side of a patch (they are the neighbours' inner cells).
    patches_per_tract : int
        Patches along each side of a tract.
    n_rings : int
        Declination rings of the full-sky ring tessellation (``SkyMap.rings``), not counting
        the two polar caps.
    tract_overlap : float
        Minimum margin, deg, by which a ring tract's pixel box must extend beyond its inner
        region on the sky (so objects near tract boundaries are fully imaged).
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

    @model_validator(mode="after")
    def _check_consistency(self) -> SkyMapConfig:
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
        if self.tract_pixels > 2_000_000:
            raise ConfigError(
                f"a tract of {self.tract_pixels} pixels on a side is implausibly large",
                value=self.tract_pixels,
                allowed=(1, 2_000_000),
            )
        return self

    @property
    def cell_outer(self) -> int:
        """Side of a cell's outer region, pixels."""
        return self.cell_inner + 2 * self.cell_border

    @property
    def patch_inner(self) -> int:
        """Side of a patch's inner region, pixels."""
        return self.cell_inner * self.cells_per_patch

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
