"""What a cell shares with its patch (Rubin's "common components"), so that a cell read
alone, or taken from a patch, describes itself: its pixel unit and zero point, band, mask-bit
names, and the tract, patch and sky map it belongs to (its own index and WCS are the
cell's)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.units import PixelUnit


class CellCommon(BaseModel):
    """The patch-level description every cell of a patch carries (frozen).

    Parameters
    ----------
    units : "nJy" or "count"
        Unit of the image and noise planes (the variance is in its square).
    zero_point : float
        AB zero point of the pixel values, mag (31.4 for nJy).
    band : str
        Filter name.
    mask_bits : MaskBits
        Names of the mask bits.
    tract : int
        Tract number.
    patch : (int, int)
        Patch index ``(px, py)`` in the tract.
    skymap : str or None
        Name of the sky map (``SkyMapConfig.name``, e.g. ``"lsst_cells_v1"``), if it has one.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    units: PixelUnit
    zero_point: float
    band: str
    mask_bits: MaskBits = Field(default_factory=MaskBits)
    tract: int = Field(ge=0)
    patch: tuple[int, int]
    skymap: str | None = None

    @property
    def unit(self) -> Any:
        """:attr:`units` as an ``astropy.units.Unit``."""
        import astropy.units as u

        return u.Unit(self.units)
