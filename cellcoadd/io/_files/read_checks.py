"""Guards of every patch-file read: the path must be a non-empty regular file, and a
failure that a damaged, truncated or foreign file can cause becomes a
:class:`~cellcoadd.errors.CellCoaddFormatError` naming it. A programming error (an
``AttributeError``, a ``NameError``, a ``TypeError`` raised by our own code, ...) is not a
damaged file: it passes through unchanged."""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from astropy.io.fits.verify import VerifyError

from cellcoadd.errors import CellCoaddError, CellCoaddFormatError
from cellcoadd.io._files.path_gate import gate_read
from cellcoadd.io._fits.cfitsio_messages import clear_cfitsio_messages

#: What the libraries under a reader (fitsio/CFITSIO, h5py/HDF5, numpy, json, astropy,
#: pydantic) raise on bytes they cannot use, and our own checks: always a file failure.
FILE_FAILURES: tuple[type[BaseException], ...] = (
    CellCoaddError,  # our checks: DamagedDataError, a read cell that is not a valid coadd
    OSError,  # CFITSIO errors (fitsio), HDF5 file and I/O errors (h5py), short reads
    EOFError,
    ValueError,  # bytes that do not parse: UTF-8, JSON, pydantic validation, numpy shapes
    KeyError,  # a missing header keyword, HDF5 object (h5py) or JSON member
    IndexError,  # a missing HDU, row or column
    OverflowError,  # a stored number too large for its type
    struct.error,
    zlib.error,
    VerifyError,  # a header card astropy cannot parse (e.g. an unquoted string value)
)

#: Raised by a library on data it cannot use (h5py maps some HDF5 failures, e.g. a bad
#: object-header checksum, to RuntimeError, and stored types it cannot convert to
#: TypeError), but by our own code only on a bug: a file failure only when raised inside
#: a library.
LIBRARY_FAILURES: tuple[type[BaseException], ...] = (TypeError, RuntimeError)

#: The cellcoadd package directory: code raising from under it is ours.
_PACKAGE = str(Path(__file__).resolve().parents[2]) + os.sep


def is_file_failure(error: BaseException) -> bool:
    """Whether ``error``, raised while reading a file, is the file's fault (damaged,
    truncated or foreign) rather than a programming error.

    True for :data:`FILE_FAILURES`, and for :data:`LIBRARY_FAILURES` raised inside a
    library (the innermost frame of the traceback is not cellcoadd's own code).
    """
    if isinstance(error, FILE_FAILURES):
        return True
    return isinstance(error, LIBRARY_FAILURES) and not _raised_by_cellcoadd(error)


def _raised_by_cellcoadd(error: BaseException) -> bool:
    frame = error.__traceback__
    if frame is None:  # not raised yet: cannot tell, so not blamed on the file
        return True
    while frame.tb_next is not None:
        frame = frame.tb_next
    return frame.tb_frame.f_code.co_filename.startswith(_PACKAGE)


def _facts(error: BaseException) -> dict[str, Any]:
    """The HDU, exposure and cell an inner check named, for the format error."""
    if not isinstance(error, CellCoaddError):
        return {}
    names = ("hdu", "visit", "detector", "cell")
    return {name: getattr(error, name) for name in names if getattr(error, name) is not None}


@contextmanager
def reading_errors(path: str, what: str) -> Iterator[None]:
    """Turn a file failure (:func:`is_file_failure`) while reading ``what`` into a
    CellCoaddFormatError naming ``path``; any other exception passes through."""
    try:
        yield
    except Exception as err:
        clear_cfitsio_messages()
        if isinstance(err, CellCoaddFormatError) or not is_file_failure(err):
            raise
        # our own checks say what is wrong; a library's error is named by its type
        problem = f"{err}" if isinstance(err, CellCoaddError) else f"{type(err).__name__}: {err}"
        raise CellCoaddFormatError(path, f"{what}: {problem}", **_facts(err)) from err


#: Most pixels an image plane may declare (8192 x 8192; an LSST detector is 4072 x 4000, a
#: DECam CCD 4096 x 2048): checked from the header alone, before CFITSIO allocates or
#: inflates the plane (a 1.6 MB stream declaring 20000 x 20000 cost 1.5 GB and 20 s).
MAX_PLANE_PIXELS = 8192 * 8192


def header_cards(header: bytes) -> dict[str, str]:
    """The ``KEY = value`` cards of raw FITS header bytes (80-character cards, up to
    ``END``), each value as written (comment cut, blanks stripped; the first of a repeated
    key). Nothing is interpreted: for checks made before a library reads the header."""
    cards: dict[str, str] = {}
    for start in range(0, len(header) - 79, 80):
        card = header[start : start + 80].decode("ascii", "replace")
        key = card[:8].strip()
        if key == "END":
            break
        if card[8:10] == "= " and key not in cards:
            cards[key] = card[10:].split("/", 1)[0].strip()
    return cards


def _card_int(value: Any) -> int | None:
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    try:
        return int(str(value).strip())
    except ValueError:
        return None


def declared_plane(cards: Mapping[str, Any]) -> tuple[int, ...] | None:
    """The dimensions (``NAXIS1, NAXIS2, ...``) of the image an HDU's header declares: the
    ``ZNAXISn`` of a tile-compressed image (``ZIMAGE = T``), the ``NAXISn`` of a primary or
    ``IMAGE`` extension; None for another HDU (a table). A missing or non-integer axis
    length counts as 0 (CFITSIO refuses such a header itself)."""
    if str(cards.get("ZIMAGE", "")).strip() in ("T", "True"):
        prefix = "ZNAXIS"
    elif "SIMPLE" in cards or str(cards.get("XTENSION", "")).strip("' ").upper() == "IMAGE":
        prefix = "NAXIS"
    else:
        return None
    naxis = _card_int(cards.get(prefix)) or 0
    return tuple(_card_int(cards.get(f"{prefix}{i}")) or 0 for i in range(1, min(naxis, 999) + 1))


def check_declared_plane(
    path: str | os.PathLike[str],
    hdu: int | str,
    cards: Mapping[str, Any],
    limit: int = MAX_PLANE_PIXELS,
) -> None:
    """Refuse an HDU whose header declares an image plane of more than ``limit`` pixels
    (:func:`declared_plane`), from the header alone.

    Raises
    ------
    CellCoaddFormatError
        Naming ``path``, the HDU, the declared size and the limit.
    """
    dims = declared_plane(cards)
    if dims is None or not dims:
        return
    pixels = 1
    for length in dims:
        pixels *= max(length, 0)
    if pixels > limit:
        shape = " x ".join(str(d) for d in dims)
        raise CellCoaddFormatError(
            path,
            f"HDU {hdu} declares a {shape} image ({pixels} pixels), more than the {limit} "
            "accepted: refused before reading it",
            hdu=hdu,
        )


def check_path_readable(path: str) -> int:
    """Size of ``path`` in bytes; FileNotFoundError if absent, CellCoaddFormatError if empty
    or not a regular file (a directory, a pipe or a device could block or mislead a reader;
    :func:`~cellcoadd.io._files.path_gate.gate_read`)."""
    return os.path.getsize(gate_read(path))
