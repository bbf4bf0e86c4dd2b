"""Where tasks run: here, a local process pool or a dask cluster, with retries; the
settings of the processes that build cells.

Below both :mod:`cellcoadd.builder` (blocks of cells) and :mod:`cellcoadd.pipelines`
(patches of a survey run): one home for pools, clusters, clients, retries and worker
settings.
"""

from cellcoadd.execution.executors import (
    dask_client,
    import_distributed,
    local_cluster,
    resolve_executor,
)
from cellcoadd.execution.runner import (
    Outcome,
    error_text,
    is_deterministic,
    parts_per_task,
    run_here,
    run_on_dask,
)
from cellcoadd.execution.settings import DASK_WORKER_CONFIG, dask_worker_environment

__all__ = [
    "DASK_WORKER_CONFIG",
    "Outcome",
    "dask_client",
    "dask_worker_environment",
    "error_text",
    "import_distributed",
    "is_deterministic",
    "local_cluster",
    "parts_per_task",
    "resolve_executor",
    "run_here",
    "run_on_dask",
]
