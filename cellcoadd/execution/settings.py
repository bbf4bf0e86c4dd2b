"""Settings of the processes that build cells: glibc's allocator and dask's housekeeping.

One home for the numbers: the ``cellcoadd`` command applies :data:`MMAP_THRESHOLD` and
:data:`TRIM_THRESHOLD` to its own process (:mod:`cellcoadd.cli.allocator`), and dask
workers get them, with :data:`ARENA_MAX` and quieter housekeeping, through
:data:`DASK_WORKER_CONFIG` (or :func:`dask_worker_environment` for workers started
elsewhere). Results never depend on them; CPU does.
"""

from __future__ import annotations

import ctypes
import os
import sys
from typing import Any

#: glibc ``M_MMAP_THRESHOLD`` (bytes): arrays up to 32 MB stay on the heap instead of being
#: mapped and unmapped each time (a third of a patch build's system CPU otherwise)
MMAP_THRESHOLD = 32 * 2**20
#: glibc ``M_TRIM_THRESHOLD`` (bytes): up to 256 MB of freed heap memory is kept for the
#: next arrays instead of being returned to the system and faulted in again
TRIM_THRESHOLD = 256 * 2**20
#: glibc's arena count for dask workers (which run their tasks in a thread)
ARENA_MAX = 1

#: dask settings for the processes that build cells (set them before a cluster starts:
#: ``dask.config.set(DASK_WORKER_CONFIG)``, or under the same keys in the dask YAML of the
#: worker machines). Results do not depend on them; CPU does:
#:
#: * ``MALLOC_MMAP_THRESHOLD_`` keeps arrays above 128 kB on the heap: the nanny's default
#:   ``MALLOC_TRIM_THRESHOLD_`` makes glibc map and unmap each, and cells build up to
#:   ~1.9x slower; ``MALLOC_TRIM_THRESHOLD_`` of 256 MB (instead of the nanny's 64 kB)
#:   keeps freed heap memory for the next arrays instead of returning it to the system and
#:   faulting it in again (system CPU of a patch build halved: 1.5 s instead of 2.9 s of
#:   18 s, the same peak RSS);
#: * ``MALLOC_ARENA_MAX`` of 1: a worker runs its tasks in a thread, and glibc gives a
#:   thread its own arena, whose 64 MB heaps are unmapped whenever they empty, whatever
#:   the trim threshold; in the main arena a tract run's two workers fault 35-40% fewer
#:   pages (9 patches of 36 cells: ~390,000 minor faults instead of 540,000-890,000, and
#:   0.3-1.5 s less system CPU of ~60 s);
#: * the statistical profiler (the task's stack sampled every 10 ms), the event loops'
#:   20 ms tick, the 100 ms memory monitor and the GIL monitor cost 10-14% of a busy
#:   worker's CPU (measured on 2 single-threaded workers); with these values, ~3%.
DASK_WORKER_CONFIG: dict[str, Any] = {
    "distributed.nanny.pre-spawn-environ.MALLOC_MMAP_THRESHOLD_": MMAP_THRESHOLD,
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": TRIM_THRESHOLD,
    "distributed.nanny.pre-spawn-environ.MALLOC_ARENA_MAX": ARENA_MAX,
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.admin.system-monitor.gil.enabled": False,
    "distributed.worker.memory.monitor-interval": "1s",
}


#: ``mallopt`` parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8


def apply_malloc_settings(*, arena_max: int | None = None) -> bool:
    """Apply :data:`MMAP_THRESHOLD` and :data:`TRIM_THRESHOLD` (and ``arena_max`` arenas,
    when given) to this process's allocator (glibc only): whether any was applied.

    Nothing is done on other C libraries, or for a setting the environment already gives
    (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``, ``MALLOC_ARENA_MAX``). For a
    process that glibc started with these environment variables this changes nothing; a
    worker forked from another process needs it, since glibc reads them only at start.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the process's own C library
    except (OSError, AttributeError):  # not glibc (e.g. musl has no mallopt)
        return False
    settings = [
        ("MALLOC_MMAP_THRESHOLD_", _M_MMAP_THRESHOLD, MMAP_THRESHOLD),
        ("MALLOC_TRIM_THRESHOLD_", _M_TRIM_THRESHOLD, TRIM_THRESHOLD),
    ]
    if arena_max is not None:
        settings.append(("MALLOC_ARENA_MAX", _M_ARENA_MAX, arena_max))
    applied = False
    for variable, parameter, value in settings:
        if variable not in os.environ:
            applied = bool(mallopt(ctypes.c_int(parameter), ctypes.c_int(value))) or applied
    return applied


def dask_worker_environment() -> dict[str, str]:
    """:data:`DASK_WORKER_CONFIG` as environment variables, for workers started elsewhere
    (``dask worker`` on a cluster node, a dask-jobqueue job script), which read their own
    configuration: ``MALLOC_MMAP_THRESHOLD_`` itself, and ``DASK_A__B__C`` for ``a.b.c``.

    Examples
    --------
    >>> env = dask_worker_environment()
    >>> env["DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED"], env["MALLOC_MMAP_THRESHOLD_"]
    ('False', '33554432')
    """
    prefix = "distributed.nanny.pre-spawn-environ."
    environment = {}
    for key, value in DASK_WORKER_CONFIG.items():
        if key.startswith(prefix):
            environment[key[len(prefix) :]] = str(value)
        else:
            parts = (part.upper().replace("-", "_") for part in key.split("."))
            environment["DASK_" + "__".join(parts)] = str(value)
    return environment
