"""cellcoadd: cell-based coadds for weak-lensing shear measurement.

The public API is re-exported here lazily: ``import cellcoadd`` loads no numba, GalSim,
matplotlib or dask; each name is imported from its home module on first use (see
``docs/`` for the tutorial and conventions). ``cellcoadd.open`` opens a coadd file lazily
(it shadows the built-in only inside this namespace).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from cellcoadd._lazy import lazy_exports
from cellcoadd._version import __version__

#: public name -> module that defines it
_EXPORTS: dict[str, str] = {
    "Box": "cellcoadd.geometry",
    "Cell": "cellcoadd.geometry",
    "Patch": "cellcoadd.geometry",
    "SkyMap": "cellcoadd.geometry",
    "SkyMapConfig": "cellcoadd.geometry",
    "Tract": "cellcoadd.geometry",
    "flag_unique": "cellcoadd.geometry",
    "trim_to_cell": "cellcoadd.geometry",
    "trim_to_patch": "cellcoadd.geometry",
    "CellCoaddError": "cellcoadd.errors",
    "CellCoaddFormatError": "cellcoadd.errors",
    "CellBuildError": "cellcoadd.errors",
    "ExposureError": "cellcoadd.errors",
    "EmptyCellError": "cellcoadd.errors",
    "BuildConfig": "cellcoadd.model.build_config",
    "CellCoadd": "cellcoadd.model.cell_coadd",
    "Exposure": "cellcoadd.model.exposure",
    "InputRecord": "cellcoadd.model.inputs",
    "InputStatus": "cellcoadd.model.inputs",
    "MaskBits": "cellcoadd.model.maskbits",
    "PsfModel": "cellcoadd.model.psf",
    "GalSimPsf": "cellcoadd.model.psf",
    "ImagePsf": "cellcoadd.model.psf",
    "CallablePsf": "cellcoadd.model.psf",
    "PsfexPsf": "cellcoadd.model.psf",
    "PiffPsf": "cellcoadd.model.psf",
    "PsfError": "cellcoadd.errors",
    "InputError": "cellcoadd.errors",
    "ConfigError": "cellcoadd.errors",
    "FORMAT_VERSION": "cellcoadd.model.patch_coadd",
    "PatchCoadd": "cellcoadd.model.patch_coadd",
    "PatchMetadata": "cellcoadd.model.patch_coadd",
    "convert": "cellcoadd.io",
    "open": "cellcoadd.io",
    "read": "cellcoadd.io",
    "read_cell": "cellcoadd.io",
    "read_exposure": "cellcoadd.io",
    "write": "cellcoadd.io",
    "write_exposure": "cellcoadd.io",
    "read_lsst_exposure": "cellcoadd.io",
    "read_des_exposure": "cellcoadd.io",
    "read_mef_exposure": "cellcoadd.io",
    "ExposureFile": "cellcoadd.io",
    "MefExposureFile": "cellcoadd.io",
    "MefLayout": "cellcoadd.io",
    "to_lsst_images": "cellcoadd.io.foreign.lsst_images",
    "from_lsst_images": "cellcoadd.io.foreign.lsst_images",
    "ExposureSource": "cellcoadd.model.sources",
    "build_cell": "cellcoadd.builder",
    "build_patch": "cellcoadd.builder",
    "measure_metacal": "cellcoadd.shear",
    "to_ngmix": "cellcoadd.shear",
    "to_observation": "cellcoadd.shear",
    "ValidationSettings": "cellcoadd.pipelines",
    "validate_shear": "cellcoadd.pipelines",
    "plot_patch_layout": "cellcoadd.plots",
}

__all__ = [
    "Box",
    "BuildConfig",
    "CallablePsf",
    "Cell",
    "CellBuildError",
    "CellCoadd",
    "CellCoaddError",
    "CellCoaddFormatError",
    "ConfigError",
    "EmptyCellError",
    "Exposure",
    "ExposureError",
    "ExposureFile",
    "ExposureSource",
    "FORMAT_VERSION",
    "GalSimPsf",
    "ImagePsf",
    "InputError",
    "InputRecord",
    "InputStatus",
    "MaskBits",
    "MefExposureFile",
    "MefLayout",
    "Patch",
    "PatchCoadd",
    "PatchMetadata",
    "PiffPsf",
    "PsfError",
    "PsfModel",
    "PsfexPsf",
    "SkyMap",
    "SkyMapConfig",
    "Tract",
    "ValidationSettings",
    "__version__",
    "build_cell",
    "build_patch",
    "convert",
    "flag_unique",
    "from_lsst_images",
    "measure_metacal",
    "open",
    "plot_patch_layout",
    "read",
    "read_cell",
    "read_des_exposure",
    "read_exposure",
    "read_lsst_exposure",
    "read_mef_exposure",
    "to_lsst_images",
    "to_ngmix",
    "to_observation",
    "trim_to_cell",
    "trim_to_patch",
    "validate_shear",
    "write",
    "write_exposure",
]


#: sub-packages reachable as attributes after ``import cellcoadd`` (``cellcoadd.io``)
_SUBPACKAGES = (
    "analysis",
    "builder",
    "errors",
    "geometry",
    "io",
    "model",
    "pipelines",
    "plots",
    "shear",
    "sim",
)

__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS, _SUBPACKAGES)


if TYPE_CHECKING:  # the same names, for type checkers and IDEs
    from cellcoadd.builder import build_cell, build_patch
    from cellcoadd.errors import (
        CellBuildError,
        CellCoaddError,
        CellCoaddFormatError,
        ConfigError,
        EmptyCellError,
        ExposureError,
        InputError,
        PsfError,
    )
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
        ExposureFile,
        MefExposureFile,
        MefLayout,
        convert,
        open,
        read,
        read_cell,
        read_des_exposure,
        read_exposure,
        read_lsst_exposure,
        read_mef_exposure,
        write,
        write_exposure,
    )
    from cellcoadd.io.foreign.lsst_images import from_lsst_images, to_lsst_images
    from cellcoadd.model.build_config import BuildConfig
    from cellcoadd.model.cell_coadd import CellCoadd
    from cellcoadd.model.exposure import Exposure
    from cellcoadd.model.inputs import InputRecord, InputStatus
    from cellcoadd.model.maskbits import MaskBits
    from cellcoadd.model.patch_coadd import FORMAT_VERSION, PatchCoadd, PatchMetadata
    from cellcoadd.model.psf import (
        CallablePsf,
        GalSimPsf,
        ImagePsf,
        PiffPsf,
        PsfexPsf,
        PsfModel,
    )
    from cellcoadd.model.sources import ExposureSource
    from cellcoadd.pipelines import ValidationSettings, validate_shear
    from cellcoadd.plots import plot_patch_layout
    from cellcoadd.shear import measure_metacal, to_ngmix, to_observation
