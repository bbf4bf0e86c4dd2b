"""Choosing where independent tasks run: here, a local process pool, or a dask cluster."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from concurrent.futures import Executor, ProcessPoolExecutor
from typing import Any

from cellcoadd.errors import MissingDependencyError
from cellcoadd.execution.settings import ARENA_MAX, DASK_WORKER_CONFIG, apply_malloc_settings


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
    Client = import_distributed().Client

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


def import_distributed() -> Any:
    """The ``distributed`` module (the ``dask`` extra).

    Raises
    ------
    MissingDependencyError
        When dask.distributed is not installed.
    """
    try:
        import distributed
    except ImportError:
        raise MissingDependencyError(
            "runs on several workers or a scheduler need dask.distributed: "
            "pip install 'cellcoadd[dask]' (or run with --workers 1)",
            package="distributed",
        ) from None
    return distributed


def _malloc_settings_plugin(distributed: Any) -> Any:
    """A worker plugin applying :func:`~cellcoadd.execution.settings.apply_malloc_settings`
    (with :data:`~cellcoadd.execution.settings.ARENA_MAX`) in each worker as it starts."""

    class MallocSettings(distributed.WorkerPlugin):
        name = "cellcoadd-malloc-settings"

        def setup(self, worker: Any) -> None:
            apply_malloc_settings(arena_max=ARENA_MAX)

    return MallocSettings()


def local_cluster(workers: int) -> tuple[Any, Callable[[], None]]:
    """A ``distributed.Client`` on a new ``LocalCluster`` of ``workers`` processes (one
    thread each) and how to close both.

    A worker that dies fails its task at once (``allowed-failures`` 0), so that the
    caller's own retries count it; the workers get :data:`DASK_WORKER_CONFIG`.

    Raises
    ------
    MissingDependencyError
        When dask.distributed is not installed.
    """
    distributed = import_distributed()
    import dask

    settings = {**DASK_WORKER_CONFIG, "distributed.scheduler.allowed-failures": 0}
    if sys.platform.startswith("linux"):
        # forked workers start with this process's modules imported: ~1.5 s (and as many
        # CPU s per worker) less than spawned ones, which import cellcoadd, GalSim and
        # numba again; a worker exits when this process does, however it ends
        settings["distributed.worker.multiprocessing-method"] = "fork"
    with dask.config.set(settings):
        cluster = distributed.LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",  # any free port: no clash with another cluster
        )
        client = distributed.Client(cluster)
    # glibc reads the environment's allocator settings only when a process starts: a
    # forked worker (and one the nanny starts again) is given them here
    register = getattr(client, "register_plugin", None) or client.register_worker_plugin
    register(_malloc_settings_plugin(distributed))

    def close() -> None:
        # every result is written and recorded by now: a worker slow to exit is killed,
        # which is no news to the user ("Worker process still alive after 4.0 seconds")
        nanny = logging.getLogger("distributed.nanny")
        level = nanny.level
        nanny.setLevel(logging.ERROR)
        try:
            client.close()
            cluster.close()
        finally:
            nanny.setLevel(level)

    return client, close
