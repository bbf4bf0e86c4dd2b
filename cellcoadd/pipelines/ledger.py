"""The run ledger of a tract run's output directory, and the lock that keeps one run there.

The ledger (``DIR/ledger.sqlite``, stdlib :mod:`sqlite3`) has one row per patch: its state
(``pending``, ``done``, ``failed``, ``no_inputs``), the signature of what it is built from
(:func:`patch_signature`: config hash, seed, library version, band, format, sky map, and
the path, size and mtime of every input file), the output's path, size and SHA-256, the
number of attempts, the last error, and the worker's summary (cells, inputs, CPU, wall).
A patch is up to date when it is ``done`` with the signature it would be built with now
and its output is on disk with the recorded size; anything else is built again.

Only the process that runs the tract writes the ledger (workers return summaries), one
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
import hashlib
import json
import os
import socket
import sqlite3
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cellcoadd.errors import CellCoaddFormatError, RunLockedError
from cellcoadd.io._files.path_gate import gate_write

LEDGER_NAME = "ledger.sqlite"
LOCK_NAME = ".run.lock"
SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS patches (
    tract INTEGER NOT NULL,
    px INTEGER NOT NULL,
    py INTEGER NOT NULL,
    band TEXT,
    state TEXT NOT NULL CHECK (state IN ('pending', 'done', 'failed', 'no_inputs')),
    signature TEXT NOT NULL,
    config_hash TEXT NOT NULL,
    seed INTEGER NOT NULL,
    version TEXT NOT NULL,
    inputs TEXT NOT NULL,
    output TEXT NOT NULL,
    checksum TEXT,
    size INTEGER,
    attempts INTEGER NOT NULL DEFAULT 0,
    error TEXT,
    summary TEXT,
    updated REAL NOT NULL,
    PRIMARY KEY (tract, px, py)
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
    return hashlib.sha256(config_json.encode()).hexdigest()


def patch_signature(fields: dict[str, Any]) -> str:
    """SHA-256 (hex) of everything a patch's bytes depend on (a JSON-able dict)."""
    text = json.dumps(fields, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class LedgerRow:
    """One patch in the ledger."""

    tract: int
    patch: tuple[int, int]
    band: str | None
    state: str
    signature: str
    output: str
    checksum: str | None
    size: int | None
    attempts: int
    error: str | None
    summary: dict[str, Any] | None
    inputs: list[Any]
    config_hash: str
    seed: int
    version: str

    def is_current(self, signature: str, verify: bool = False) -> bool:
        """Whether this patch is built with ``signature`` and its output is intact (size;
        with ``verify``, the SHA-256 of its bytes)."""
        if self.state != "done" or self.signature != signature:
            return False
        try:
            if os.path.getsize(self.output) != self.size:
                return False
        except OSError:
            return False
        if verify:
            from cellcoadd.io.exposures.index import file_sha256

            return file_sha256(self.output) == self.checksum
        return True


class Ledger:
    """The run ledger of an output directory (created if needed).

    Raises
    ------
    CellCoaddFormatError
        When ``DIR/ledger.sqlite`` is not a ledger of this schema version.
    """

    def __init__(self, out_dir: str | os.PathLike[str]):
        self.path = os.path.join(os.fspath(out_dir), LEDGER_NAME)
        # a FIFO, a device or a directory in its place is refused before SQLite opens it
        resolved = gate_write(self.path, what="run ledger")
        try:
            self._db = sqlite3.connect(resolved, timeout=60.0)
            self._db.executescript(_SCHEMA)
            with self._db:
                self._db.execute(
                    "INSERT OR IGNORE INTO meta VALUES ('schema_version', ?)",
                    (str(SCHEMA_VERSION),),
                )
            (version,) = self._db.execute(
                "SELECT value FROM meta WHERE key = 'schema_version'"
            ).fetchone()
        except sqlite3.DatabaseError as err:
            raise CellCoaddFormatError(self.path, f"not a run ledger ({err})") from None
        if version != str(SCHEMA_VERSION):
            raise CellCoaddFormatError(
                self.path, f"run ledger schema {version}, this library writes {SCHEMA_VERSION}"
            )

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> Ledger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def rows(self, tract: int | None = None) -> dict[tuple[int, tuple[int, int]], LedgerRow]:
        """Every patch of ``tract`` (all tracts when None), keyed ``(tract, (px, py))``."""
        sql = (
            "SELECT tract, px, py, band, state, signature, output, checksum, size, attempts, "
            "error, summary, inputs, config_hash, seed, version FROM patches"
        )
        params: tuple[Any, ...] = ()
        if tract is not None:
            sql += " WHERE tract = ?"
            params = (tract,)
        out = {}
        for row in self._db.execute(sql, params):
            item = LedgerRow(
                tract=row[0],
                patch=(row[1], row[2]),
                band=row[3],
                state=row[4],
                signature=row[5],
                output=row[6],
                checksum=row[7],
                size=row[8],
                attempts=row[9],
                error=row[10],
                summary=json.loads(row[11]) if row[11] else None,
                inputs=json.loads(row[12]),
                config_hash=row[13],
                seed=row[14],
                version=row[15],
            )
            out[(item.tract, item.patch)] = item
        return out

    def set(
        self,
        tract: int,
        patch: tuple[int, int],
        *,
        band: str | None,
        state: str,
        signature: str,
        config_hash: str,
        seed: int,
        version: str,
        inputs: list[Any],
        output: str,
        checksum: str | None = None,
        size: int | None = None,
        attempts: int = 0,
        error: str | None = None,
        summary: dict[str, Any] | None = None,
    ) -> None:
        """Record one patch (one transaction)."""
        with self._db:
            self._db.execute(
                "INSERT OR REPLACE INTO patches VALUES "
                "(?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    tract,
                    patch[0],
                    patch[1],
                    band,
                    state,
                    signature,
                    config_hash,
                    seed,
                    version,
                    json.dumps(inputs, separators=(",", ":")),
                    output,
                    checksum,
                    size,
                    attempts,
                    error,
                    None if summary is None else json.dumps(summary, separators=(",", ":")),
                    time.time(),
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
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
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
