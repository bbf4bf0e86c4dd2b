"""Start writing a file to disk while it is still being written (Linux ``sync_file_range``).

An atomic write ends with ``fsync`` (:mod:`cellcoadd.io._files.atomic`): until then the bytes sit
in the page cache, and the kernel only starts writing them back once a tenth of the memory
is dirty or after 30 s. A patch file of ~1 GB is therefore written to disk only by the final
``fsync``, after all the work of formatting and checksumming it, as ``dd conv=fsync`` does.
:class:`EarlyWriteback` watches the file while it is written and, each time it has grown by
:data:`STEP` bytes, asks the kernel to start writing back what is there
(``sync_file_range(SYNC_FILE_RANGE_WRITE)``: it starts the write and returns, waits for
nothing, changes no data and does not drop the page cache), so the disk works while the
writer computes and the final ``fsync`` only waits for the tail.

This is only a head start: durability still comes from the ``fsync`` that follows (errors
of the early write are reported by that ``fsync``, as the kernel keeps them for it).
Where ``sync_file_range`` does not exist (not Linux), nothing is done.
"""

from __future__ import annotations

import ctypes
import os
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from types import TracebackType

#: Bytes written between two requests to start writing back (Linux only).
STEP = 32 << 20
#: Seconds between two looks at the file's size.
POLL = 0.005
_SYNC_FILE_RANGE_WRITE = 2


def _sync_file_range() -> Callable[[int, int, int, int], int] | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        function = ctypes.CDLL(None, use_errno=True).sync_file_range  # the C library's
    except (OSError, AttributeError):
        return None
    function.argtypes = [ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint]
    function.restype = ctypes.c_int
    return function


_START_WRITEBACK = _sync_file_range()


class EarlyWriteback:
    """While the ``with`` block runs, start the write-back of ``path`` as it grows.

    A background thread looks at the file every :data:`POLL` seconds (it may not exist
    yet: the writer creates it) and starts the write-back of everything written so far
    whenever :data:`STEP` more bytes are there. Leaving the block stops the thread; it never
    raises (a failed request only means the data are written back later, by ``fsync``).

    Parameters
    ----------
    path : path-like
        The file being written.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(os.fspath(path))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> EarlyWriteback:
        if _START_WRITEBACK is not None:
            self._thread = threading.Thread(
                target=self._run, name="cellcoadd-writeback", daemon=True
            )
            self._thread.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def _run(self) -> None:
        descriptor = None
        started = 0  # file size when the write-back was last started, bytes
        try:
            while not self._stop.wait(POLL):
                if descriptor is None:
                    try:
                        descriptor = os.open(self.path, os.O_RDONLY)
                    except OSError:
                        continue  # not created yet
                size = os.fstat(descriptor).st_size
                if size - started >= STEP and _START_WRITEBACK is not None:
                    _START_WRITEBACK(descriptor, 0, 0, _SYNC_FILE_RANGE_WRITE)
                    started = size
        except OSError:
            pass  # only a head start: fsync writes whatever was not written back
        finally:
            if descriptor is not None:
                os.close(descriptor)
