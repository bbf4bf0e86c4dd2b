"""An open multi-extension FITS file, as the survey readers use it (headers, HDUs, pixels)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import fitsio
import numpy as np

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.geometry.box import Box
from cellcoadd.io._files.path_gate import gate_read
from cellcoadd.io._fits.headers import read_header
from cellcoadd.io._fits.paths import starts_like_fits
from cellcoadd.io.exposures.mef_layout import HduRef

#: Most pixels a plane of a survey exposure file may declare (8192 x 8192; an LSST
#: detector is 4072 x 4000, a DECam CCD 4096 x 2048).
MAX_DETECTOR_PIXELS = 8192 * 8192
#: Most bytes a plane may declare per byte it stores (compression ratio; lossless
#: compression of sky images stays far below it, a constant plane reaches ~1000).
MAX_INFLATION = 1100


class MefFile:
    """An open multi-extension FITS file: headers read at most once (:func:`read_header`),
    HDUs found by number, EXTNAME or EXTTYPE, boxes of pixels read; errors name the file
    and the HDU."""

    def __init__(self, path: str, fits_file: fitsio.FITS, descriptor: int | None):
        self.path = path
        self.fits = fits_file
        self.descriptor = descriptor  # the file's own bytes (see io.fits_headers), or None
        self._cache: dict[int, fitsio.FITSHDR] = {}

    def fail(self, index: int | None, problem: str) -> CellCoaddFormatError:
        where = f"HDU {self.label(index)}: " if index is not None else ""
        return CellCoaddFormatError(self.path, where + problem)

    def label(self, index: int) -> str:
        try:
            name = self.fits[index].get_extname()
        except (OSError, ValueError):  # a damaged header: the number alone
            return str(index)
        return f"{index} ({name})" if name else str(index)

    def header(self, index: int) -> fitsio.FITSHDR:
        if index not in self._cache:
            try:
                self._cache[index] = read_header(self.fits[index], self.descriptor)
            except (OSError, ValueError) as err:  # ValueError: e.g. bytes that are not ASCII
                raise self.fail(index, f"cannot read the header ({err})") from None
        return self._cache[index]

    def index(self, ref: HduRef, what: str) -> int:
        """HDU number of ``ref``: a number, an EXTNAME, else an EXTTYPE (no case)."""
        try:  # fitsio lists the HDUs when first asked
            count = len(self.fits)
            names = [self.fits[i].get_extname().strip().upper() for i in range(count)]
        except (OSError, ValueError) as err:
            raise CellCoaddFormatError(self.path, f"cannot read the HDUs ({err})") from None
        if isinstance(ref, int):
            if 0 <= ref < count:
                return ref
        else:
            wanted = ref.strip().upper()
            if wanted in names:
                return names.index(wanted)
            for i in range(count):
                if str(self.header(i).get("EXTTYPE", "")).strip().upper() == wanted:
                    return i
        names = [self.label(i) for i in range(count)]
        raise CellCoaddFormatError(self.path, f"no {what} HDU {ref!r} (HDUs: {names})")

    def dims(self, index: int, what: str) -> tuple[int, int]:
        """The plane's (ny, nx), checked against the file before any pixel is read."""
        dims: tuple[int, ...] = tuple(int(d) for d in self.fits[index].get_dims())
        if self.fits[index].get_exttype() != "IMAGE_HDU" or len(dims) != 2 or 0 in dims:
            raise self.fail(index, f"the {what} is not a 2-D image (dimensions {dims})")
        self._check_declared_size(index, what, dims)
        return (dims[0], dims[1])

    def _check_declared_size(self, index: int, what: str, dims: tuple[int, ...]) -> None:
        """CFITSIO allocates what a header declares (a tile-compressed plane is inflated
        whole on a full read): bound it by :data:`MAX_DETECTOR_PIXELS` and by
        :data:`MAX_INFLATION` times the bytes the HDU stores."""
        pixels = int(np.prod(dims, dtype=np.float64))
        if pixels > MAX_DETECTOR_PIXELS:
            raise self.fail(
                index,
                f"the {what} declares {dims[1]} x {dims[0]} pixels, more than the "
                f"{MAX_DETECTOR_PIXELS} of a detector image accepted",
            )
        header = self.header(index)
        bitpix = header.get("ZBITPIX", header.get("BITPIX", 8))
        if isinstance(bitpix, bool) or not isinstance(bitpix, int) or bitpix == 0:
            raise self.fail(index, f"the {what} has BITPIX {bitpix!r}")
        declared = pixels * abs(bitpix) // 8
        offsets = self.fits[index].get_offsets()
        size = os.fstat(self.descriptor).st_size if self.descriptor is not None else 0
        stored = max(0, min(int(offsets["data_end"]), size) - int(offsets["data_start"]))
        if declared > MAX_INFLATION * stored + 2880:
            raise self.fail(
                index,
                f"the {what} declares {dims[1]} x {dims[0]} pixels ({declared} bytes) but "
                f"stores {stored} bytes (more than {MAX_INFLATION}:1; truncated or forged?)",
            )

    def pixels(self, index: int, box: Box, what: str) -> np.ndarray:
        try:
            data = self.fits[index][box.y_start : box.y_stop, box.x_start : box.x_stop]
        except (OSError, ValueError) as err:
            raise self.fail(index, f"cannot read the {what} pixels ({err})") from None
        data = np.asarray(data)
        if not data.dtype.isnative:
            data = data.astype(data.dtype.newbyteorder("="))
        return data


@contextmanager
def open_mef(path: str) -> Iterator[MefFile]:
    """``with open_mef(path) as mef``: the :class:`MefFile` of ``path``, open for the block.

    ``path`` passes the path gate (:mod:`cellcoadd.io._files.path_gate`) and must start
    like a FITS file before CFITSIO opens it.

    Raises
    ------
    CellCoaddFormatError
        When ``path`` is not a file or not a readable FITS file.
    """
    try:
        resolved = gate_read(path, what="exposure file", fits=True)
    except FileNotFoundError:
        raise CellCoaddFormatError(path, "no such file") from None
    if not starts_like_fits(resolved):
        # CFITSIO would inflate a gzip (or compress, bzip2) stream into memory first
        raise CellCoaddFormatError(path, "not a FITS file (it does not start with SIMPLE)")
    fits_file: Any = None
    descriptor: int | None = None
    try:
        try:
            descriptor = os.open(resolved, os.O_RDONLY)
            fits_file = fitsio.FITS(resolved)
        except (OSError, ValueError) as err:
            raise CellCoaddFormatError(path, f"not a readable FITS file ({err})") from None
        yield MefFile(path, fits_file, descriptor)
    finally:
        if descriptor is not None:
            os.close(descriptor)
        if fits_file is not None:
            fits_file.close()
