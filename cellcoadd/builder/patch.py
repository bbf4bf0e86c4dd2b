"""Coadding every cell of a patch, in parallel on any ``concurrent.futures`` executor.

Each cell is an independent task that receives only the exposures near it; its result
depends only on its inputs and the seed, so the patch is bit-identical whatever the
executor and the number of workers. Inputs are sent to each worker once, never with
every task: a process pool created here installs them in each process (its initializer)
and tasks carry indices; on a dask cluster they are scattered once, then copied to every
worker, and tasks carry references to them. Inputs given as exposure sources
(:class:`~cellcoadd.model.sources.ExposureSource`: paths and options) weigh nothing:
which cells they serve is decided from their headers, and each worker loads the pixels
it needs, one exposure cut to one cell at a time, so memory does not grow with the
number of exposures and no pixel crosses a process boundary except finished cells. A
failing cell stops the build with an error naming the cell and carrying the worker's
traceback.
"""

from __future__ import annotations

import contextlib
import traceback
from collections.abc import Sequence
from concurrent.futures import (
    BrokenExecutor,
    Executor,
    Future,
    ProcessPoolExecutor,
    as_completed,
)
from typing import Any

from tqdm.auto import tqdm

from cellcoadd._version import __version__
from cellcoadd.builder.cell import build_cell, check_mask_bits, check_unique_inputs
from cellcoadd.builder.executors import dask_client, resolve_executor
from cellcoadd.builder.select import exposures_near_cells, rough_exposure_box
from cellcoadd.errors import CellBuildError
from cellcoadd.geometry.tract import Cell, Patch
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.inputs import check_band_name
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.patch_coadd import FORMAT_VERSION, PatchCoadd, PatchMetadata
from cellcoadd.model.sources import DescribedSource, ExposureSource, describe, header_of

Input = Exposure | DescribedSource

# The inputs of the build, installed once in each process of a pool this module creates
# (its initializer), so that cell tasks carry input indices instead of pixels.
# Per-process transport state only: every result depends on the task's arguments alone.
_pool_inputs: list[Input] = []


def _install_inputs(inputs: list[Input]) -> None:
    _pool_inputs[:] = inputs


def _build_one(
    cell: Cell,
    candidates: Sequence[Input | int],
    config: BuildConfig,
    seed: int,
    mask_bits: MaskBits,
) -> CellCoadd:
    """Build one cell from its candidate inputs (or their indices in the pool table)."""
    try:
        inputs = [_pool_inputs[i] if isinstance(i, int) else i for i in candidates]
        # the cheap batched search over-selects; the exact test decides, here in the task
        near = [e for e in inputs if rough_exposure_box(cell, header_of(e)) is not None]
        return build_cell(cell, near, config, seed, mask_bits=mask_bits)
    except Exception as err:
        # the traceback text travels with the error across process boundaries
        raise _cell_failed(cell, err, "\n" + traceback.format_exc()) from None


def _cell_failed(cell: Cell, err: BaseException, details: str = "") -> CellBuildError:
    """The error naming ``cell`` for ``err`` (with ``details``, e.g. a traceback)."""
    return CellBuildError(
        f"cell {cell.index} of tract {cell.tract} failed: {type(err).__name__}: {err}{details}"
    )


def _run_on(
    pool: Executor,
    tasks: Sequence[tuple[Cell, Sequence[Input | int]]],
    config: BuildConfig,
    seed: int,
    mask_bits: MaskBits,
    results: dict[tuple[int, int], CellCoadd],
    bar: tqdm,
) -> None:
    """Build the cells of ``tasks`` on ``pool`` into ``results``; on the first failure,
    cancel what has not started and raise a CellBuildError naming the cell."""
    submitted: list[tuple[Future, Cell]] = [
        (pool.submit(_build_one, cell, candidates, config, seed, mask_bits), cell)
        for cell, candidates in tasks
    ]
    cells = dict(submitted)
    try:
        for future in as_completed(cells):
            cell = cells[future]
            try:
                results[cell.index] = future.result()
            except CellBuildError:
                raise
            except BrokenExecutor as err:
                raise CellBuildError(_died_message(submitted, err)) from err
            except Exception as err:  # e.g. dask's KilledWorker: names this very cell
                raise _cell_failed(cell, err) from err
            bar.update()
    except BaseException:
        for future, _ in submitted:
            future.cancel()
        raise


def _run_on_dask(
    client: Any,
    tasks: Sequence[tuple[Cell, Sequence[Input | int]]],
    exposures: list[Input],
    config: BuildConfig,
    seed: int,
    mask_bits: MaskBits,
    results: dict[tuple[int, int], CellCoadd],
    bar: tqdm,
) -> None:
    """Build the cells of ``tasks`` (cell, indices of its candidate exposures) on the dask
    cluster of ``client`` into ``results``; on the first failure, cancel the cells not yet
    built and raise a CellBuildError naming the cell.

    Every exposure is sent once to the workers, then copied to all of them; a task's
    arguments are its cell and the futures of its exposures, which the worker resolves
    from its own memory, so no pixels travel with a task. The exposures are released at
    the end.
    """
    from distributed import as_completed as dask_as_completed  # optional: the dask extra

    # each exposure to one worker (hash=False: no tokenizing of pixels, keys private to this
    # build); copying them to every worker comes after the tasks are queued, so the first
    # cells build during the copy instead of after it, as they would with a broadcast
    table = client.scatter(exposures, hash=False)
    pending: dict[str, tuple[Any, Cell]] = {}
    try:
        for cell, indices in tasks:
            future = client.submit(
                _build_one, cell, [table[i] for i in indices], config, seed, mask_bits, pure=False
            )
            pending[future.key] = (future, cell)
        _replicate(client, table)
        for future in dask_as_completed([future for future, _ in pending.values()]):
            _, cell = pending.pop(future.key)  # dropped once read: frees the worker's copy
            try:
                results[cell.index] = future.result()
            except CellBuildError:
                raise
            except Exception as err:  # e.g. KilledWorker: names this very cell
                raise _cell_failed(cell, err) from err
            bar.update()
    except BaseException:
        client.cancel([future for future, _ in pending.values()])
        raise
    finally:
        client.cancel(table)


def _replicate(client: Any, futures: list[Any]) -> None:
    """Copy the data of ``futures`` to every worker of ``client``'s cluster, if possible.

    The copies save each worker fetching exposures task by task and keep them available
    if a worker dies. Without them (e.g. a worker died during the copy) tasks still get
    their exposures from where they are, so a failure here is not an error of the build.
    """
    with contextlib.suppress(Exception):  # an optimisation only, see above
        client.replicate(futures)


def _died_message(submitted: list[tuple[Future, Cell]], err: BaseException) -> str:
    """Name the cell a dead worker process was building, as far as it can be known.

    A broken process pool fails every unfinished future at once without saying which
    task killed its worker. Tasks start in submission order, so the earliest-submitted
    unfinished cell had started: it is named, with the next unfinished ones (one of which
    may have been the task that died instead).
    """
    unfinished = [cell for future, cell in submitted if _broken_or_pending(future)]
    first = unfinished[0] if unfinished else submitted[0][1]
    others = ", ".join(str(cell.index) for cell in unfinished[1:4])
    after = f" or one started after it ({others}...)" if others else ""
    return (
        f"cell {first.index} of tract {first.tract} failed: a worker process died while "
        f"building it{after}: {type(err).__name__}: {err}"
    )


def _broken_or_pending(future: Future) -> bool:
    if not future.done():
        return True
    return not future.cancelled() and isinstance(future.exception(), BrokenExecutor)


def build_patch(
    patch: Patch,
    exposures: Sequence[Exposure | ExposureSource | DescribedSource],
    config: BuildConfig | None = None,
    seed: int = 0,
    executor: Executor | None = None,
    progress: bool = True,
    *,
    workers: int = 1,
    scheduler: object | None = None,
) -> PatchCoadd:
    """Build every cell (inner and border) of ``patch`` from ``exposures``.

    Parameters
    ----------
    patch : Patch
        The patch to build.
    exposures : sequence of Exposure or ExposureSource
        All candidate inputs, of one band; each cell receives those near it. Sources
        (e.g. :class:`cellcoadd.io.MefExposureFile`) are described from their headers
        here and loaded by the workers, cut to each cell, one at a time.
    config : BuildConfig
        Build settings (default ``BuildConfig()``), stored in the result. Its ``units``
        and ``zero_point`` set the pixel unit (nJy by default, or counts at a zero
        point), recorded as the metadata's ``units`` and ``zero_point``.
    seed : int
        Seed of the noise realizations.
    executor : concurrent.futures.Executor, optional
        Where to run the cells. Default: serially in this process when ``workers == 1``,
        else a local process pool of ``workers`` processes.
    progress : bool
        Show a progress bar.
    workers : int
        Size of the default process pool.
    scheduler : str or distributed.Client, optional
        A dask.distributed scheduler address (a client is opened and closed here) or
        client (left open) to run the cells on, when no ``executor`` is given. The
        exposures are sent to the workers once (released at the end); each task carries
        a cell and references to its exposures. See the notes on the workers' settings.

    Raises
    ------
    CellBuildError
        If any cell fails; names the cell and includes the original traceback.
    ValueError
        On duplicate ``(visit, detector)`` inputs or mixed bands.

    Notes
    -----
    Dask workers started by a nanny (``LocalCluster``, ``dask worker``) get
    ``MALLOC_TRIM_THRESHOLD_=65536`` from dask's ``distributed.nanny.pre-spawn-environ``
    setting, which makes glibc map and unmap every array above 128 kB: cells then build
    up to ~1.9x slower than in a plain process. Keeping such arrays on the heap restores
    the speed; set this before the cluster (or the worker) starts::

        dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_MMAP_THRESHOLD_": 33554432})
        cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1)

    or the same key under ``distributed: nanny: pre-spawn-environ:`` in the dask YAML
    configuration of the worker machines (or ``MALLOC_MMAP_THRESHOLD_=33554432`` in the
    environment of ``dask worker``). Results are identical either way.
    """
    config = config or BuildConfig()
    inputs = [describe(item) for item in exposures]  # a source's header is read once, here
    headers = [header_of(item) for item in inputs]
    check_unique_inputs(headers)
    bands = sorted({header.band for header in headers})
    if not bands:
        raise ValueError("build_patch needs at least one exposure")
    if len(bands) > 1:
        raise ValueError(f"exposures of several bands given ({bands}); build one band at a time")
    try:
        check_band_name(bands[0])
    except ValueError as err:
        raise ValueError(f"band {bands[0]!r} cannot be recorded in a coadd: {err}") from None
    check_mask_bits(headers, config)  # before any work
    mask_bits = MaskBits.union(header.mask_bits for header in headers)
    cells = patch.cells
    near = exposures_near_cells(cells, headers)
    client = pool = None
    if executor is None and scheduler is not None:
        client, release = dask_client(scheduler)
    else:
        pool, release = resolve_executor(
            executor, workers, scheduler, initializer=_install_inputs, initargs=(inputs,)
        )
    # a pool made here holds the inputs and dask receives them once: tasks name them by
    # index; a given executor gets the inputs with each task
    owned = isinstance(pool, ProcessPoolExecutor) and release is not None
    tasks = [
        (cell, indices if owned or client is not None else [inputs[i] for i in indices])
        for cell, indices in zip(cells, near, strict=True)
    ]
    results: dict[tuple[int, int], CellCoadd] = {}
    bar = tqdm(total=len(tasks), desc=f"patch {patch.index}", unit="cell", disable=not progress)
    try:
        if client is not None:
            _run_on_dask(client, tasks, inputs, config, seed, mask_bits, results, bar)
        elif pool is None:
            for cell, candidates in tasks:
                results[cell.index] = _build_one(cell, candidates, config, seed, mask_bits)
                bar.update()
        else:
            _run_on(pool, tasks, config, seed, mask_bits, results, bar)
    finally:
        bar.close()
        if release is not None:
            release()
    metadata = PatchMetadata(
        skymap_config=patch.config,
        tract=patch.tract.id,
        tract_center=patch.tract.center,
        patch=patch.index,
        band=bands[0],
        units=config.units,
        zero_point=config.zero_point,
        mask_bits=mask_bits,
        build_config=config,
        software_version=__version__,
        format_version=FORMAT_VERSION,
    )
    ordered = {cell.index: results[cell.index] for cell in cells}
    return PatchCoadd(metadata=metadata, cells=ordered)
