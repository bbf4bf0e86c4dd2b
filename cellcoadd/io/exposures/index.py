"""The exposure index: one SQLite row per input file, its described header and sky footprint.

A survey run must answer "which inputs may touch this patch" for hundreds of thousands of
files without opening them, and its workers must build a patch without parsing a header
again. :class:`ExposureIndex` stores, per input file (stdlib :mod:`sqlite3`, one file, no
server):

* how to open it: the manifest entry (path, layout, PSF model file, background file,
  identity overrides), all paths absolute;
* what the builder needs before pixels: the described header
  (:class:`~cellcoadd.model.sources.ExposureHeader`: identity, band, zero point, shape,
  valid box, mask-bit names and the exact WCS through
  :func:`~cellcoadd.model.wcs_codec.wcs_to_record`), as JSON;
* its sky footprint: the RA/Dec of the valid box's corners, and the HEALPix pixels (nested,
  ``nside`` of the index, :mod:`hpgeom`) that the footprint overlaps: the spatial key.
  HEALPix has no RA wrap and no singular poles, so a query near RA 0/360 or a pole is
  the same query as anywhere else;
* the size, modification time (ns) and, optionally, SHA-256 of every file the input reads
  (exposure, PSF model, background), so that a changed input is found and re-read.

Files that cannot be described are stored too, with the reason (status ``bad``), and
listed; files that vanished since they were indexed are marked ``vanished``. Queries
return only ``ok`` rows. A file is bad, and only it, when its footprint is degenerate or
overlaps more than :data:`~cellcoadd.geometry.footprint.MAX_FOOTPRINT_PIXELS` HEALPix
pixels (checked before they are listed, in the describing process), or when another file
already holds its (visit, detector). A row that disagrees with its checksum is read again
by the next update (or marked bad); one whose columns do not decode raises
:class:`~cellcoadd.errors.IndexRowError` naming the index, the row, the file and the
column when used.

Footprints are the polygon of the valid box's corners pushed outward by
:data:`FOOTPRINT_MARGIN` pixels (WCS distortion bends the edges between the corners);
HEALPix queries are ``inclusive``, so a query returns every input that may touch the
region, and a few more: the builder's selection is exact.
"""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import hpgeom
import numpy as np

from cellcoadd.errors import (
    CellCoaddError,
    CellCoaddFormatError,
    GeometryError,
    IndexRowError,
    InputError,
)
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.footprint import (
    FOOTPRINT_MARGIN,
    check_nside,
    healpix_pixels,
    polygon_area,
    sky_corners,
)
from cellcoadd.geometry.wcs_utils import canonical_wcs, pixel_area
from cellcoadd.io._files.path_gate import gate_create, gate_read
from cellcoadd.io._files.sqlite_files import open_own_database
from cellcoadd.io._files.stamps import FileStamp, json_sha256
from cellcoadd.model.manifest import Manifest, ManifestEntry
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.sources import DescribedSource, ExposureHeader, ExposureSource
from cellcoadd.model.wcs_codec import wcs_from_record, wcs_to_record

#: Version of the tables below (``PRAGMA user_version``); an index of another version is
#: refused. 2: each row carries a checksum of its stored fields and its footprint's pixel
#: count.
SCHEMA_VERSION = 2

#: ``PRAGMA application_id`` of an exposure index ("CCXI"): a SQLite file without it is
#: not ours, and is refused unmodified.
APPLICATION_ID = 0x43435849

#: Default HEALPix resolution of the spatial key: nside 512 pixels are 6.9 arcmin on a side,
#: so an LSST detector (13 arcmin) or a DECam CCD (9 x 18 arcmin) overlaps ~6 to 12 of them
#: and an LSST patch (~10 arcmin) about as many.
DEFAULT_NSIDE = 512

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS exposures (
    id INTEGER PRIMARY KEY,
    path TEXT NOT NULL UNIQUE,
    status TEXT NOT NULL CHECK (status IN ('ok', 'bad', 'vanished')),
    reason TEXT,
    entry TEXT NOT NULL,
    layout TEXT NOT NULL,
    psf TEXT,
    visit INTEGER,
    detector INTEGER,
    band TEXT,
    zero_point REAL,
    nx INTEGER,
    ny INTEGER,
    valid_box TEXT,
    corners TEXT,
    area_deg2 REAL,
    header TEXT,
    files TEXT NOT NULL,
    size INTEGER NOT NULL,
    mtime_ns INTEGER NOT NULL,
    sha256 TEXT,
    indexed REAL NOT NULL,
    header_sha256 TEXT,
    n_pixels INTEGER NOT NULL DEFAULT 0,
    checksum TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS footprint (
    pixel INTEGER NOT NULL,
    exposure INTEGER NOT NULL REFERENCES exposures(id) ON DELETE CASCADE,
    PRIMARY KEY (pixel, exposure)
) WITHOUT ROWID;
CREATE INDEX IF NOT EXISTS footprint_by_exposure ON footprint (exposure);
CREATE INDEX IF NOT EXISTS exposures_by_band ON exposures (band, status);
"""


# -- the stored forms ------------------------------------------------------------------


def header_to_json(header: ExposureHeader) -> str:
    """``header`` as JSON; :func:`header_from_json` rebuilds it exactly (WCS bit for bit)."""
    return json.dumps(
        {
            "visit": header.visit,
            "detector": header.detector,
            "band": header.band,
            "wcs": wcs_to_record(header.wcs),
            "wcs_pixel_shape": None
            if header.wcs.pixel_shape is None
            else list(header.wcs.pixel_shape),
            "shape": list(header.shape),
            "valid_box": [
                header.valid_box.x_start,
                header.valid_box.x_stop,
                header.valid_box.y_start,
                header.valid_box.y_stop,
            ],
            "zero_point": header.zero_point,
            "mask_bits": header.mask_bits.bits,
        },
        separators=(",", ":"),
    )


def header_from_json(text: str) -> ExposureHeader:
    """The :class:`ExposureHeader` stored by :func:`header_to_json`."""
    data = json.loads(text)
    x0, x1, y0, y1 = data["valid_box"]
    wcs = wcs_from_record(data["wcs"])
    if data.get("wcs_pixel_shape") is not None:
        wcs.pixel_shape = tuple(data["wcs_pixel_shape"])
    return ExposureHeader(
        visit=int(data["visit"]),
        detector=int(data["detector"]),
        band=str(data["band"]),
        # in the form a header read from its file takes (canonical_wcs), bit for bit
        wcs=canonical_wcs(wcs),
        shape=(int(data["shape"][0]), int(data["shape"][1])),
        valid_box=Box(x_start=x0, x_stop=x1, y_start=y0, y_stop=y1),
        zero_point=float(data["zero_point"]),
        mask_bits=MaskBits(bits=data["mask_bits"]),
    )


def footprint_corners(header: ExposureHeader, margin: float = FOOTPRINT_MARGIN) -> np.ndarray:
    """RA/Dec (deg) of the corners of the valid box, pushed outward by ``margin`` pixels,
    in order around the box: shape ``(4, 2)``
    (:func:`~cellcoadd.geometry.footprint.sky_corners`)."""
    return sky_corners(header.wcs, header.valid_box, margin)


# -- rows -------------------------------------------------------------------------------


#: The stored fields of a row that its checksum covers (the header through its SHA-256).
CHECKED_FIELDS = (
    "path", "status", "reason", "entry", "layout", "psf", "visit", "detector", "band",
    "zero_point", "nx", "ny", "valid_box", "corners", "area_deg2", "header_sha256", "files",
    "size", "mtime_ns", "sha256", "n_pixels",
)  # fmt: skip


def row_checksum(values: Mapping[str, Any] | sqlite3.Row) -> str:
    """SHA-256 of a row's :data:`CHECKED_FIELDS` (a dict or a ``sqlite3.Row``): their
    ``repr`` joined by a unit separator. ``repr`` of SQLite's values (str, int, float,
    None) is exact and stable (floats round-trip), and three times cheaper than JSON: a
    query checks every row it returns (~6 us a row)."""
    text = "\x1f".join([repr(values[name]) for name in CHECKED_FIELDS])
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class IndexedExposure:
    """One usable input of the index (an ``ok`` row): how to open it and its header.

    The stored JSON is parsed when first asked for, so that a query returning hundreds
    of rows costs little more than reading them. Rows are checked against their checksum
    when read (:meth:`ExposureIndex.query`, :meth:`ExposureIndex.by_ids`).

    Attributes
    ----------
    id : int
        Row id in the index.
    path : str
        The exposure file (absolute).
    visit, detector : int
    band : str
    checksum : str
        SHA-256 of the row's stored fields (:func:`row_checksum`): what a patch built from
        this input depends on, as indexed.
    entry : ManifestEntry
        How to open the file (absolute paths). ``trust_psf`` is always False here: trust
        comes from the run's own configuration, never from a data file.
    corners : numpy.ndarray
        ``(4, 2)`` RA/Dec (deg) of its footprint's corners.
    files : tuple of FileStamp
        Every file it reads (exposure, PSF model, background) as indexed.
    header_json : str or None
        The described header (:func:`header_from_json`); None when not read (queries).
    index_path : str
        The index file the row was read from (named by errors).

    A stored column that does not decode as its kind (JSON of the right shape) raises
    :class:`~cellcoadd.errors.IndexRowError` naming the index, the row, the file and the
    column, when first asked for: only what uses this input fails.
    """

    id: int
    path: str
    visit: int
    detector: int
    band: str
    checksum: str
    entry_json: str = field(repr=False)
    corners_json: str = field(repr=False)
    files_json: str = field(repr=False)
    header_json: str | None = field(default=None, repr=False)
    index_path: str = field(default="", repr=False)

    def damaged(self, column: str, problem: object) -> IndexRowError:
        """The error naming this row's ``column`` and what is wrong with it."""
        return IndexRowError(
            f"{self.path}: row {self.id} of the exposure index {self.index_path or '?'}: "
            f"its {column} column is unusable ({_short_text(problem)}): run `cellcoadd index "
            "--checksum` again",
            path=self.path,
            row=self.id,
            fields=(column,),
        )

    @cached_property
    def entry(self) -> ManifestEntry:
        try:
            entry = ManifestEntry.model_validate_json(self.entry_json)
        except (TypeError, ValueError) as err:  # pydantic's ValidationError is a ValueError
            raise self.damaged("entry", err) from None
        return entry.model_copy(update={"trust_psf": False}) if entry.trust_psf else entry

    @cached_property
    def corners(self) -> np.ndarray:
        try:
            corners = np.asarray(json.loads(self.corners_json), dtype=float)
        except (TypeError, ValueError, OverflowError) as err:
            raise self.damaged("corners", err) from None
        if corners.shape != (4, 2) or not np.all(np.isfinite(corners)):
            raise self.damaged("corners", "not 4 finite RA/Dec pairs")
        return corners

    @cached_property
    def files(self) -> tuple[FileStamp, ...]:
        files = _decoded_files(self.files_json)
        if not files:
            raise self.damaged("files", "not a list of [path, size, mtime_ns, sha256]")
        return tuple(FileStamp(p, s, m, h) for p, s, m, h in files)

    def not_as_indexed(self, index_path: str) -> InputError | None:
        """The error naming the first file this input reads that changed or vanished
        since it was indexed in ``index_path`` (one ``stat`` per file); None when all
        are as indexed."""
        for stamp in self.files:
            reason = stamp.changed()
            if reason is not None:
                return InputError(
                    f"input (visit={self.visit}, detector={self.detector}): {reason} since "
                    f"it was indexed in {index_path}; run `cellcoadd index` again",
                    path=stamp.path,
                    visit=self.visit,
                    detector=self.detector,
                )
        return None

    def header(self) -> ExposureHeader:
        """The described header (rows from :meth:`ExposureIndex.by_ids` only).

        Raises
        ------
        IndexRowError
            When the stored header does not decode (names the row and the column).
        """
        if self.header_json is None:
            raise CellCoaddFormatError(self.path, "its header was not read from the index")
        try:
            return header_from_json(self.header_json)
        except CellCoaddError as err:
            raise self.damaged("header", err) from None
        except (TypeError, ValueError, KeyError, IndexError, OverflowError) as err:
            raise self.damaged("header", f"{type(err).__name__}: {err}") from None

    def source(self, trust_psf: bool = False) -> ExposureSource:
        """The exposure source of the file (reads the PSF model file of survey layouts);
        ``trust_psf`` (from the run's configuration) allows pickled PSF models."""
        entry = self.entry.model_copy(update={"trust_psf": True}) if trust_psf else self.entry
        return source_of(entry)

    def described(self, trust_psf: bool = False) -> DescribedSource:
        """The source with its stored header: what a build takes, no header parsed."""
        return DescribedSource(self.source(trust_psf), self.header())

    def cross_check(self, source: ExposureSource | None = None) -> DescribedSource:
        """The source with its header read from the file, after checking that every
        stored field the build uses (identity, band, zero point, shape, valid box, mask
        bits, WCS) equals what the file says now, and that the row's own columns used to
        plan (visit, detector, band, footprint corners) agree with it.

        Raises
        ------
        IndexRowError
            Naming the file, the row and each field that differs.
        """
        source = source or self.source()
        header = self.header()  # IndexRowError if the stored header does not decode
        stored = json.loads(self.header_json or "{}")
        read = source.header()
        found = json.loads(header_to_json(read))
        fields = tuple(name for name in found if stored.get(name) != found[name])
        details = [
            f"{name}: index {_short(stored.get(name))}, file {_short(found[name])}"
            for name in fields
        ]
        for name, value in (("visit", self.visit), ("detector", self.detector)):
            if value != found[name]:
                fields += (name,)
                details.append(f"{name} column: index {value}, file {found[name]}")
        if self.path != self.entry.path:
            fields += ("path",)
            details.append(f"path column: index {self.path!r}, entry {self.entry.path!r}")
        if self.band != found["band"]:
            fields += ("band",)
            details.append(f"band column: index {self.band!r}, file {found['band']!r}")
        # the footprint planning used (a row forged with its checksum could move it)
        if not _same_corners(self.corners, footprint_corners(read)):
            fields += ("corners",)
            details.append("corners column: not the file's footprint")
        if fields:
            raise IndexRowError(
                f"{self.path}: row {self.id} of the exposure index differs from the file "
                f"({'; '.join(details)}): run `cellcoadd index` again",
                path=self.path,
                row=self.id,
                fields=fields,
            )
        return DescribedSource(source, header)


def _same_corners(a: np.ndarray, b: np.ndarray, tolerance_deg: float = 1e-6) -> bool:
    """Whether two footprints' RA/Dec corners agree within ``tolerance_deg`` (RA across
    0/360 too)."""
    ra = (a[:, 0] - b[:, 0] + 180.0) % 360.0 - 180.0
    return bool(
        np.all(np.abs(ra) <= tolerance_deg) and np.all(np.abs(a[:, 1] - b[:, 1]) <= tolerance_deg)
    )


def _short(value: Any) -> str:
    text = json.dumps(value, separators=(",", ":"))
    return text if len(text) <= 80 else text[:77] + "..."


def _short_text(value: object) -> str:
    text = str(value).replace("\n", " ")
    return text if len(text) <= 120 else text[:117] + "..."


def source_of(entry: ManifestEntry) -> ExposureSource:
    """The exposure source of a manifest entry whose paths are absolute."""
    from cellcoadd.io.exposures.manifest_io import sources_from_manifest

    return sources_from_manifest(Manifest(exposures=(entry,)), "/")[0]


def absolute_entry(entry: ManifestEntry, base: str | os.PathLike[str]) -> ManifestEntry:
    """``entry`` with its paths (file, PSF, background) made absolute from ``base``."""
    base = Path(base)
    changes = {
        name: os.path.abspath(base / value)
        for name in ("path", "psf", "background")
        if (value := getattr(entry, name)) is not None
    }
    return entry.model_copy(update=changes)


def entry_files(entry: ManifestEntry) -> list[str]:
    """The files an input reads: the exposure, its PSF model and background files."""
    return [p for p in (entry.path, entry.psf, entry.background) if p is not None]


@dataclass(frozen=True)
class Described:
    """What a worker found in one file: its header, footprint and the footprint's HEALPix
    pixels (None: computed when stored), or why it is bad."""

    entry: ManifestEntry
    files: tuple[FileStamp, ...]
    header_json: str | None = None
    corners: np.ndarray | None = None
    reason: str | None = None
    pixels: np.ndarray | None = field(default=None, repr=False)


def describe_entry(
    entry: ManifestEntry, checksum: bool = False, nside: int | None = None
) -> Described:
    """Read one input's headers (in any process): a :class:`Described`, never an error.

    With ``nside``, the footprint's HEALPix pixels are listed here too, so that a
    footprint too large for the key
    (:data:`~cellcoadd.geometry.footprint.MAX_FOOTPRINT_PIXELS`) or degenerate (a pixel
    scale far too small) makes this file bad, and only this one.
    """
    stamps: list[FileStamp] = []
    try:
        for path in entry_files(entry):
            stamps.append(FileStamp.of(path, checksum))
    except OSError as err:
        return Described(entry, tuple(stamps), reason=f"cannot read: {err}")
    try:
        header = source_of(entry).header()
        corners = footprint_corners(header)
        if not np.all(np.isfinite(corners)):
            return Described(entry, tuple(stamps), reason="the WCS gives no sky footprint")
        pixels = None if nside is None else healpix_pixels(nside, corners)
    except GeometryError as err:  # the footprint: say at which pixel scale
        return Described(entry, tuple(stamps), reason=f"{err}{_pixel_scale_note(header)}")
    except (CellCoaddError, OSError, ValueError, KeyError, TypeError) as err:
        return Described(entry, tuple(stamps), reason=_bad_reason(err, entry.path))
    return Described(entry, tuple(stamps), header_to_json(header), corners, pixels=pixels)


def _bad_reason(err: Exception, path: str) -> str:
    """Why a file is bad, as listed beside its path: our errors in their own words (without
    the path when it is the file's own), a library's named by its type."""
    if isinstance(err, CellCoaddFormatError) and os.path.abspath(err.path) == os.path.abspath(path):
        return err.problem
    if isinstance(err, CellCoaddError):
        return str(err)
    return f"{type(err).__name__}: {err}"


def _pixel_scale_note(header: ExposureHeader) -> str:
    """`` (the WCS gives S arcsec/pixel)`` at the centre of the valid box, or nothing."""
    box = header.valid_box
    centre = ((box.x_start + box.x_stop - 1) / 2, (box.y_start + box.y_stop - 1) / 2)
    try:
        scale = float(np.sqrt(pixel_area(header.wcs, *centre)))
    except (ValueError, ArithmeticError):
        return ""
    return f" (the WCS gives {scale:.3g} arcsec/pixel)"


# -- the index ---------------------------------------------------------------------------


@dataclass(frozen=True)
class UnusableFile:
    """A file the index marks bad or vanished: why, and its band and footprint corners
    when they were known (a vanished file keeps those it was indexed with)."""

    path: str
    status: str
    reason: str
    band: str | None = None
    corners: np.ndarray | None = field(default=None, repr=False)


@dataclass
class IndexUpdate:
    """What one :meth:`ExposureIndex.update` did (paths in each list)."""

    added: list[str] = field(default_factory=list)
    updated: list[str] = field(default_factory=list)
    unchanged: list[str] = field(default_factory=list)
    bad: list[tuple[str, str]] = field(default_factory=list)
    vanished: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def summary(self) -> str:
        return (
            f"{len(self.added)} added, {len(self.updated)} updated, "
            f"{len(self.unchanged)} unchanged, {len(self.bad)} bad, "
            f"{len(self.vanished)} vanished ({self.seconds:.1f} s)"
        )


class ExposureIndex:
    """An exposure index file (SQLite), opened for reading or updating.

    Parameters
    ----------
    path : path-like
        The ``.sqlite`` file; created (with ``nside``) unless ``readonly``.
    readonly : bool
        Open for queries only (what workers do); the file must exist.
    nside : int
        HEALPix resolution of a new index (a power of 2 up to
        :data:`~cellcoadd.geometry.footprint.MAX_NSIDE`); an existing index keeps its own.

    Raises
    ------
    CellCoaddRangeError
        For an ``nside`` that is not a power of 2 in the allowed range (before any file
        is opened).
    CellCoaddFormatError
        When the file is not an index of this schema version, or does not exist (readonly),
        or its stored nside is out of range.
    """

    def __init__(
        self, path: str | os.PathLike[str], *, readonly: bool = False, nside: int = DEFAULT_NSIDE
    ):
        self.path = os.fspath(path)
        if not readonly:
            check_nside(nside)  # before any file is touched
        if readonly and not os.path.lexists(self.path):
            raise CellCoaddFormatError(self.path, "no such exposure index")
        # a FIFO, a device or a directory is refused before SQLite opens it
        # a writer never follows a link (SQLite would create or change its target)
        resolved = (
            gate_read(self.path, what="exposure index")
            if readonly
            else gate_create(self.path, what="exposure index", companions=("-journal", "-wal"))
        )
        self._db = open_own_database(
            resolved,
            application_id=APPLICATION_ID,
            version=SCHEMA_VERSION,
            schema=_SCHEMA,
            what="exposure index",
            readonly=readonly,
            older="index the files again into a new file",
        )
        self._db.row_factory = sqlite3.Row
        try:
            self._db.execute("PRAGMA foreign_keys = ON")
            rows = dict(self._db.execute("SELECT key, value FROM meta").fetchall())
            if not rows and not readonly:
                with self._db:
                    self._db.execute("INSERT INTO meta VALUES ('nside', ?)", (str(nside),))
                rows = {"nside": str(nside)}
            self.nside = check_nside(int(rows["nside"]))
        except (sqlite3.DatabaseError, KeyError, ValueError, TypeError) as err:
            self._db.close()
            raise CellCoaddFormatError(self.path, f"damaged exposure index ({err})") from None

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> ExposureIndex:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- updating ----------------------------------------------------------------------

    def update(
        self,
        entries: Sequence[ManifestEntry],
        *,
        checksum: bool = False,
        workers: int = 1,
        progress: Callable[[Iterable[Any], int], Iterable[Any]] | None = None,
    ) -> IndexUpdate:
        """Add new inputs, re-read changed ones, mark vanished ones.

        Parameters
        ----------
        entries : sequence of ManifestEntry
            Inputs with absolute paths (:func:`absolute_entry`).
        checksum : bool
            Also compare (and store) the SHA-256 of every file: finds changes that keep
            size and mtime, at the cost of reading every byte; and decode every stored
            row (a row damaged with its checksum made to agree is read again).
        workers : int
            Processes reading headers.
        progress : callable, optional
            ``progress(iterable, total)`` wrapping the described files (e.g. tqdm).

        Every row of the index (not only ``entries``) whose file is gone is marked
        ``vanished``; it returns to ``ok`` when the file comes back and is indexed again.
        A row that disagrees with its checksum, or whose header disagrees with the
        header's SHA-256, is read again from its file. A file with the (visit, detector)
        of a file already indexed is bad (the first stays).
        """
        start = time.perf_counter()
        result = IndexUpdate()
        # a damaged row is read again, or marked vanished or bad: never fatal
        columns = ", ".join(("id", "checksum", "header", *CHECKED_FIELDS))
        known = {
            row["path"]: (
                row["status"] if row["status"] != "ok" or _row_intact(row, checksum) else "damaged",
                _decoded_files(row["files"]),
                row["entry"],
                row["id"],
            )
            for row in self._db.execute(f"SELECT {columns} FROM exposures")
        }
        todo: list[ManifestEntry] = []
        seen: set[str] = set()
        for entry in entries:
            if entry.path in seen:
                continue
            seen.add(entry.path)
            old = known.get(entry.path)
            if (
                old is not None
                and old[0] == "ok"
                and old[2] == entry.model_dump_json()
                and not _stale(old[1], entry, checksum)
            ):
                result.unchanged.append(entry.path)
            else:
                todo.append(entry)
        described = self._describe_all(todo, checksum, workers, progress)
        with self._db:
            for path, (status, files, _, row_id) in known.items():
                if path in seen or status == "vanished":
                    continue
                if not _exists(files, path):
                    change = ("vanished", "the file vanished")
                    result.vanished.append(path)
                elif status == "damaged":  # not read again now: its columns are not trusted
                    change = ("bad", _DAMAGED_ROW)
                    result.bad.append((str(path), _DAMAGED_ROW))
                else:
                    continue
                self._db.execute(
                    "UPDATE exposures SET status = ?, reason = ? WHERE id = ?", (*change, row_id)
                )
                self._db.execute("DELETE FROM footprint WHERE exposure = ?", (row_id,))
            identities = _Identities(self._db)
            for item in described:
                item = identities.claim(item)
                path = item.entry.path
                if item.reason is not None:
                    result.bad.append((path, item.reason))
                elif path in known:
                    result.updated.append(path)
                else:
                    result.added.append(path)
                self.store(item)
        result.seconds = time.perf_counter() - start
        return result

    def _describe_all(
        self,
        entries: list[ManifestEntry],
        checksum: bool,
        workers: int,
        progress: Callable[[Iterable[Any], int], Iterable[Any]] | None,
    ) -> Iterator[Described]:
        wrap = progress or (lambda items, total: items)
        nside = self.nside
        if workers <= 1 or len(entries) < 2:
            described = (describe_entry(e, checksum, nside) for e in entries)
            yield from wrap(described, len(entries))
            return
        chunk = max(1, min(64, len(entries) // (4 * workers)))
        with ProcessPoolExecutor(max_workers=workers) as pool:
            n = len(entries)
            options = ([checksum] * n, [nside] * n)
            results = pool.map(describe_entry, entries, *options, chunksize=chunk)
            yield from wrap(results, n)

    def store(self, item: Described) -> None:
        """Insert or replace the row of ``item`` and its footprint pixels; the caller
        commits (:meth:`commit`, or a ``with`` block on the connection)."""
        entry = item.entry
        first = item.files[0] if item.files else FileStamp(entry.path, -1, -1)
        layout = entry.layout if isinstance(entry.layout, str) else "custom"
        values: dict[str, Any] = {
            "path": entry.path,
            "entry": entry.model_dump_json(),
            "layout": layout,
            "psf": entry.psf,
            "files": json.dumps([[f.path, f.size, f.mtime_ns, f.sha256] for f in item.files]),
            "size": first.size,
            "mtime_ns": first.mtime_ns,
            "sha256": first.sha256,
            "indexed": time.time(),
        }
        if item.reason is not None or item.header_json is None or item.corners is None:
            values.update(status="bad", reason=item.reason)
            pixels: np.ndarray = np.zeros(0, dtype=np.int64)
        else:
            header = json.loads(item.header_json)
            values.update(
                status="ok",
                reason=None,
                visit=header["visit"],
                detector=header["detector"],
                band=header["band"],
                zero_point=header["zero_point"],
                ny=header["shape"][0],
                nx=header["shape"][1],
                valid_box=json.dumps(header["valid_box"]),
                corners=json.dumps(item.corners.tolist()),
                area_deg2=polygon_area(item.corners),
                header=item.header_json,
                header_sha256=json_sha256(item.header_json),
            )
            pixels = (
                healpix_pixels(self.nside, item.corners) if item.pixels is None else item.pixels
            )
        values["n_pixels"] = len(pixels)
        values["checksum"] = row_checksum({name: values.get(name) for name in CHECKED_FIELDS})
        self._db.execute("DELETE FROM exposures WHERE path = ?", (entry.path,))
        names = ", ".join(values)
        marks = ", ".join("?" for _ in values)
        cursor = self._db.execute(
            f"INSERT INTO exposures ({names}) VALUES ({marks})", tuple(values.values())
        )
        row_id = cursor.lastrowid
        self._db.executemany(
            "INSERT INTO footprint (pixel, exposure) VALUES (?, ?)",
            ((int(p), row_id) for p in pixels),
        )

    def put(self, entry: ManifestEntry, header: ExposureHeader, files: Sequence[FileStamp]) -> None:
        """Store an input described elsewhere (e.g. synthetic rows for a benchmark); the
        caller commits through :meth:`commit`."""
        self.store(
            Described(entry, tuple(files), header_to_json(header), footprint_corners(header))
        )

    def commit(self) -> None:
        self._db.commit()

    # -- queries -----------------------------------------------------------------------

    def query(self, corners: np.ndarray, band: str | None = None) -> list[IndexedExposure]:
        """The usable inputs whose footprint may overlap the convex polygon ``corners``
        (``(n, 2)`` RA/Dec, deg), of ``band`` if given, ordered by (visit, detector).

        Raises
        ------
        IndexRowError
            When a row returned does not match its checksum (names the file, the row and
            the fields that differ from the file).
        GeometryError
            For a region over 2**24 HEALPix pixels, or a degenerate one.
        """
        pixels = healpix_pixels(self.nside, np.asarray(corners, dtype=float), _MAX_QUERY_PIXELS)
        ids: set[int] = set()
        for start in range(0, len(pixels), _CHUNK):
            part = [int(p) for p in pixels[start : start + _CHUNK]]
            marks = ", ".join("?" for _ in part)
            # an explicit list: SQLite then searches the (pixel, exposure) key per pixel
            ids.update(
                row[0]
                for row in self._db.execute(
                    f"SELECT DISTINCT exposure FROM footprint WHERE pixel IN ({marks})", part
                )
            )
        rows = self._rows(sorted(ids), header=False)
        if len(rows) != len(ids):  # footprint pixels of no usable row: a changed row id
            orphans = sorted(ids - {row["id"] for row in rows})
            raise IndexRowError(
                f"{self.path}: the spatial key lists rows {orphans[:5]} of the exposure index, "
                "which are not usable rows (a row id changed, or the key was damaged): run "
                "`cellcoadd index` into a new file",
                path=self.path,
                row=int(orphans[0]),
                fields=("id",),
            )
        found = [self._checked(row) for row in rows if band in (None, row["band"])]
        return sorted(found, key=lambda item: (item.visit, item.detector, item.path))

    def _rows(self, ids: Sequence[int], header: bool = True) -> list[sqlite3.Row]:
        """The ``ok`` rows among ``ids``, by column name (the header NULL unless asked)."""
        columns = ", ".join(("id", "checksum", *CHECKED_FIELDS)) + (
            ", header" if header else ", NULL AS header"
        )
        rows: list[sqlite3.Row] = []
        for start in range(0, len(ids), _CHUNK):
            part = [int(i) for i in ids[start : start + _CHUNK]]
            marks = ", ".join("?" for _ in part)
            rows += self._db.execute(
                f"SELECT {columns} FROM exposures WHERE status = 'ok' AND id IN ({marks})", part
            ).fetchall()
        return rows

    def _checked(self, row: sqlite3.Row) -> IndexedExposure:
        """The row as an :class:`IndexedExposure`, after checking it against its checksum
        (and its header against the header's SHA-256, when read)."""
        damaged = row_checksum(row) != row["checksum"]
        header = row["header"]
        if header is not None and (
            not isinstance(header, str) or json_sha256(header) != row["header_sha256"]
        ):
            damaged = True
        if damaged:
            fields = self._differing_fields(row)
            raise IndexRowError(
                f"{row['path']!s}: row {row['id']} of the exposure index {self.path} does not "
                f"match its checksum (stored {', '.join(fields)} "
                f"{'differ' if len(fields) > 1 else 'differs'} from the file or was damaged): "
                "run `cellcoadd index` again",
                path=str(row["path"]),
                row=int(row["id"]),
                fields=fields,
            )
        # stored values of another type (a row forged with its checksum) are named too
        wrong = tuple(name for name, kind in _ROW_TYPES.items() if type(row[name]) is not kind)
        if wrong:
            raise IndexRowError(
                f"{row['path']!s}: row {row['id']} of the exposure index {self.path}: its "
                f"{', '.join(wrong)} column{'s are' if len(wrong) > 1 else ' is'} not of the "
                "stored type: run `cellcoadd index` again",
                path=str(row["path"]),
                row=int(row["id"]),
                fields=wrong,
            )
        return IndexedExposure(
            int(row["id"]), row["path"], row["visit"], row["detector"], row["band"],
            row["checksum"], row["entry"], row["corners"], row["files"], row["header"],
            self.path,
        )  # fmt: skip

    def _differing_fields(self, row: sqlite3.Row) -> tuple[str, ...]:
        """Which stored fields of ``row`` differ from the file described now (the
        checksum itself when none does)."""
        try:
            entry = ManifestEntry.model_validate_json(row["entry"])
        except (TypeError, ValueError):
            return ("entry",)
        fresh = describe_entry(entry.model_copy(update={"trust_psf": False}), nside=self.nside)
        if fresh.reason is not None or fresh.header_json is None or fresh.pixels is None:
            return ("header",)
        stored_header = row["header"]
        if stored_header is None:
            (stored_header,) = self._db.execute(
                "SELECT header FROM exposures WHERE id = ?", (row["id"],)
            ).fetchone()
        now = json.loads(fresh.header_json)
        expected = {
            "visit": now["visit"],
            "detector": now["detector"],
            "band": now["band"],
            "zero_point": now["zero_point"],
            "ny": now["shape"][0],
            "nx": now["shape"][1],
            "valid_box": json.dumps(now["valid_box"]),
            "corners": json.dumps(np.asarray(fresh.corners).tolist()),
            "n_pixels": len(fresh.pixels),
            "path": entry.path,
        }
        fields = [name for name, value in expected.items() if row[name] != value]
        try:
            stored = json.loads(stored_header or "{}")
        except (TypeError, ValueError):
            stored = {}
        if not isinstance(stored, dict):
            stored = {}
        fields += [f"header.{name}" for name in now if stored.get(name) != now[name]]
        if (
            not isinstance(stored_header, str) or json_sha256(stored_header) != row["header_sha256"]
        ) and not any(f.startswith("header.") for f in fields):
            fields.append("header")
        return tuple(fields) or ("checksum",)

    def by_ids(self, ids: Sequence[int]) -> list[IndexedExposure]:
        """The usable inputs of row ``ids``, in the order of ``ids``, each checked
        against its checksum.

        Raises
        ------
        CellCoaddFormatError
            When a row is missing or no longer usable (re-indexed, bad or vanished).
        IndexRowError
            When a row does not match its checksum (names the file, row and fields).
        """
        rows = {row["id"]: row for row in self._rows(ids)}
        missing = [i for i in ids if i not in rows]
        if missing:
            raise CellCoaddFormatError(
                self.path, f"rows {missing[:5]} are gone or unusable: the index changed"
            )
        return [self._checked(rows[i]) for i in ids]

    def check_footprints(self) -> None:
        """Check that every usable row has the footprint pixels it was stored with (one
        count over the spatial key; rows are named only when the totals differ).

        Raises
        ------
        IndexRowError
            Naming the first rows whose pixels are missing or extra.
        """
        (stored,) = self._db.execute("SELECT COUNT(*) FROM footprint").fetchone()
        (expected,) = self._db.execute(
            "SELECT COALESCE(SUM(n_pixels), 0) FROM exposures WHERE status = 'ok'"
        ).fetchone()
        if stored == expected:
            return
        wrong = self._db.execute(
            "SELECT e.id, e.path, e.n_pixels, COUNT(f.pixel) FROM exposures e LEFT JOIN "
            "footprint f ON f.exposure = e.id WHERE e.status = 'ok' GROUP BY e.id "
            "HAVING COUNT(f.pixel) != e.n_pixels ORDER BY e.id LIMIT 5"
        ).fetchall()
        named = "; ".join(f"{path} (row {i}: {n} of {want} pixels)" for i, path, want, n in wrong)
        raise IndexRowError(
            f"{self.path}: the spatial key has {stored} footprint pixels where the rows "
            f"list {expected}{': ' + named if named else ''}: run `cellcoadd index` again",
            path=wrong[0][1] if wrong else self.path,
            row=int(wrong[0][0]) if wrong else None,
            fields=("footprint",),
        )

    def bad_files(self) -> list[tuple[str, str]]:
        """``(path, reason)`` of every file that is bad or vanished."""
        return [
            (path, reason or status)
            for path, status, reason in self._db.execute(
                "SELECT path, status, reason FROM exposures WHERE status != 'ok' ORDER BY path"
            )
        ]

    def bands(self) -> list[str]:
        """The bands of the usable inputs, sorted."""
        return [row[0] for row in self._db.execute(
            "SELECT DISTINCT band FROM exposures WHERE status = 'ok' ORDER BY band"
        )]  # fmt: skip

    def footprint_pixels(self, bands: Sequence[str] | None = None) -> np.ndarray:
        """The distinct HEALPix pixels (nested, :attr:`nside`) of the usable inputs' footprints
        (of ``bands`` only, when given): where the index has data."""
        sql = "SELECT DISTINCT f.pixel FROM footprint f"
        params: list[Any] = []
        if bands is not None:
            marks = ", ".join("?" for _ in bands)
            sql += f" JOIN exposures e ON e.id = f.exposure WHERE e.band IN ({marks})"
            params = list(bands)
        return np.fromiter((row[0] for row in self._db.execute(sql, params)), dtype=np.int64)

    def unusable(self) -> list[UnusableFile]:
        """Every file the index marks bad or vanished, with where it was (when known)."""
        out = []
        for row in self._db.execute(
            "SELECT id, path, status, reason, band, corners FROM exposures "
            "WHERE status != 'ok' ORDER BY path"
        ):
            try:
                corners = None if row["corners"] is None else np.asarray(json.loads(row["corners"]))
            except ValueError:
                corners = None
            out.append(
                UnusableFile(
                    row["path"], row["status"], row["reason"] or row["status"], row["band"], corners
                )
            )
        return out

    def stats(self) -> dict[str, Any]:
        """Files by status, bands (files and visits), visits, summed footprint area (deg^2)
        and the union area covered (deg^2, from the HEALPix key: an upper bound)."""
        db = self._db
        by_status = dict(db.execute("SELECT status, COUNT(*) FROM exposures GROUP BY status"))
        bands = {
            band: {"files": files, "visits": visits, "area_deg2": round(area or 0.0, 4)}
            for band, files, visits, area in db.execute(
                "SELECT band, COUNT(*), COUNT(DISTINCT visit), SUM(area_deg2) FROM exposures "
                "WHERE status = 'ok' GROUP BY band ORDER BY band"
            )
        }
        (visits,) = db.execute(
            "SELECT COUNT(DISTINCT visit) FROM exposures WHERE status = 'ok'"
        ).fetchone()
        (pixels,) = db.execute("SELECT COUNT(DISTINCT pixel) FROM footprint").fetchone()
        (area,) = db.execute("SELECT SUM(area_deg2) FROM exposures WHERE status = 'ok'").fetchone()
        return {
            "path": self.path,
            "nside": self.nside,
            "files": sum(by_status.values()),
            "ok": by_status.get("ok", 0),
            "bad": by_status.get("bad", 0),
            "vanished": by_status.get("vanished", 0),
            "visits": visits,
            "bands": bands,
            "footprint_area_deg2": round(area or 0.0, 4),
            "covered_area_deg2": round(pixels * hpgeom.nside_to_pixel_area(self.nside), 4),
        }


#: Values per ``IN (...)`` list (SQLite allows 999 parameters in old versions).
_CHUNK = 900

#: Most HEALPix pixels a query region may cover (128 MiB of pixel numbers): an LSST tract
#: (1.7 deg on a side) covers ~4 million at the finest nside, 65536.
_MAX_QUERY_PIXELS = 1 << 24

#: Why a damaged row not read again in an update is marked bad.
_DAMAGED_ROW = "its index row was damaged (it disagrees with its checksum): index the file again"

#: The type each column an :class:`IndexedExposure` takes has in a row as stored.
_ROW_TYPES: dict[str, type] = {
    "path": str, "visit": int, "detector": int, "band": str, "checksum": str, "entry": str,
    "corners": str, "files": str,
}  # fmt: skip


def _row_intact(row: sqlite3.Row, deep: bool) -> bool:
    """Whether a stored row agrees with its checksum and its header with the header's
    SHA-256 (~10 us); ``deep``: and every JSON column decodes as its kind (~50 us)."""
    header = row["header"]
    if (
        row_checksum(row) != row["checksum"]
        or not isinstance(header, str)
        or json_sha256(header) != row["header_sha256"]
    ):
        return False
    if deep:
        try:
            described = header_from_json(header)
            stored = json.loads(header)
            entry = ManifestEntry.model_validate_json(row["entry"])
            corners = np.asarray(json.loads(row["corners"]), dtype=float)
            files = _decoded_files(row["files"])
            # the columns queries and plans use are those of the header
            return (
                files is not None
                and entry_files(entry) == [f[0] for f in files]
                and entry.path == row["path"]
                and corners.shape == (4, 2)
                and _same_corners(corners, footprint_corners(described))
                and [row[k] for k in ("visit", "detector", "band", "zero_point")]
                == [stored[k] for k in ("visit", "detector", "band", "zero_point")]
                and [row["ny"], row["nx"]] == stored["shape"]
                and row["valid_box"] == json.dumps(stored["valid_box"])
            )
        except (CellCoaddError, TypeError, ValueError, KeyError, IndexError, OverflowError):
            return False
    return True


def _decoded_files(text: Any) -> list[list[Any]] | None:
    """The ``files`` column of a row (``[path, size, mtime_ns, sha256]`` each), or None
    when it does not decode as that (a damaged row: read its file again)."""
    try:
        files = json.loads(text)
    except (TypeError, ValueError):
        return None
    if not isinstance(files, list) or not all(
        isinstance(f, list) and len(f) == 4 and isinstance(f[0], str)
        and all(isinstance(v, int) and not isinstance(v, bool) for v in f[1:3])
        and (f[3] is None or isinstance(f[3], str))
        for f in files
    ):  # fmt: skip
        return None
    return files


def _stale(files: list[list[Any]] | None, entry: ManifestEntry, checksum: bool) -> bool:
    """Whether an indexed input must be read again: other files, or a file changed."""
    if files is None:
        return True
    if [f[0] for f in files] != entry_files(entry):
        return True
    if checksum and any(f[3] is None for f in files):
        return True  # no checksum stored yet
    return any(FileStamp(p, s, m, h).changed(checksum) is not None for p, s, m, h in files)


def _exists(files: list[list[Any]] | None, path: Any) -> bool:
    first = files[0][0] if files else path
    return isinstance(first, str) and os.path.exists(first)


class _Identities:
    """Which file holds each (visit, detector) among the usable rows, during an update:
    a second file with the identity of another is refused (bad), the first stays."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._owner: dict[tuple[Any, Any], str] = {}
        self._key: dict[str, tuple[Any, Any]] = {}
        for path, visit, detector in db.execute(
            "SELECT path, visit, detector FROM exposures WHERE status = 'ok' ORDER BY id"
        ):
            self._owner.setdefault((visit, detector), path)
            self._key[path] = (visit, detector)

    def claim(self, item: Described) -> Described:
        """``item``, or ``item`` made bad when another file holds its identity."""
        path = item.entry.path
        old = self._key.pop(path, None)
        if old is not None and self._owner.get(old) == path:
            del self._owner[old]  # its row is replaced below
        if item.reason is not None or item.header_json is None:
            return item
        header = json.loads(item.header_json)
        key = (header["visit"], header["detector"])
        other = self._owner.get(key)
        if other is not None and other != path:
            reason = (
                f"(visit={key[0]}, detector={key[1]}) is already indexed from {other}: two "
                "files cannot be one exposure"
            )
            return Described(item.entry, item.files, reason=reason)
        self._owner[key] = path
        self._key[path] = key
        return item
