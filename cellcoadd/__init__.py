"""cellcoadd: cell-based coadds for weak-lensing shear measurement.

The public API is re-exported here; see ``docs/`` for the tutorial and conventions.
"""

from cellcoadd._version import __version__
from cellcoadd.build import CellBuildError, build_cell, build_patch
from cellcoadd.geometry import (
    Box,
    Cell,
    Patch,
    SkyMap,
    SkyMapConfig,
    Tract,
    flag_unique,
    trim_to_cell,
    trim_to_patch,
)
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.exposure import Exposure, ExposureError
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.plots import plot_patch_layout

__all__ = [
    "Box",
    "BuildConfig",
    "Cell",
    "CellBuildError",
    "Exposure",
    "ExposureError",
    "MaskBits",
    "Patch",
    "SkyMap",
    "SkyMapConfig",
    "Tract",
    "__version__",
    "build_cell",
    "build_patch",
    "flag_unique",
    "plot_patch_layout",
    "trim_to_cell",
    "trim_to_patch",
]
