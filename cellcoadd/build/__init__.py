"""Building cell coadds from exposures: selection, warp, accumulation, PSF, noise."""

from cellcoadd.build.cell import build_cell
from cellcoadd.build.patch import CellBuildError, build_patch

__all__ = ["CellBuildError", "build_cell", "build_patch"]
