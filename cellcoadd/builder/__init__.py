"""Building cell coadds from exposures: selection, warp, accumulation, PSF, noise."""

from cellcoadd.builder.cell import build_cell
from cellcoadd.builder.patch import build_patch

__all__ = ["build_cell", "build_patch"]
