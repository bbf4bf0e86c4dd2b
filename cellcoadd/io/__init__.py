"""Storage: patch coadds in FITS (fitsio) and HDF5 (h5py), exposure files, errors."""

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.io.api import convert, file_format, open, read, read_cell, write
from cellcoadd.io.exposures.exposure_io import read_exposure, read_exposure_header, write_exposure
from cellcoadd.io.exposures.exposure_source import ExposureFile
from cellcoadd.io.exposures.manifest_io import (
    read_build_config,
    read_manifest,
    sources_from_manifest,
)
from cellcoadd.io.exposures.mef_layout import (
    DES_BAD_MASK_BITS,
    DES_LAYOUT,
    DES_MASK_VALUES,
    LSST_BAD_MASK_BITS,
    LSST_LAYOUT,
    MefLayout,
    ZeroPointKey,
)
from cellcoadd.io.exposures.psf_files import read_piff, read_psf_file, read_psfex
from cellcoadd.io.exposures.survey_readers import (
    MefExposureFile,
    read_des_exposure,
    read_lsst_exposure,
    read_mef_exposure,
)

__all__ = [
    "CellCoaddFormatError",
    "DES_BAD_MASK_BITS",
    "DES_LAYOUT",
    "DES_MASK_VALUES",
    "ExposureFile",
    "LSST_BAD_MASK_BITS",
    "LSST_LAYOUT",
    "MefExposureFile",
    "MefLayout",
    "ZeroPointKey",
    "convert",
    "file_format",
    "open",
    "read",
    "read_cell",
    "read_des_exposure",
    "read_build_config",
    "read_exposure",
    "read_exposure_header",
    "read_lsst_exposure",
    "read_manifest",
    "read_mef_exposure",
    "read_piff",
    "read_psf_file",
    "read_psfex",
    "sources_from_manifest",
    "write",
    "write_exposure",
]
