"""Choosing where independent tasks run: here, a local process pool, or a dask cluster."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Executor, ProcessPoolExecutor
from typing import Any

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
    "distributed.nanny.pre-spawn-environ.MALLOC_MMAP_THRESHOLD_": 33554432,
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": 268435456,
    "distributed.nanny.pre-spawn-environ.MALLOC_ARENA_MAX": 1,
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.admin.system-monitor.gil.enabled": False,
    "distributed.worker.memory.monitor-interval": "1s",
}


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


def dask_client(scheduler: object) -> tuple[Any, Callable[[], None] | None]:
    """The ``distributed.Client`` for ``scheduler`` and how to release it.

    Parameters
    ----------
    scheduler : str or distributed.Client
        A dask.distributed scheduler address (a client is opened, and closed by the
        release function) or an existing client (returned as it is, left open).

    Returns
    -------
    client, release
        ``release`` is None for a client given here; otherwise call it when done.
    """
    from distributed import Client  # optional: the dask extra

    if isinstance(scheduler, Client):
        return scheduler, None
    client = Client(scheduler)  # ours: closed at the end, so nothing lingers
    return client, client.close


def resolve_executor(
    executor: Executor | None,
    workers: int,
    scheduler: object | None,
    *,
    initializer: Callable[..., None] | None = None,
    initargs: tuple[Any, ...] = (),
) -> tuple[Executor | None, Callable[[], None] | None]:
    """The executor to use and how to release it.

    Parameters
    ----------
    executor : Executor, optional
        Used as given (never shut down here).
    workers : int
        Size of a local process pool when neither ``executor`` nor ``scheduler`` is given;
        1 means run serially in this process (``None`` is returned).
    scheduler : str or distributed.Client, optional
        A dask.distributed scheduler address or client (see :func:`dask_client`); its
        ``concurrent.futures`` executor is returned.
    initializer, initargs
        Run in each process of a pool created here (not on other executors).

    Returns
    -------
    executor, release
        ``release`` is None when nothing here was created; otherwise call it when done.
    """
    if executor is not None:
        return executor, None
    if scheduler is not None:
        client, release = dask_client(scheduler)
        return client.get_executor(), release
    if workers > 1:
        pool = ProcessPoolExecutor(max_workers=workers, initializer=initializer, initargs=initargs)
        return pool, lambda: pool.shutdown(wait=True, cancel_futures=True)
    return None, None
