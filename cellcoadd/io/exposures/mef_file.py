"""An open multi-extension FITS file, as the survey readers use it (headers, HDUs, pixels)."""

from __future__ import annotations

import gzip
import os
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import fitsio
import numpy as np

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.geometry.box import Box
from cellcoadd.io._files.path_gate import gate_read
from cellcoadd.io._files.read_checks import MAX_PLANE_PIXELS, check_declared_plane, header_cards
from cellcoadd.io._fits.headers import read_header
from cellcoadd.io._fits.paths import FITS_MAGIC, starts_like_fits
from cellcoadd.io.exposures.mef_layout import HduRef

#: Most pixels a plane of a survey exposure file may declare (8192 x 8192; an LSST
#: detector is 4072 x 4000, a DECam CCD 4096 x 2048).
MAX_DETECTOR_PIXELS = MAX_PLANE_PIXELS
#: Most bytes a plane may declare per byte it stores (compression ratio; lossless
#: compression of sky images stays far below it, a constant plane reaches ~1000).
MAX_INFLATION = 1100
#: Most bytes a gzip-compressed exposure file (``.fits.gz``) may inflate to: CFITSIO holds
#: the whole inflated file in memory (an LSST or DECam CCD file is 0.1-0.3 GB).
MAX_GZIP_BYTES = 2 << 30
_GZIP_MAGIC = b"\x1f\x8b"
#: FITS block size (bytes); headers are whole blocks of 36 cards.
_BLOCK = 2880
#: Most header blocks an HDU of a gzip stream may have before ``END`` (~36,000 cards).
_MAX_HEADER_BLOCKS = 1000


def check_gzip_stream(path: str, resolved: str) -> int:
    """The inflated size in bytes of a gzip-compressed FITS file; refuses one that is not a
    FITS file, declares a plane too large, or inflates too far.

    The stream is inflated once, 1 MiB at a time (memory bounded), before CFITSIO inflates
    it whole into memory: at most :data:`MAX_INFLATION` times the compressed size and
    :data:`MAX_GZIP_BYTES` bytes. Each HDU's header is checked as it comes out of the
    stream, before its data is inflated: an image (plain, or tile-compressed:
    ``ZNAXISn``) of more than :data:`~cellcoadd.io._files.read_checks.MAX_PLANE_PIXELS`
    pixels is refused at once.

    Raises
    ------
    CellCoaddFormatError
        Naming ``path``: a damaged stream, one that does not hold a FITS file, an HDU that
        declares too large an image (names the HDU, its size and the limit), or a stream
        that inflates beyond the bound.
    """
    limit = min(MAX_INFLATION * os.path.getsize(resolved), MAX_GZIP_BYTES)
    total = 0

    def read(stream: Any, size: int) -> bytes:
        nonlocal total
        chunk = stream.read(size)
        total += len(chunk)
        if total > limit:
            raise CellCoaddFormatError(
                path,
                f"its gzip stream inflates beyond {limit} bytes (at most "
                f"{MAX_INFLATION}:1 and {MAX_GZIP_BYTES} bytes; forged?)",
            )
        return bytes(chunk)

    try:
        with gzip.open(resolved, "rb") as stream:
            first = read(stream, _BLOCK)
            if not first.startswith(FITS_MAGIC):
                raise CellCoaddFormatError(
                    path, "not a FITS file (its gzip stream does not start with SIMPLE)"
                )
            header, hdu = first, 0
            while header:
                # the whole header first (bounded), then its declared data, skipped
                while not _ends_header(header[-_BLOCK:]):
                    block = read(stream, _BLOCK)
                    if len(block) < _BLOCK or len(header) >= _MAX_HEADER_BLOCKS * _BLOCK:
                        header = b""  # truncated or endless: CFITSIO refuses it later
                        break
                    header += block
                if not header:
                    break
                cards = header_cards(header)
                check_declared_plane(path, hdu, cards)
                remaining = _data_blocks(cards) * _BLOCK
                while remaining > 0 and (chunk := read(stream, min(remaining, 1 << 20))):
                    remaining -= len(chunk)
                header, hdu = read(stream, _BLOCK), hdu + 1
            while read(stream, 1 << 20):
                pass  # bytes after the last HDU still count against the bound
    except (OSError, EOFError, zlib.error) as err:
        raise CellCoaddFormatError(path, f"a damaged gzip stream ({err})") from None
    return total


def _ends_header(block: bytes) -> bool:
    """Whether a header block holds the ``END`` card."""
    return any(block[i : i + 80] == _END_CARD for i in range(0, len(block), 80))


_END_CARD = b"END" + b" " * 77


def _data_blocks(cards: dict[str, str]) -> int:
    """FITS blocks of the data unit an HDU's header declares (``|BITPIX| / 8 * GCOUNT *
    (PCOUNT + NAXIS1 * ... * NAXISn)`` bytes, whole blocks); 0 for a header that does not
    say (CFITSIO refuses it later)."""
    try:
        naxis = int(cards.get("NAXIS", "0"))
        size = 1 if naxis > 0 else 0
        for axis in range(1, min(naxis, 999) + 1):
            size *= max(int(cards.get(f"NAXIS{axis}", "0")), 0)
        size += max(int(cards.get("PCOUNT", "0")), 0)
        size *= max(int(cards.get("GCOUNT", "1")), 1) * abs(int(cards.get("BITPIX", "8"))) // 8
    except ValueError:
        return 0
    return -(-size // _BLOCK)


class MefFile:
    """An open multi-extension FITS file: headers read at most once (:func:`read_header`),
    HDUs found by number, EXTNAME or EXTTYPE, boxes of pixels read; errors name the file
    and the HDU."""

    def __init__(
        self, path: str, fits_file: fitsio.FITS, descriptor: int | None, size: int
    ) -> None:
        self.path = path
        self.fits = fits_file
        self.descriptor = descriptor  # the file's own bytes (see io.fits_headers), or None
        self.size = size  # bytes of the FITS content (inflated, for a gzip stream)
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
        stored = max(0, min(int(offsets["data_end"]), self.size) - int(offsets["data_start"]))
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
    inflated: int | None = None  # a gzip stream's size, which CFITSIO holds in memory
    if not starts_like_fits(resolved):
        with open(resolved, "rb") as raw:
            magic = raw.read(len(_GZIP_MAGIC))
        if magic != _GZIP_MAGIC:
            # CFITSIO would also inflate compress and bzip2 streams into memory first
            raise CellCoaddFormatError(path, "not a FITS file (it does not start with SIMPLE)")
        inflated = check_gzip_stream(path, resolved)
    fits_file: Any = None
    descriptor: int | None = None
    try:
        try:
            if inflated is None:  # not inflated by CFITSIO: its bytes are the HDUs
                descriptor = os.open(resolved, os.O_RDONLY)
            fits_file = fitsio.FITS(resolved)
        except (OSError, ValueError) as err:
            raise CellCoaddFormatError(path, f"not a readable FITS file ({err})") from None
        size = inflated if descriptor is None else os.fstat(descriptor).st_size
        yield MefFile(path, fits_file, descriptor, size or 0)
    finally:
        if descriptor is not None:
            os.close(descriptor)
        if fits_file is not None:
            fits_file.close()
