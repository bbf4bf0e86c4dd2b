"""Uncompressed FITS HDUs written directly, byte for byte as CFITSIO (through fitsio) writes them.

Writing a patch's ~7 HDUs per cell through fitsio costs far more than the bytes: CFITSIO
creates each image HDU with a zero-filled data unit before the pixels overwrite it, every
keyword is a separate update of the header, and ``write_checksum`` reads each data unit
back to sum it, after which :func:`~cellcoadd.io._fits.checksums.stabilise_fits_checksums`
maps the whole file again for ``DATACRC``. Here an HDU is assembled in memory: its header
cards formatted as CFITSIO formats them (:func:`card`), DATASUM summed from the pixels as
they are in memory (the sum of 32-bit words does not depend on byte order), the CRC-32
taken over the big-endian copy that is written, CHECKSUM computed over the finished
header (from the sums of its cards, each card summed once), then the header, data and
fill are written in one pass. :class:`DirectHdus` knows where each cell's HDUs go before
making them (their sizes follow from shapes and card counts), so threads make whole cells
side by side and write each with one ``pwritev`` at its place.

Only what cellcoadd writes is supported: image HDUs of int32, float32 and float64 arrays
and binary tables of int64, float64 and fixed-width byte-string columns, with integer,
float, boolean and short string keywords. Anything else raises
:class:`UnsupportedCard` before the HDU is written, and the caller falls back to CFITSIO.
Tests compare both writers' files byte for byte.
"""

from __future__ import annotations

import io
import math
import os
import re
import struct
import threading
import zlib
from collections.abc import Sequence
from typing import Any, BinaryIO, NamedTuple

import numpy as np

from cellcoadd.io._files.parallel import map_in_threads
from cellcoadd.io._fits.checksums import (
    DATACRC_PLACEHOLDER,
    encode_checksum,
    ones_complement_sum,
)

BLOCK = 2880
#: Buffers per ``writev`` call (POSIX guarantees at least 16; Linux allows 1024).
_IOV_MAX = os.sysconf("SC_IOV_MAX") if hasattr(os, "sysconf") else 16
_CARD = 80
#: Names CFITSIO writes as ordinary 8-character keywords.
_SHORT_NAME = re.compile(r"^[A-Z0-9_-]{1,8}$")
#: Names written with the HIERARCH convention (longer than 8 characters).
_LONG_NAME = re.compile(r"^[A-Z0-9_-]{9,60}$")
#: Keywords fitsio removes from (or CFITSIO manages in) a header: never given here.
_RESERVED = frozenset(
    (
        "SIMPLE",
        "EXTEND",
        "XTENSION",
        "BITPIX",
        "NAXIS",
        "PCOUNT",
        "GCOUNT",
        "THEAP",
        "EXTNAME",
        "TFIELDS",
        "CHECKSUM",
        "DATASUM",
        "BSCALE",
        "BZERO",
        "BLANK",
        "CONTINUE",
        "COMMENT",
        "HISTORY",
        "END",
    )
)
_RESERVED_PREFIXES = ("NAXIS", "TTYPE", "TFORM", "TDIM", "TUNIT", "TNULL", "TSCAL", "TZERO", "Z")
_BITPIX = {("i", 4): 32, ("f", 4): -32, ("f", 8): -64}
_TFORM = {("i", 8): ("K", "8-byte INTEGER"), ("f", 8): ("D", "8-byte DOUBLE")}


class UnsupportedCard(ValueError):
    """Something this writer does not reproduce exactly as CFITSIO would: use CFITSIO."""


def card(name: str, value: Any, comment: str = "") -> bytes:
    """One 80-byte header card, formatted as fitsio's ``write_key`` (CFITSIO) formats it."""
    name = name.upper()
    quoted = False
    if isinstance(value, bool):
        text = "T" if value else "F"
    elif isinstance(value, (int, np.integer)) and not isinstance(value, np.bool_):
        text = str(int(value))
    elif isinstance(value, (float, np.floating)):
        text = _double(float(value))
    elif isinstance(value, str):
        text, quoted = _quoted(value), True
    else:
        raise UnsupportedCard(f"{name}: value of type {type(value).__name__}")
    if _SHORT_NAME.match(name):
        prefix = f"{name:<8}= "
    elif _LONG_NAME.match(name) and not quoted:
        prefix = f"HIERARCH {name} = "
    else:
        raise UnsupportedCard(f"keyword name {name!r}")
    if quoted:
        body = (prefix + text).ljust(30)
    else:
        body = prefix + text.rjust(max(0, 30 - len(prefix)))
    if comment:
        body = f"{body} / {comment}"
    if len(body) > _CARD or not body.isascii() or not body.isprintable():
        raise UnsupportedCard(f"{name}: the card does not fit in 80 printable characters")
    return body.ljust(_CARD).encode("ascii")


def _double(value: float) -> str:
    # CFITSIO ffd2e with decimals = -15 (fitsio's write_double_key)
    if not math.isfinite(value):
        raise UnsupportedCard(f"non-finite value {value}")
    text = f"{value:.15G}"
    if "." not in text:
        text = f"{value:.1E}" if "E" in text else text + "."
    return text


def _quoted(value: str) -> str:
    # CFITSIO ffs2c: quotes doubled, padded with blanks to at least 8 characters
    text = value.replace("'", "''")
    if len(text) > 68 or value.endswith(" "):
        raise UnsupportedCard(f"string value {value!r}")
    return "'" + text.ljust(8) + "'"


#: Cards already formatted, by (name, value type, repr of the value, comment): a patch's
#: HDUs repeat most of their cards. ``repr`` tells -0.0 from 0.0, the type 1 from 1.0.
_CARDS: dict[tuple[str, type, str, str], bytes] = {}
_MAX_CARDS = 1 << 16


def check_keys(keys: list[dict[str, Any]]) -> list[bytes]:
    """The cards of ``keys`` (``name``, ``value``, optional ``comment`` dicts, as for fitsio's
    ``write_keys``), refusing names fitsio would drop, merge or treat specially."""
    cards = []
    seen: set[str] = set()
    for key in keys:
        name = str(key["name"]).upper()
        if name in seen or name in _RESERVED or name.startswith(_RESERVED_PREFIXES):
            raise UnsupportedCard(f"keyword {name}")
        seen.add(name)
        cards.append(_card(name, key["value"], key.get("comment") or ""))
    return cards


def _card(name: str, value: Any, comment: str = "") -> bytes:
    """:func:`card`, remembered."""
    memo = (name, type(value), repr(value), comment)
    text = _CARDS.get(memo)
    if text is None:
        text = card(name, value, comment)
        if len(_CARDS) >= _MAX_CARDS:
            _CARDS.clear()
        _CARDS[memo] = text
    return text


def _padding(size: int) -> int:
    return -size % BLOCK


def _finish_header(cards: list[bytes], datasum: int) -> bytes:
    """Header bytes: ``cards``, CHECKSUM and DATASUM (fixed comments, as
    :func:`~cellcoadd.io._fits.checksums.stabilise_fits_checksums` leaves them), END, fill.

    The header's ones' complement sum is the sum of its cards' sums (a card is 20 whole
    32-bit words), each summed once per distinct card, and of the blank fill.
    """
    # CFITSIO's initial value stays when the sum is zero
    datasum_card = _card("DATASUM", str(datasum) if datasum else "         0", "data unit checksum")
    zero_card = _card("CHECKSUM", "0" * 16, "HDU checksum")
    every = [*cards, zero_card, datasum_card, _END_CARD]
    body = b"".join(every)
    fill = _padding(len(body))
    total = datasum + sum(map(_card_sum, every)) + (fill // 4) * _BLANK_WORD
    value = len(body) - 3 * _CARD + 11  # the 16 characters of CHECKSUM's value
    checksum = encode_checksum(_fold(total))
    return body[:value] + checksum + body[value + 16 :] + b" " * fill


#: Sums of the 20 big-endian 32-bit words of cards already summed.
_CARD_SUMS: dict[bytes, int] = {}
_CARD_WORDS = struct.Struct(">20I")
_BLANK_WORD = 0x20202020
_END_CARD = b"END".ljust(_CARD)


def _card_sum(card_bytes: bytes) -> int:
    total = _CARD_SUMS.get(card_bytes)
    if total is None:
        total = sum(_CARD_WORDS.unpack(card_bytes))
        if len(_CARD_SUMS) >= _MAX_CARDS:
            _CARD_SUMS.clear()
        _CARD_SUMS[card_bytes] = total
    return total


def _fold(total: int) -> int:
    while total >> 32:
        total = (total & 0xFFFFFFFF) + (total >> 32)
    return total


def write_image(
    stream: BinaryIO,
    data: np.ndarray,
    extname: str,
    keys: list[dict[str, Any]],
    scratch: Scratch | None = None,
) -> None:
    """Append an image HDU named ``extname`` holding ``data`` with ``keys`` (the last of which
    is the ``DATACRC`` placeholder, given its value here) to ``stream``; ``scratch`` is
    reused for the big-endian copy of the data."""
    write_parts(stream, image_hdu(data, extname, keys, scratch))


def write_table(
    stream: BinaryIO, table: np.ndarray, extname: str, keys: list[dict[str, Any]]
) -> None:
    """Append a binary table HDU of the packed structured array ``table`` (as fitsio writes it)."""
    write_parts(stream, table_hdu(table, extname, keys))


def write_parts(
    stream: BinaryIO, parts: Sequence[bytes | memoryview], offset: int | None = None
) -> None:
    """Write ``parts`` (headers, data and fills of HDUs from :func:`image_hdu` /
    :func:`table_hdu`) one after the other.

    ``offset`` None: at the current position, with one ``writev`` call when ``stream`` is an
    unbuffered file, else one ``write`` each. Otherwise at byte ``offset`` of the file
    (``pwritev``, where it exists: safe from several threads; the position is unchanged).
    """
    if offset is None and (not isinstance(stream, io.FileIO) or not hasattr(os, "writev")):
        for part in parts:
            stream.write(part)
        return
    views = [memoryview(part).cast("B") for part in parts if len(part)]
    while views:
        if offset is None:
            written = os.writev(stream.fileno(), views[:_IOV_MAX])
        else:
            written = os.pwritev(stream.fileno(), views[:_IOV_MAX], offset)
            offset += written
        while views and written >= len(views[0]):
            written -= len(views.pop(0))
        if views and written:
            views[0] = views[0][written:]


class Scratch:
    """A buffer reused for the big-endian copies of successive planes: a fresh array per
    plane costs a page fault per 4 kB, more than swapping the bytes."""

    def __init__(self) -> None:
        self._buffer = np.empty(0, dtype=np.uint8)

    def big_endian(self, data: np.ndarray) -> memoryview:
        """The bytes of native-order ``data`` in big-endian order (valid until the next call)."""
        if self._buffer.size < data.nbytes:
            self._buffer = np.empty(max(data.nbytes, 2 * self._buffer.size), dtype=np.uint8)
        words = data.reshape(-1).view(f"u{data.dtype.itemsize}")
        out = self._buffer[: data.nbytes].view(words.dtype.newbyteorder(">"))
        out[...] = words  # a cast between byte orders: bits swapped, never changed
        return self._buffer[: data.nbytes].data


class ImageData(NamedTuple):
    """The data unit of an image HDU as stored, with its sums (:func:`image_data`)."""

    #: BITPIX of the stored values.
    bitpix: int
    #: Array shape (C order; NAXISn are its reverse).
    shape: tuple[int, ...]
    #: Big-endian bytes of the values (the caller's scratch buffer).
    stored: memoryview
    #: Zero bytes completing the last 2880-byte block.
    fill: bytes
    #: 32-bit ones' complement sum of the data unit (DATASUM).
    datasum: int
    #: CRC-32 of the data unit, fill included (``DATACRC``).
    crc: int


def image_data(data: np.ndarray, scratch: Scratch | None = None) -> ImageData:
    """The stored bytes and the sums of an image HDU holding ``data``.

    Only numpy and ``zlib`` work here (both release the GIL): safe in a worker thread, as
    long as ``scratch`` is not used elsewhere until the bytes are written. DATASUM is summed
    from the pixels as they are in memory (the 32-bit words of a native array are the
    big-endian words of the file, in another order), the CRC-32 over the big-endian copy.
    """
    data = np.ascontiguousarray(data)
    if not data.dtype.isnative:  # the same values in native order (bits kept)
        data = data.byteswap().view(data.dtype.newbyteorder())
    if data.ndim and not data.size:  # no pixels: NAXIS = 0, as CFITSIO writes it
        return ImageData(16, (), memoryview(b""), b"", 0, 0)
    bitpix = _BITPIX.get((data.dtype.kind, data.dtype.itemsize))
    if bitpix is None or data.ndim == 0:
        raise UnsupportedCard(f"image of {data.dtype} {data.shape}")
    words = data.reshape(-1).view(np.uint32)  # the same 32-bit words in any byte order
    datasum = _fold(int(np.add.reduce(words, dtype=np.uint64)))
    stored = (scratch or Scratch()).big_endian(data)
    fill = bytes(_padding(len(stored)))
    crc = zlib.crc32(fill, zlib.crc32(stored))
    return ImageData(bitpix, data.shape, stored, fill, datasum, crc)


def image_header(image: ImageData, extname: str, keys: list[dict[str, Any]]) -> bytes:
    """Header of the image HDU of :func:`image_data` (``keys`` end with the DATACRC
    placeholder, given its value here; CHECKSUM covers header and data)."""
    cards = [
        _card("XTENSION", "IMAGE", "IMAGE extension"),
        _card("BITPIX", image.bitpix, "number of bits per data pixel"),
        _card("NAXIS", len(image.shape), "number of data axes"),
        *(
            _card(f"NAXIS{axis + 1}", length, "length of data axis " + str(axis + 1))
            for axis, length in enumerate(reversed(image.shape))
        ),
        _card("PCOUNT", 0, "required keyword; must = 0"),
        _card("GCOUNT", 1, "required keyword; must = 1"),
        _card("EXTNAME", extname),
    ]
    return _header(cards, keys, image.datasum, image.crc)


def image_hdu(
    data: np.ndarray, extname: str, keys: list[dict[str, Any]], scratch: Scratch | None = None
) -> tuple[bytes, memoryview, bytes]:
    """Header, data as stored and fill of an image HDU (see :func:`write_image`)."""
    image = image_data(data, scratch)
    return image_header(image, extname, keys), image.stored, image.fill


def table_hdu(
    table: np.ndarray, extname: str, keys: list[dict[str, Any]]
) -> tuple[bytes, memoryview, bytes]:
    """Header, data as stored and fill of a binary table HDU (see :func:`write_table`)."""
    dtype = table.dtype
    fields = dtype.fields
    if dtype.names is None or fields is None or table.ndim != 1:
        raise UnsupportedCard("not a structured 1-d array")
    cards = [
        _card("XTENSION", "BINTABLE", "binary table extension"),
        _card("BITPIX", 8, "8-bit bytes"),
        _card("NAXIS", 2, "2-dimensional binary table"),
        _card("NAXIS1", dtype.itemsize, "width of table in bytes"),
        _card("NAXIS2", len(table), "number of rows in table"),
        _card("PCOUNT", 0, "size of special data area"),
        _card("GCOUNT", 1, "one data group (required keyword)"),
        _card("TFIELDS", len(dtype.names), "number of fields in each row"),
    ]
    offset = 0
    big = []
    for number, name in enumerate(dtype.names, start=1):
        field, field_offset = fields[name][:2]
        if field_offset != offset or field.shape != ():
            raise UnsupportedCard(f"column {name}: not packed or not scalar")
        if field.kind == "S":
            form, meaning = f"{field.itemsize}A", "ASCII Character"
        elif (field.kind, field.itemsize) in _TFORM:
            form, meaning = _TFORM[(field.kind, field.itemsize)]
        else:
            raise UnsupportedCard(f"column {name} of {field}")
        cards.append(_card(f"TTYPE{number}", name, f"label for field {number:3d}"))
        cards.append(_card(f"TFORM{number}", form, "data format of field: " + meaning))
        big.append((name, field.newbyteorder(">") if field.kind != "S" else field))
        offset += field.itemsize
    if offset != dtype.itemsize:
        raise UnsupportedCard("table rows are not packed")
    cards.append(_card("EXTNAME", extname, "name of this binary table extension"))
    stored = np.ascontiguousarray(table.astype(np.dtype(big)))
    raw = stored.view(np.uint8).reshape(-1)
    fill = bytes(_padding(len(raw)))
    datasum = ones_complement_sum(raw.tobytes() + fill)
    crc = zlib.crc32(fill, zlib.crc32(raw.data))
    return _header(cards, keys, datasum, crc), raw.data, fill


def _header(cards: list[bytes], keys: list[dict[str, Any]], datasum: int, crc: int) -> bytes:
    """The finished header: ``cards``, then ``keys`` with the DATACRC placeholder (their last)
    given the value ``crc``, the checksum cards and END."""
    if not keys or keys[-1]["name"] != "DATACRC":
        raise UnsupportedCard("the last keyword must be the DATACRC placeholder")
    filled = [*keys[:-1], {**keys[-1], "value": crc}]
    return _finish_header([*cards, *check_keys(filled)], datasum)


#: An HDU queued for :class:`DirectHdus`: image or table, its array, EXTNAME and keys.
_QueuedHdu = tuple[bool, np.ndarray, str, list[dict[str, Any]]]


class DirectHdus:
    """Uncompressed cell HDUs, given in order, then written after ``start`` by
    :meth:`write`: the bytes of writing them one after the other, in less time.

    A cell's HDUs end with its table (its inputs), so each table closes a cell. Every
    HDU's size follows from its shape and number of cards (values do not change a card's
    80 bytes), so each cell's place in the file is known before its bytes are made; the
    threads of :func:`~cellcoadd.io._files.parallel.map_in_threads` then each take whole cells,
    prepare them (big-endian copy, DATASUM, CRC-32, headers) and write them in place
    (``pwritev``). numpy, ``zlib`` and the writes release the GIL, and a thread's data stay
    in its core's cache.
    """

    def __init__(self) -> None:
        self._cells: list[list[_QueuedHdu]] = []
        self._cell: list[_QueuedHdu] = []

    def image(self, plane: str, data: np.ndarray, name: str, keys: list[dict[str, Any]]) -> None:
        self._cell.append((True, data, name, [*keys, DATACRC_PLACEHOLDER]))

    def table(self, table: np.ndarray, name: str, keys: list[dict[str, Any]]) -> None:
        self._cell.append((False, table, name, [*keys, DATACRC_PLACEHOLDER]))
        self._cells.append(self._cell)
        self._cell = []

    def write(self, stream: BinaryIO, start: int) -> int:
        """Write every HDU given from byte ``start`` of ``stream`` (an unbuffered file);
        returns the offset after the last one. Raises :class:`UnsupportedCard` (nothing
        usable written) for what only CFITSIO writes exactly."""
        cells = [*self._cells, self._cell] if self._cell else self._cells
        offsets = [start]
        for hdus in cells:
            offsets.append(offsets[-1] + sum(_hdu_size(hdu) for hdu in hdus))
        if not hasattr(os, "pwritev"):  # one after the other, in this thread
            stream.seek(start)
            scratches: list[Scratch] = []
            for hdus, offset in zip(cells, offsets, strict=False):
                _write_cell_hdus(stream, hdus, offset, scratches, positional=False)
            return offsets[-1]
        local = threading.local()

        def write_cell(number: int) -> None:
            if not hasattr(local, "scratches"):
                local.scratches = []  # big-endian buffers, reused by each thread
            _write_cell_hdus(
                stream, cells[number], offsets[number], local.scratches, positional=True
            )

        map_in_threads(write_cell, range(len(cells)))
        return offsets[-1]


def _hdu_size(hdu: _QueuedHdu) -> int:
    """Bytes of an HDU written by :func:`image_header`/:func:`table_hdu`: header cards
    (the type's own, the keys, CHECKSUM, DATASUM, END) and data, each filled to blocks."""
    is_image, array, _, keys = hdu
    if is_image:  # XTENSION BITPIX NAXIS NAXISn PCOUNT GCOUNT EXTNAME (no pixels: NAXIS 0)
        own = 6 + (array.ndim if array.size else 0)
    else:
        own = 9 + 2 * len(array.dtype.names or ())  # and TFIELDS, TTYPEn, TFORMn
    header = (own + len(keys) + 3) * _CARD
    return header + _padding(header) + array.nbytes + _padding(array.nbytes)


def _write_cell_hdus(
    stream: BinaryIO,
    hdus: list[_QueuedHdu],
    offset: int,
    scratches: list[Scratch],
    *,
    positional: bool,
) -> None:
    """Make and write the HDUs of one cell, at ``offset`` (``positional``) or at the
    stream's position (which must be ``offset``)."""
    parts: list[bytes | memoryview] = []
    for number, (is_image, array, name, keys) in enumerate(hdus):
        if is_image:
            if number == len(scratches):
                scratches.append(Scratch())
            image = image_data(array, scratches[number])
            parts += (image_header(image, name, keys), image.stored, image.fill)
        else:
            parts += table_hdu(array, name, keys)
    size, planned = sum(len(part) for part in parts), sum(_hdu_size(hdu) for hdu in hdus)
    if size != planned:  # never seen: the place of every later cell would be wrong
        raise UnsupportedCard(f"a cell's HDUs take {size} bytes, {planned} were planned")
    write_parts(stream, parts, offset if positional else None)
