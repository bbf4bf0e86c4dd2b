"""Pieces shared by the FITS and HDF5 layouts: version checks, JSON payloads, input tables,
error wrapping and the lazy :class:`CoaddFile` interface."""

from __future__ import annotations

import abc
import errno
import hashlib
import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import fitsio
import numpy as np
from astropy.table import Table
from pydantic import BaseModel

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.geometry.box import Box
from cellcoadd.model.cell_coadd import CellCoadd, wcs_from_record, wcs_to_record
from cellcoadd.model.inputs import FLOAT_FIELDS, InputRecord
from cellcoadd.model.patch_coadd import FORMAT_VERSION, PatchMetadata, parse_format_version

#: Marker identifying a cellcoadd patch file (FITS keyword CCFORMAT, HDF5 attribute).
FILE_KIND = "cellcoadd-patch"

#: Largest metadata JSON accepted, bytes (a guard against corrupted sizes).
MAX_METADATA_BYTES = 64 * 1024 * 1024

#: Free space (bytes) below which a failed write is blamed on a full disk.
DISK_FULL_MARGIN = 1 << 20

#: Pixel planes of a cell (besides the inputs table).
PLANES = ("image", "mask", "variance", "mfrac", "noise", "psf")


def sha256_hex(data: bytes) -> str:
    """Hex SHA-256 digest of ``data``."""
    return hashlib.sha256(data).hexdigest()


def metadata_payload(metadata: PatchMetadata) -> tuple[bytes, str]:
    """UTF-8 JSON of ``metadata`` as written, and the format version written with it.

    The writer always writes the layout of :data:`FORMAT_VERSION`, so that is the version
    recorded, whatever version ``metadata`` was read from.
    """
    stamped = metadata.model_copy(update={"format_version": FORMAT_VERSION})
    return stamped.model_dump_json().encode("utf-8"), FORMAT_VERSION


def check_format_version(path: str, version: Any) -> tuple[int, int]:
    """``(major, minor)`` of a file's version; CellCoaddFormatError unless the major is ours."""
    if isinstance(version, bytes):
        version = version.decode("ascii", errors="replace")
    try:
        major, minor = parse_format_version(str(version))
    except ValueError as err:
        raise CellCoaddFormatError(path, str(err)) from None
    ours = parse_format_version(FORMAT_VERSION)[0]
    if major != ours:
        raise CellCoaddFormatError(
            path,
            f"format version {version} has major version {major}; this cellcoadd reads "
            f"major version {ours} only (format {FORMAT_VERSION})",
        )
    return major, minor


def decode_metadata(path: str, payload: bytes, version: str) -> PatchMetadata:
    """Parse and validate the metadata JSON of a file whose header declares ``version``.

    Fields unknown to this reader are dropped only when the file's minor version is newer
    than ours (minor versions are additive); otherwise they are an error.
    """
    _, minor = check_format_version(path, version)
    data = json.loads(payload.decode("utf-8"))
    if not isinstance(data, dict):
        raise ValueError("metadata JSON is not an object")
    if minor > parse_format_version(FORMAT_VERSION)[1]:
        data = _drop_unknown_fields(PatchMetadata, data)
    metadata = PatchMetadata.model_validate(data)
    if metadata.format_version != version:
        raise CellCoaddFormatError(
            path,
            f"metadata says format version {metadata.format_version} but the file header "
            f"says {version}",
        )
    return metadata


def _drop_unknown_fields(model: type[BaseModel], data: dict[str, Any]) -> dict[str, Any]:
    kept = {}
    for name, value in data.items():
        field = model.model_fields.get(name)
        if field is None:
            continue
        annotation = field.annotation
        if (
            isinstance(annotation, type)
            and issubclass(annotation, BaseModel)
            and isinstance(value, dict)
        ):
            value = _drop_unknown_fields(annotation, value)
        kept[name] = value
    return kept


def cell_record_json(cell: CellCoadd) -> str:
    """ASCII JSON of a cell's identity: tract, index, boxes and exact WCS."""
    record = {
        "tract": cell.tract,
        "index": list(cell.index),
        "inner_bbox": cell.inner_bbox.model_dump(),
        "outer_bbox": cell.outer_bbox.model_dump(),
        "wcs": wcs_to_record(cell.wcs),
    }
    return json.dumps(record, ensure_ascii=True, separators=(",", ":"), allow_nan=False)


def parse_cell_record(text: str | bytes) -> dict[str, Any]:
    """Inverse of :func:`cell_record_json`: tract, index, inner_bbox, outer_bbox, wcs."""
    record = json.loads(text)
    return {
        "tract": int(record["tract"]),
        "index": (int(record["index"][0]), int(record["index"][1])),
        "inner_bbox": Box.model_validate(record["inner_bbox"]),
        "outer_bbox": Box.model_validate(record["outer_bbox"]),
        "wcs": wcs_from_record(record["wcs"]),
    }


def _escape_ascii(text: str) -> str:
    # JSON string escapes keep any Unicode band in an ASCII-only FITS column, reversibly.
    return json.dumps(text, ensure_ascii=True)[1:-1]


def _unescape_ascii(text: str) -> str:
    return json.loads(f'"{text}"')


def inputs_to_array(records: list[InputRecord], *, ascii_only: bool) -> np.ndarray:
    """Structured array (one row per record) of the inputs of a cell.

    ``band`` and ``status`` are fixed-width byte strings: UTF-8, or JSON-escaped ASCII when
    ``ascii_only`` (FITS tables hold ASCII only).
    """
    bands = [(_escape_ascii(r.band) if ascii_only else r.band).encode("utf-8") for r in records]
    statuses = [r.status.encode("ascii") for r in records]
    band_width = max([1, *(len(b) for b in bands)])
    status_width = max([1, *(len(s) for s in statuses)])
    dtype = np.dtype(
        [
            ("visit", "<i8"),
            ("detector", "<i8"),
            ("band", f"S{band_width}"),
            ("status", f"S{status_width}"),
            *((name, "<f8") for name in FLOAT_FIELDS),
        ]
    )
    table = np.zeros(len(records), dtype=dtype)
    for row, record in enumerate(records):
        table[row] = (
            record.visit,
            record.detector,
            bands[row],
            statuses[row],
            *(getattr(record, name) for name in FLOAT_FIELDS),
        )
    return table


def inputs_from_array(table: np.ndarray, *, ascii_only: bool) -> list[InputRecord]:
    """Validated records from a table written by :func:`inputs_to_array`."""
    records = []
    for row in table:
        band = _text(row["band"])
        records.append(
            InputRecord(
                visit=int(row["visit"]),
                detector=int(row["detector"]),
                band=_unescape_ascii(band) if ascii_only else band,
                status=_text(row["status"]),
                **{name: float(row[name]) for name in FLOAT_FIELDS},
            )
        )
    return records


def _text(value: Any) -> str:
    # Fixed-width strings come back NUL- or space-padded (bands never end in whitespace).
    if isinstance(value, (bytes, np.bytes_)):
        value = bytes(value).decode("utf-8")
    return str(value).rstrip(" \x00")


def expected_shapes(metadata: PatchMetadata, outer: Box) -> dict[str, tuple[int, ...]]:
    """Array shape of every plane of a cell with outer box ``outer``."""
    ny, nx = outer.shape
    psf = metadata.psf_size
    return {
        "image": (ny, nx),
        "mask": (ny, nx),
        "variance": (ny, nx),
        "mfrac": (ny, nx),
        "noise": (metadata.n_noise, ny, nx),
        "psf": (psf, psf),
    }


@contextmanager
def reading_errors(path: str, what: str) -> Iterator[None]:
    """Turn any failure while reading ``what`` into a CellCoaddFormatError naming ``path``."""
    try:
        yield
    except CellCoaddFormatError:
        clear_cfitsio_messages()
        raise
    except Exception as err:  # a corrupted file may fail in any library call
        clear_cfitsio_messages()
        raise CellCoaddFormatError(path, f"{what}: {type(err).__name__}: {err}") from err


#: A path no file can have (a file is not a directory), opened to drain CFITSIO messages.
_NO_SUCH_FITS_FILE = os.path.join(os.devnull, "cellcoadd-no-such-file.fits")


def clear_cfitsio_messages() -> None:
    """Empty CFITSIO's process-wide stack of error messages.

    fitsio takes messages off that stack only when it raises an error, and only as many as
    fit its 1 kB buffer. What a damaged file leaves there (any bytes, from its corrupted
    header) is then attached to the next, unrelated CFITSIO error, which fitsio cannot
    decode: even opening an intact file would fail. fitsio has no call to clear the stack,
    so it is drained by failing to open a file that cannot exist until an error comes back
    short (the stack was empty).
    """
    for _ in range(8):
        try:
            fitsio.FITS(_NO_SUCH_FITS_FILE).close()
        except UnicodeDecodeError:  # undecodable leftovers, now removed: drain on
            continue
        except OSError as err:
            if len(str(err)) < 512:
                return
            continue
        return


def check_path_readable(path: str) -> int:
    """Size of ``path`` in bytes; FileNotFoundError if absent, CellCoaddFormatError if empty
    or not a regular file (a directory, a pipe or a device could block or mislead a reader)."""
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file")
    if not os.path.isfile(path):
        raise CellCoaddFormatError(path, "not a regular file")
    size = os.path.getsize(path)
    if size == 0:
        raise CellCoaddFormatError(path, "the file is empty")
    return size


class CoaddFile(abc.ABC):
    """An open cellcoadd patch file, read lazily (one cell at a time).

    Use as a context manager or call :meth:`close`. ``metadata`` and ``cell_indices`` come
    from the small header part of the file; :meth:`read_cell` reads one cell's bytes.
    """

    #: ``"fits"`` or ``"hdf5"``.
    format_name: str = ""

    def __init__(self, path: str, metadata: PatchMetadata, cell_indices: list[tuple[int, int]]):
        self.path = path
        self.metadata = metadata
        self.cell_indices = cell_indices

    @abc.abstractmethod
    def read_cell(self, index: tuple[int, int]) -> CellCoadd:
        """The cell ``index`` (KeyError if the file does not hold it)."""

    @abc.abstractmethod
    def read_cell_inputs(self, index: tuple[int, int]) -> list[InputRecord]:
        """Only the inputs of cell ``index``."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the file."""

    def _check_index(self, index: tuple[int, int]) -> tuple[int, int]:
        key = (int(index[0]), int(index[1]))
        if key not in self.cell_indices:
            raise KeyError(f"{self.path}: no cell {key} in this file")
        return key

    def read_inputs(self) -> Table:
        """All inputs of all cells as an astropy Table with ``cell_x`` / ``cell_y`` columns."""
        rows: list[dict[str, Any]] = []
        for cx, cy in self.cell_indices:
            for record in self.read_cell_inputs((cx, cy)):
                rows.append({"cell_x": cx, "cell_y": cy, **record.model_dump()})
        names = ["cell_x", "cell_y", *InputRecord.model_fields]
        if not rows:
            dtypes = [int, int, int, int, str, float, str, *([float] * 6)]
            return Table(names=names, dtype=dtypes)
        return Table(rows=[[row[name] for name in names] for row in rows], names=names)

    def __enter__(self) -> CoaddFile:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        meta = self.metadata
        return (
            f"<{type(self).__name__} {self.path!r}: tract {meta.tract} patch {meta.patch} "
            f"band {meta.band!r}, {len(self.cell_indices)} cells>"
        )


# ------------------------------------------------------------------ safe, reproducible writes


def check_free_space(target: str | os.PathLike[str], needed: int) -> None:
    """Refuse to start a write of about ``needed`` bytes that cannot fit on the disk.

    Writing into a full disk is worse than refusing up front: HDF5 2.0 cannot close a file
    whose flush failed (the process then crashes at exit) and CFITSIO reports unrelated
    errors. File systems that report no size at all (some network mounts) are not checked.

    Raises
    ------
    OSError
        ``errno.ENOSPC``, naming ``target`` and the space needed and free.
    """
    directory = os.path.dirname(os.path.abspath(target))
    try:
        stats = os.statvfs(directory)
    except (OSError, AttributeError):  # no statvfs on this platform or mount
        return
    if stats.f_blocks == 0:
        return
    free = stats.f_bavail * stats.f_frsize
    if free < needed:
        raise OSError(
            errno.ENOSPC,
            f"disk full: writing needs up to {needed} bytes but only {free} are free in "
            f"{directory}; nothing was written",
            os.fspath(target),
        )


def disk_full_error(target: str | os.PathLike[str], error: BaseException) -> OSError | None:
    """A clear ``ENOSPC`` error if ``error`` (raised while writing ``target``) came from a
    full disk or exhausted quota, else None.

    CFITSIO does not pass the system error on, so a failure while the target's file
    system has less than :data:`DISK_FULL_MARGIN` free is taken to be a full disk too.
    Call this before removing the partial file, whose blocks are part of the evidence.
    """
    code = getattr(error, "errno", None)
    text = str(error)
    full = code in (errno.ENOSPC, errno.EDQUOT) or any(
        phrase in text for phrase in ("No space left on device", "Disk quota exceeded")
    )
    directory = os.path.dirname(os.path.abspath(target))
    free: int | None = None
    try:
        stats = os.statvfs(directory)
        if stats.f_blocks > 0:
            free = stats.f_bavail * stats.f_frsize
    except (OSError, AttributeError):
        pass
    if not full and (free is None or free >= DISK_FULL_MARGIN):
        return None
    where = f"{directory} has {free} bytes free" if free is not None else directory
    return OSError(
        errno.ENOSPC,
        f"disk full or quota exceeded while writing ({where}); nothing was written and any "
        f"previous file is unchanged [{type(error).__name__}: {_first_line(text)}]",
        os.fspath(target),
    )


def _first_line(text: str) -> str:
    return text.strip().splitlines()[0] if text.strip() else ""
