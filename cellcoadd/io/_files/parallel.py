"""Threads for the writers' number crunching: what numpy and ``zlib`` do with the GIL released.

Writing a patch file costs, besides the bytes, a pass or two over every pixel for the
checksums (FITS DATASUM and CRC-32 after a big-endian copy, HDF5 Fletcher-32). Those passes
are numpy reductions and copies and ``zlib.crc32``, which release the GIL, so on a machine
with a free core they run side by side. :func:`map_in_threads` runs a function over items
in up to :data:`THREADS` threads and returns the results in the items' order; what the
writers write never depends on which thread did what or when (tests compare the bytes with
single-threaded writes).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

Item = TypeVar("Item")
Result = TypeVar("Result")

#: Threads a write uses at most (1: everything in the calling thread).
THREADS = min(2, os.cpu_count() or 1)


def map_in_threads(
    function: Callable[[Item], Result], items: Sequence[Item], threads: int | None = None
) -> list[Result]:
    """``[function(item) for item in items]``, computed in up to ``threads`` threads.

    Parameters
    ----------
    function : callable
        Called once per item, from any of the threads (it must be safe to call from
        several threads at once; what it shares must be read-only or thread-local).
    items : sequence
        The items, taken in order by whichever thread is free.
    threads : int, optional
        At most this many threads (the calling thread waits); None: :data:`THREADS`.
        With 1, or a single item, everything runs in the calling thread.

    Returns
    -------
    list
        The results, in the order of ``items``.

    Raises
    ------
    Exception
        The first exception (in item order) raised by ``function``; items not started
        yet are then skipped, and the call returns only once no thread is running.
    """
    threads = min(THREADS if threads is None else threads, len(items))
    if threads <= 1:
        return [function(item) for item in items]
    with ThreadPoolExecutor(threads, thread_name_prefix="cellcoadd-write") as executor:
        futures = [executor.submit(function, item) for item in items]
        try:
            return [future.result() for future in futures]
        except BaseException:
            for future in futures:
                future.cancel()
            raise
