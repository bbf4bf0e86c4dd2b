"""Integrity keywords of the FITS files cellcoadd writes (coadds and exposures).

Every HDU carries the standard CHECKSUM/DATASUM cards and ``DATACRC``, the CRC-32
(``zlib.crc32``, unsigned, as a FITS integer) of its data unit *as stored*: the bytes from
the end of the header to the end of the data unit, fill included. For a tile-compressed
image those are the bytes of the binary table CFITSIO stores (tile descriptors and heap of
compressed tiles), not the decompressed pixels, so checking costs one pass over the
compressed bytes. An HDU without data has ``DATACRC = 0``.

CHECKSUM and DATASUM are sums of 32-bit words: they catch flipped bits but not reordered
words, so two 2880-byte blocks swapped inside one data unit pass them; a CRC depends on
the order. Files written before ``DATACRC`` existed are read without that check. Readers
check all three in one pass over an HDU's bytes (:func:`verify_hdu`), in place of CFITSIO's
own checksum pass, so the CRC adds no read.

Writers add the card with the placeholder value 0 (:data:`DATACRC_PLACEHOLDER`), so the
header has room for it, and :func:`stabilise_fits_checksums` fills in the real value in
place once the file is complete, together with fixed comments on the checksum cards. The
direct writer of uncompressed coadds (:mod:`cellcoadd.io._fits.direct`) computes the same
cards as it writes each HDU, with the same result.
"""

from __future__ import annotations

import mmap
import os
import zlib
from typing import Any, BinaryIO

import fitsio
import numpy as np

from cellcoadd.errors import DamagedDataError
from cellcoadd.io._fits.paths import cfitsio_path

#: Keyword of the CRC-32 of an HDU's data unit as stored.
DATACRC = "DATACRC"
#: The card writers put in every HDU header; :func:`stabilise_fits_checksums` fills it in.
DATACRC_PLACEHOLDER: dict[str, Any] = {
    "name": DATACRC,
    "value": 0,
    "comment": "CRC-32 of the data unit as stored",
}

#: Fixed comments of the FITS checksum cards (CFITSIO writes the current time there).
_CHECKSUM_COMMENTS = {b"CHECKSUM=": b"HDU checksum", b"DATASUM =": b"data unit checksum"}
_CARD = 80
_DATACRC_KEY = b"DATACRC ="
#: Columns 11-30 (0-based 10:30) of the placeholder card hold its integer value.
_VALUE = slice(10, 30)
#: Characters the FITS checksum encoding avoids (ASCII punctuation between digits/letters).
_CHECKSUM_EXCLUDED = frozenset(b":;<=>?@[\\]^_`")
#: Bytes read at a time when checking a data unit (bounds memory for large exposures).
_CHUNK = 1 << 22


def stabilise_fits_checksums(path: str | os.PathLike[str]) -> None:
    """Fill in ``DATACRC`` and give the CHECKSUM/DATASUM cards fixed comments, in every HDU.

    CFITSIO stamps the current time into the comments of the checksum cards, so the same
    data written twice would differ byte-wise. This rewrites each comment and the
    ``DATACRC`` placeholder (in place, headers only) and recomputes CHECKSUM for the new
    header with the standard FITS algorithm (32-bit ones' complement sum, ASCII encoding),
    keeping DATASUM, which covers the unchanged data. Readers verify the result like any
    FITS checksum. Call it once the file is complete: the CRC covers the data as stored.
    """
    with fitsio.FITS(cfitsio_path(path)) as fits:
        offsets = [hdu.get_offsets() for hdu in fits]
    with open(path, "r+b") as stream, mmap.mmap(stream.fileno(), 0) as mapped:
        for extent in offsets:
            start, stop = extent["header_start"], extent["data_start"]
            header = bytearray(mapped[start:stop])
            with memoryview(mapped) as view:
                crc = zlib.crc32(view[stop : extent["data_end"]])
            filled = fill_datacrc(header, crc)
            if stable_checksum_header(header) or filled:
                mapped[start:stop] = header
        mapped.flush()


def verify_hdu(stream: BinaryIO, offsets: dict[str, int]) -> None:
    """Check the CHECKSUM, DATASUM and ``DATACRC`` of one HDU, reading it from ``stream``.

    One pass over the HDU's bytes (``offsets`` are its ``header_start``, ``data_start`` and
    ``data_end``, from fitsio ``get_offsets()``), read here rather than by CFITSIO so the
    CRC costs no second read; no other HDU is read. The checksums follow the FITS
    standard: DATASUM is the 32-bit ones' complement sum of the data unit, and the sum of
    the whole HDU, header included, must be all ones (or zero). An HDU without
    ``DATACRC`` (a file written before it existed) is checked without it.

    Raises
    ------
    ValueError
        When a checksum keyword is missing, a sum or the CRC differs (data changed or
        blocks reordered), or the file ends inside the HDU.
    """
    start, data_start, stop = offsets["header_start"], offsets["data_start"], offsets["data_end"]
    stream.seek(start)
    header = stream.read(data_start - start)
    if len(header) != data_start - start or len(header) % 4:
        raise DamagedDataError("the file ends inside a header")
    datasum_text = _card_value(header, b"DATASUM =")
    if datasum_text is None or _card_value(header, b"CHECKSUM=") is None:
        raise DamagedDataError("checksum keywords CHECKSUM/DATASUM missing")
    crc_text = _card_value(header, _DATACRC_KEY)
    datasum, crc, position = 0, 0, data_start
    while position < stop:
        chunk = stream.read(min(_CHUNK, stop - position))
        if not chunk or len(chunk) % 4:
            raise DamagedDataError("the file ends inside a data unit")
        datasum = ones_complement_sum(chunk, datasum)
        crc = zlib.crc32(chunk, crc)
        position += len(chunk)
    if not datasum_text.strip(b"' ").isdigit() or int(datasum_text.strip(b"' ")) != datasum:
        raise DamagedDataError("data checksum (DATASUM) mismatch: the data unit was changed")
    if ones_complement_sum(header, datasum) not in (0, 0xFFFFFFFF):
        raise DamagedDataError("HDU checksum (CHECKSUM) mismatch: the header was changed")
    if crc_text is None:
        return
    if not crc_text.isdigit() or int(crc_text) > 0xFFFFFFFF:
        raise DamagedDataError(f"{DATACRC} is not a CRC-32 value: {crc_text!r}")
    if crc != int(crc_text):
        raise DamagedDataError(
            f"{DATACRC} mismatch (data unit CRC-32 {crc}, header {int(crc_text)}): "
            "the data were changed or their blocks reordered"
        )


def _card_value(header: bytes, key: bytes) -> bytes | None:
    """The value field (columns 11-80 up to any comment) of the card ``key``, or None."""
    card = find_card(header, key)
    if card < 0:
        return None
    return header[card + 10 : card + _CARD].split(b"/")[0].strip()


def fill_datacrc(header: bytearray, crc: int) -> bool:
    """Write ``crc`` into the DATACRC card of one header; False if it has none."""
    card = find_card(header, _DATACRC_KEY)
    if card < 0:
        return False
    header[card + _VALUE.start : card + _VALUE.stop] = f"{crc:20d}".encode("ascii")
    return True


def find_card(header: bytes | bytearray, key: bytes) -> int:
    """Offset of the card starting with ``key`` (name and ``=``), or -1."""
    offset = header.find(key)
    while offset >= 0 and offset % _CARD:
        offset = header.find(key, offset + 1)
    return offset


def stable_checksum_header(header: bytearray) -> bool:
    """Rewrite the checksum cards of one header in place; False if it has none."""
    cards = {key: find_card(header, key) for key in _CHECKSUM_COMMENTS}
    if min(cards.values()) < 0:
        return False
    for key, offset in cards.items():
        card = bytes(header[offset : offset + _CARD])
        closing = card.index(b"'", 11)  # string values start at column 11
        slash = card.find(b"/", closing)
        value = card[: slash if slash > 0 else closing + 1]
        header[offset : offset + _CARD] = (value + b"/ " + _CHECKSUM_COMMENTS[key]).ljust(_CARD)
    datasum_card = bytes(header[cards[b"DATASUM ="] : cards[b"DATASUM ="] + _CARD])
    datasum = int(datasum_card[11 : datasum_card.index(b"'", 11)].strip() or b"0")
    checksum_value = slice(cards[b"CHECKSUM="] + 11, cards[b"CHECKSUM="] + 27)
    header[checksum_value] = b"0" * 16
    header[checksum_value] = encode_checksum(ones_complement_sum(bytes(header), datasum))
    return True


def ones_complement_sum(data: bytes, initial: int = 0) -> int:
    """32-bit ones' complement sum of big-endian words (FITS checksum convention)."""
    total = int(np.frombuffer(data, dtype=">u4").sum(dtype=np.uint64)) + initial
    while total >> 32:
        total = (total & 0xFFFFFFFF) + (total >> 32)
    return total


def _encoded_byte(byte: int) -> tuple[int, int, int, int]:
    """The four characters that encode one byte of a checksum (FITS checksum standard)."""
    quotient, remainder = byte // 4 + 0x30, byte % 4
    chars = [quotient + remainder, quotient, quotient, quotient]
    # Shift pairs off punctuation; each pair keeps its sum, so the checksum holds.
    while any(c in _CHECKSUM_EXCLUDED for c in chars):
        for first in (0, 2):
            if chars[first] in _CHECKSUM_EXCLUDED or chars[first + 1] in _CHECKSUM_EXCLUDED:
                chars[first] += 1
                chars[first + 1] -= 1
    return chars[0], chars[1], chars[2], chars[3]


_ENCODED_BYTES = [_encoded_byte(byte) for byte in range(256)]


def encode_checksum(total: int) -> bytes:
    """16-character ASCII encoding of the complement of ``total`` (FITS checksum standard)."""
    value = 0xFFFFFFFF - total
    encoded = [0] * 16
    for byte_index in range(4):
        chars = _ENCODED_BYTES[(value >> (24 - 8 * byte_index)) & 0xFF]
        for position in range(4):
            encoded[4 * position + byte_index] = chars[position]
    # The standard rotates the string one character to the right.
    return bytes(encoded[15:] + encoded[:15])
