"""Building cell coadds from exposures: selection, warp, accumulation, PSF, noise."""

from cellcoadd.builder.cell import build_cell
from cellcoadd.builder.patch import PatchStream, build_patch, stream_patch

__all__ = ["PatchStream", "build_cell", "build_patch", "stream_patch"]
