"""cellcoadd: cell-based coadds for weak-lensing shear measurement.

The public API is re-exported here; see ``docs/`` for the tutorial and conventions.
``cellcoadd.open`` opens a coadd file lazily (it shadows the built-in only inside this
namespace).
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
from cellcoadd.io import (
    CellCoaddFormatError,
    convert,
    open,
    read,
    read_cell,
    read_exposure,
    write,
    write_exposure,
)
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd, CellCoaddError
from cellcoadd.model.exposure import Exposure, ExposureError
from cellcoadd.model.inputs import InputRecord
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.patch_coadd import FORMAT_VERSION, PatchCoadd, PatchMetadata
from cellcoadd.plots import plot_patch_layout
from cellcoadd.shear import (
    EmptyCellError,
    ValidationSettings,
    measure_metacal,
    to_ngmix,
    to_observation,
    validate_shear,
)

__all__ = [
    "FORMAT_VERSION",
    "Box",
    "BuildConfig",
    "Cell",
    "CellBuildError",
    "CellCoadd",
    "CellCoaddError",
    "CellCoaddFormatError",
    "EmptyCellError",
    "Exposure",
    "ExposureError",
    "InputRecord",
    "MaskBits",
    "Patch",
    "PatchCoadd",
    "PatchMetadata",
    "SkyMap",
    "SkyMapConfig",
    "Tract",
    "ValidationSettings",
    "__version__",
    "build_cell",
    "build_patch",
    "convert",
    "flag_unique",
    "measure_metacal",
    "open",
    "plot_patch_layout",
    "read",
    "read_cell",
    "read_exposure",
    "to_ngmix",
    "to_observation",
    "trim_to_cell",
    "trim_to_patch",
    "validate_shear",
    "write",
    "write_exposure",
]
