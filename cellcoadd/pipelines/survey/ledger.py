"""The run ledger of a survey run's output directory, and the lock that keeps one run there.

The ledger (``DIR/ledger.sqlite``, stdlib :mod:`sqlite3`) has one row per patch and band
(:class:`~cellcoadd.pipelines.survey.records.PatchRecord`): its state (``pending``,
``done``, ``failed``, ``no_inputs``), the signature of what it is built from
(:func:`patch_signature`: config hash, seed, library version, band, format, sky map,
tract, patch, and the checksum of every index row it used), the output's path (relative
to DIR), size and SHA-256, the attempts and why earlier ones failed, the last error, and
the worker's summary (cells, inputs, CPU, wall). A patch is up to date when it is
``done`` with the signature it would be built with now and its output is on disk with
the recorded size; anything else is built again. The ledger also records the sky map
(a directory holds one sky map's patches) and its layout version (``PRAGMA
user_version``; ``PRAGMA application_id`` marks the file as a ledger).

Only the process that runs the survey writes the ledger (workers return summaries), one
transaction per patch, so a ``kill -9`` at any moment leaves a consistent ledger: at
worst a patch written but not yet recorded, which the next run builds again (the same
bytes). The ledger uses SQLite's default rollback journal, which, unlike WAL, also works
on network file systems that lack shared memory, as long as their POSIX locks work.

:class:`RunLock` is an exclusive :func:`fcntl.flock` on ``DIR/.run.lock``, held for the
whole run; a second run on the same directory is refused with an error naming the
holder (host, pid, start time, command). The kernel releases the lock when its process
dies, however it dies, so a killed run never leaves a stale lock. On NFS, ``flock`` is
emulated with ``fcntl`` byte-range locks (Linux >= 2.6.12), which need a working lock
manager (``lockd``); Lustre needs the ``flock`` mount option, GPFS supports it natively.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import sqlite3
import stat
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from cellcoadd.errors import CellCoaddFormatError, ConfigError, RunLockedError
from cellcoadd.io._files.path_gate import gate_create, open_nofollow
from cellcoadd.io._files.sqlite_files import open_own_database
from cellcoadd.io._files.stamps import file_sha256, json_sha256
from cellcoadd.pipelines.survey.records import PatchKey, PatchRecord, PatchState

LEDGER_NAME = "ledger.sqlite"
LOCK_NAME = ".run.lock"
#: Layout of the output directory and the ledger (``PRAGMA user_version``). 2: the band
#: in every path and key (``BAND/tract_T/patch_X_Y.fits``), paths relative to DIR, typed
#: records, the sky map recorded.
SCHEMA_VERSION = 2
#: ``PRAGMA application_id`` of a run ledger ("CCXL").
APPLICATION_ID = 0x4343584C
#: the files SQLite creates next to a database (rollback journal; WAL files if enabled)
_SQLITE_COMPANIONS = ("-journal", "-wal", "-shm")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS patches (
    band TEXT NOT NULL,
    tract INTEGER NOT NULL,
    px INTEGER NOT NULL,
    py INTEGER NOT NULL,
    state TEXT NOT NULL CHECK (state IN ('pending', 'done', 'failed', 'no_inputs')),
    record TEXT NOT NULL,
    updated REAL NOT NULL,
    PRIMARY KEY (band, tract, px, py)
);
CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY,
    started REAL NOT NULL,
    finished REAL,
    host TEXT NOT NULL,
    pid INTEGER NOT NULL,
    command TEXT NOT NULL,
    planned INTEGER,
    built INTEGER,
    failed INTEGER
);
"""


def config_hash(config_json: str) -> str:
    """SHA-256 (hex) of a build configuration's JSON."""
    return json_sha256(json.loads(config_json))


def patch_signature(fields: dict[str, Any]) -> str:
    """SHA-256 (hex) of everything a patch's bytes depend on (a JSON-able dict)."""
    return json_sha256(fields)


def is_current(
    record: PatchRecord, signature: str, out_dir: str | os.PathLike[str], verify: bool = False
) -> bool:
    """Whether ``record`` is built with ``signature`` and its output (relative to
    ``out_dir``) is intact: its size, and with ``verify`` the SHA-256 of its bytes."""
    if record.state != PatchState.DONE or record.signature != signature:
        return False
    relative = Path(record.output)
    if relative.is_absolute() or ".." in relative.parts:
        return False  # a stored row never points outside DIR
    path = Path(out_dir) / relative
    try:
        # the file itself, not a link's target, and never a FIFO or device to hash
        info = path.lstat()
        if not stat.S_ISREG(info.st_mode) or info.st_size != record.size:
            return False
        return not verify or file_sha256(path) == record.checksum
    except OSError:
        return False


class Ledger:
    """The run ledger of an output directory (created if needed), for ``skymap_json``.

    Raises
    ------
    CellCoaddFormatError
        When ``DIR/ledger.sqlite`` is not a ledger of this layout version (an older
        layout is refused: give a new output directory).
    ConfigError
        When the ledger belongs to another sky map.
    """

    def __init__(self, out_dir: str | os.PathLike[str], skymap_json: str | None = None):
        self.path = os.path.join(os.fspath(out_dir), LEDGER_NAME)
        #: rows :meth:`records` could not read: ``"row N"`` -> why (names the ledger)
        self.unreadable: dict[str, str] = {}
        #: the same, for the rows whose key names a patch (that patch is built again)
        self.unreadable_patches: dict[PatchKey, str] = {}
        # a link (SQLite would create or change its target, outside DIR), a FIFO, a device
        # or a directory in its place, or in its journal's, is refused before SQLite opens it
        path = gate_create(self.path, what="run ledger", companions=_SQLITE_COMPANIONS)
        self._db = open_own_database(
            path,
            application_id=APPLICATION_ID,
            version=SCHEMA_VERSION,
            schema=_SCHEMA,
            what="run ledger",
            older=f"written by an older layout; give a new --out-dir instead of {out_dir}",
        )
        if skymap_json is None:
            return
        digest = json_sha256(json.loads(skymap_json))
        try:
            row = self._db.execute(
                "SELECT CAST(value AS BLOB) FROM meta WHERE key = 'skymap_sha256'"
            ).fetchone()
        except sqlite3.DatabaseError as err:
            self._db.close()
            raise CellCoaddFormatError(self.path, f"cannot read its sky map ({err})") from None
        if row is None:
            with self._db:
                self._db.executemany(
                    "INSERT INTO meta VALUES (?, ?)",
                    [("skymap_sha256", digest), ("skymap", skymap_json)],
                )
        elif row[0] != digest.encode():
            self._db.close()
            raise ConfigError(
                f"{out_dir} holds patches of another sky map (ledger {self.path}): give a "
                "new --out-dir, or the sky map those patches were built with"
            )

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> Ledger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def records(
        self, band: str | None = None, tract: int | None = None
    ) -> dict[PatchKey, PatchRecord]:
        """The patches of ``band`` and ``tract`` (every one when None), by key.

        A row that cannot be read (key columns of the wrong type, a record that is not a
        :class:`PatchRecord` in JSON, or one naming another patch) is left out, so a run
        builds that patch again (which replaces the row), and is named in
        :attr:`unreadable` with the ledger's path and the row's number and patch. Only
        the ledger file as a whole being unreadable raises.

        Raises
        ------
        CellCoaddFormatError
            When SQLite cannot read the table (names the ledger).
        """
        # raw bytes: a text column of invalid UTF-8 would stop the whole query in sqlite3
        sql = (
            "SELECT rowid, typeof(band), CAST(band AS BLOB), tract, px, py, "
            "CAST(record AS BLOB) FROM patches"
        )
        where: list[str] = []
        params: list[Any] = []
        if band is not None:
            where.append("band = ?")
            params.append(band)
        if tract is not None:
            where.append("tract = ?")
            params.append(tract)
        if where:
            sql += " WHERE " + " AND ".join(where)
        out = {}
        try:
            rows = self._db.execute(sql, params).fetchall()
        except sqlite3.DatabaseError as err:
            raise CellCoaddFormatError(self.path, f"cannot read the patches ({err})") from None
        for row in rows:
            read = _read_row(*row)
            if isinstance(read, PatchRecord):
                out[read.key] = read
                continue
            key, why = read
            message = f"{self.path}: row {row[0]} of the patches table is unreadable: {why}"
            self.unreadable[f"row {row[0]}"] = message
            if key is not None:
                self.unreadable_patches[key] = message
        return out

    def put(self, record: PatchRecord) -> None:
        """Record one patch (one transaction)."""
        self.put_many([record])

    def put_many(self, records: Iterable[PatchRecord]) -> None:
        """Record patches (one transaction)."""
        with self._db:
            self._db.executemany(
                "INSERT OR REPLACE INTO patches VALUES (?, ?, ?, ?, ?, ?, ?)",
                (
                    (r.band, r.tract, r.px, r.py, r.state.value, r.model_dump_json(), time.time())
                    for r in records
                ),
            )

    def start_run(self, command: str, planned: int) -> int:
        with self._db:
            cursor = self._db.execute(
                "INSERT INTO runs (started, host, pid, command, planned) VALUES (?, ?, ?, ?, ?)",
                (time.time(), socket.gethostname(), os.getpid(), command, planned),
            )
        return int(cursor.lastrowid or 0)

    def finish_run(self, run_id: int, built: int, failed: int) -> None:
        with self._db:
            self._db.execute(
                "UPDATE runs SET finished = ?, built = ?, failed = ? WHERE id = ?",
                (time.time(), built, failed, run_id),
            )


def _read_row(
    rowid: int,
    band_type: str,
    band: object,
    tract: object,
    px: object,
    py: object,
    record: object,
) -> PatchRecord | tuple[PatchKey | None, str]:
    """The record of a stored row, or why it cannot be read (naming its patch if known)."""
    band_text = None
    if band_type == "text" and isinstance(band, bytes):  # a blob never matches band = ?
        try:
            band_text = band.decode("utf-8")
        except UnicodeDecodeError:
            band_text = None
    numbers = (tract, px, py)
    if band_text is None or not all(isinstance(n, int) for n in numbers):
        return None, (
            f"its key is not a band and three integers (band {band!r}, tract {tract!r}, "
            f"patch {px!r},{py!r}); that row is ignored: remove it"
        )
    key = PatchKey(band_text, *numbers)  # type: ignore[arg-type]
    if not isinstance(record, bytes):
        return key, f"{key}: no record ({record!r}); that patch is built again"
    try:
        parsed = PatchRecord.model_validate_json(record)
    except ValueError as err:
        why = _first_error(err)
        return key, f"{key}: its record is not a patch record ({why}); that patch is built again"
    if parsed.key != key:
        return key, f"{key}: its record is of {parsed.key}; that patch is built again"
    stem = f"{key.band}/tract_{key.tract}/patch_{key.px}_{key.py}"
    if parsed.output not in (stem + ".fits", stem + ".h5"):
        return key, (
            f"{key}: its record names the output {parsed.output!r}, not this patch's; that "
            "patch is built again"
        )
    return parsed


def _first_error(err: ValueError) -> str:
    """The first problem a validation error names, on one short line."""
    if isinstance(err, ValidationError) and err.errors():
        first = err.errors()[0]
        where = ".".join(str(part) for part in first.get("loc", ()))
        text = f"{where}: {first['msg']}" if where else str(first["msg"])
    else:
        text = str(err)
    text = " ".join(text.split())
    return text if len(text) <= 200 else text[:197] + "..."


class RunLock:
    """An exclusive lock on an output directory for one run (``with RunLock(dir):``).

    Raises
    ------
    RunLockedError
        When another process holds it: names the directory and the holder.
    """

    def __init__(self, out_dir: str | os.PathLike[str], command: str | None = None):
        self.path = Path(out_dir) / LOCK_NAME
        self.command = command or " ".join(sys.argv)
        self._fd: int | None = None

    def __enter__(self) -> RunLock:
        # never through a symbolic link (its target would be truncated), never a FIFO or a
        # device (opened non-blocking and checked on the descriptor)
        fd = open_nofollow(self.path, what="run lock")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 4096, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise RunLockedError(
                f"{self.path.parent}: another run is using this directory ({holder}); wait "
                "for it to finish, or give another --out-dir"
            ) from None
        holder = (
            f"host {socket.gethostname()}, pid {os.getpid()}, started "
            f"{time.strftime('%Y-%m-%d %H:%M:%S')}, command: {self.command}"
        )
        os.ftruncate(fd, 0)
        os.pwrite(fd, holder.encode(), 0)
        self._fd = fd
        return self

    def __exit__(self, *exc: object) -> None:
        if self._fd is not None:
            os.ftruncate(self._fd, 0)
            os.close(self._fd)  # releases the lock
            self._fd = None
