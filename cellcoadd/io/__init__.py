"""Storage: patch coadds in FITS (fitsio) and HDF5 (h5py), exposure files, errors."""

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.io.api import convert, file_format, open, read, read_cell, write
from cellcoadd.io.exposure_io import read_exposure, write_exposure

__all__ = [
    "CellCoaddFormatError",
    "convert",
    "file_format",
    "open",
    "read",
    "read_cell",
    "read_exposure",
    "write",
    "write_exposure",
]
