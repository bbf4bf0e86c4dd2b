"""Guards of every patch-file read: the path must be a non-empty regular file, and any
library failure becomes a :class:`~cellcoadd.errors.CellCoaddFormatError` naming it."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.io._files.path_gate import gate_read
from cellcoadd.io._fits.cfitsio_messages import clear_cfitsio_messages


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


def check_path_readable(path: str) -> int:
    """Size of ``path`` in bytes; FileNotFoundError if absent, CellCoaddFormatError if empty
    or not a regular file (a directory, a pipe or a device could block or mislead a reader;
    :func:`~cellcoadd.io._files.path_gate.gate_read`)."""
    return os.path.getsize(gate_read(path))
