"""File stamps and hashing: one home for "is this still the file we saw" and for the
SHA-256s the index, the ledger and the run reports store.

A :class:`FileStamp` is a file as seen once: path, size, modification time (ns) and,
when asked for, the SHA-256 of its bytes. :func:`json_sha256` hashes JSON-able records
in one canonical form (sorted keys, no spaces), so that the same record always has the
same hash whatever process or Python version writes it.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from typing import Any


def file_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes, hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        while chunk := file.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def json_sha256(record: Any) -> str:
    """SHA-256 (hex) of a JSON-able record in canonical form (sorted keys, no spaces)."""
    text = json.dumps(record, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class FileStamp:
    """A file as it was seen: path, size (bytes), mtime (ns), SHA-256 (or None)."""

    path: str
    size: int
    mtime_ns: int
    sha256: str | None = None

    @classmethod
    def of(cls, path: str, checksum: bool = False) -> FileStamp:
        info = os.stat(path)
        digest = file_sha256(path) if checksum else None
        return cls(path, int(info.st_size), int(info.st_mtime_ns), digest)

    def changed(self, checksum: bool = False) -> str | None:
        """Why the file on disk is no longer this one (None: unchanged): one ``stat``
        (and, with ``checksum``, a read of every byte)."""
        try:
            now = os.stat(self.path)
        except FileNotFoundError:
            return f"{self.path} vanished"
        except OSError as err:
            return f"{self.path} cannot be read ({err.strerror or err})"
        if int(now.st_size) != self.size or int(now.st_mtime_ns) != self.mtime_ns:
            return f"{self.path} changed (size/mtime)"
        if checksum and self.sha256 is not None and file_sha256(self.path) != self.sha256:
            return f"{self.path} changed (checksum)"
        return None

    def as_list(self) -> list[Any]:
        """``[path, size, mtime_ns, sha256]``: the stored form."""
        return [self.path, self.size, self.mtime_ns, self.sha256]
