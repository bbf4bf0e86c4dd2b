"""Coadding every cell of a patch, in parallel on any ``concurrent.futures`` executor.

Each exposure is mapped once onto the patch (:func:`~cellcoadd.builder.exposure_frame.
exposure_frame`, from its header, here, in the set-up every build shares:
:func:`~cellcoadd.builder.inputs.prepare`); the cells are then built in blocks of
neighbours, each block an independent task that receives only the exposures near it and
warps each of them once for all its cells (:class:`~cellcoadd.builder.cell.CellBlock`). A
cell's result depends only on its inputs, their mapping over the patch and the seed, not
on its block, so the patch is bit-identical whatever the executor, the number of workers
and hence the blocks. Inputs are sent to each worker once, never with every task: a
process pool created here installs them in each process (its initializer) and tasks carry
indices; on a dask cluster they are scattered once, then copied to every worker, and
tasks carry references to them. Inputs given as exposure sources
(:class:`~cellcoadd.model.sources.ExposureSource`: paths and options) weigh nothing:
which cells they serve is decided from their headers, and each worker loads the pixels
it needs, one exposure cut to one block at a time, so memory does not grow with the
number of exposures and no pixel crosses a process boundary except finished cells. A
failing cell stops the build with an error naming the cell and carrying the worker's
traceback.
"""

from __future__ import annotations

import contextlib
import functools
import traceback
from collections.abc import Callable, Collection, Sequence
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
from cellcoadd.builder.cell import CellBlock
from cellcoadd.builder.executors import dask_client, resolve_executor
from cellcoadd.builder.exposure_frame import ExposureFrame
from cellcoadd.builder.inputs import BuildInput, BuildSettings, prepare
from cellcoadd.builder.psf import warn_truncated_psfs
from cellcoadd.errors import CellBuildError, ConfigError, InvalidCoaddError
from cellcoadd.geometry.tract import Cell, Patch
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.patch_coadd import FORMAT_VERSION, PatchCoadd, PatchMetadata
from cellcoadd.model.sources import DescribedSource, ExposureSource

#: Largest block of cells built together (per side): bounds a block's memory, e.g. 64
#: cells of 250 x 250 px with 3 noise realizations hold ~190 MB of float64 sums.
MAX_BLOCK_SIDE = 8

# The inputs of the build and their frames, installed once in each process of a pool this
# module creates (its initializer), so that block tasks carry input indices instead of
# pixels. Per-process transport state only: every result depends on the task's arguments.
_pool_inputs: list[tuple[BuildInput, ExposureFrame | None]] = []


def _install_inputs(inputs: list[tuple[BuildInput, ExposureFrame | None]]) -> None:
    _pool_inputs[:] = inputs


#: One task: the cells of a block and their candidate inputs (with their frames), or the
#: indices of those in the pool's table.
Task = tuple[list[Cell], Sequence[tuple[BuildInput, ExposureFrame | None] | int]]
#: What runs one task: its cells and candidates in, their coadds out.
Runner = Callable[[list[Cell], Sequence[Any]], list[CellCoadd]]


def _build_block(
    settings: BuildSettings,
    cells: list[Cell],
    candidates: Sequence[tuple[BuildInput, ExposureFrame | None] | int],
) -> list[CellCoadd]:
    """Build the cells of one block from their candidate inputs (or indices of them)."""
    block = None
    try:
        block = CellBlock(cells, settings)
        for candidate in candidates:
            item, frame = _pool_inputs[candidate] if isinstance(candidate, int) else candidate
            block.add(item, frame)
        return block.finish()
    except Exception as err:
        # the traceback text travels with the error across process boundaries
        cell = block.current if block is not None else cells[0]
        raise _cell_failed(cell, err, "\n" + traceback.format_exc()) from None


def blocks_of(cells: Sequence[Cell], n_tasks: int) -> list[list[Cell]]:
    """Blocks of neighbouring cells: bands of whole rows (at most :data:`MAX_BLOCK_SIDE`
    cells on a side), about ``n_tasks`` of them when there are enough rows; cells in
    row-major order within a block, blocks in row-major order."""
    if not cells:
        return []
    xs = sorted({cell.index[0] for cell in cells})
    ys = sorted({cell.index[1] for cell in cells})
    side_x = min(len(xs), MAX_BLOCK_SIDE)
    per_band = -(-len(xs) // side_x)
    side_y = min(MAX_BLOCK_SIDE, max(1, -(-len(ys) * per_band // max(1, n_tasks))))
    groups: dict[tuple[int, int], list[Cell]] = {}
    for cell in sorted(cells, key=lambda c: (c.index[1], c.index[0])):
        key = ((cell.index[1] - ys[0]) // side_y, (cell.index[0] - xs[0]) // side_x)
        groups.setdefault(key, []).append(cell)
    return [groups[key] for key in sorted(groups)]


def _cell_failed(cell: Cell, err: BaseException, details: str = "") -> CellBuildError:
    """The error naming ``cell`` for ``err`` (with ``details``, e.g. a traceback)."""
    return CellBuildError(
        f"cell {cell.index} of tract {cell.tract} failed: {type(err).__name__}: {err}{details}"
    )


def _collect(
    cells: list[Cell], built: list[CellCoadd], results: dict[tuple[int, int], CellCoadd]
) -> None:
    for cell, coadd in zip(cells, built, strict=True):
        results[cell.index] = coadd


def _run_on(
    pool: Executor,
    tasks: Sequence[Task],
    run: Runner,
    results: dict[tuple[int, int], CellCoadd],
    bar: tqdm,
) -> None:
    """Build the blocks of ``tasks`` with ``run`` on ``pool`` into ``results``; on the first
    failure, cancel what has not started and raise a CellBuildError naming the cell."""
    submitted: list[tuple[Future, list[Cell]]] = [
        (pool.submit(run, cells, candidates), cells) for cells, candidates in tasks
    ]
    blocks = dict(submitted)
    try:
        for future in as_completed(blocks):
            cells = blocks[future]
            try:
                _collect(cells, future.result(), results)
            except CellBuildError:
                raise
            except BrokenExecutor as err:
                workers = int(getattr(pool, "_max_workers", 1))
                raise CellBuildError(_died_message(submitted, err, workers)) from err
            except Exception as err:  # e.g. a result that could not be sent back
                raise _cell_failed(cells[0], err) from err
            bar.update(len(cells))
    except BaseException:
        for future, _ in submitted:
            future.cancel()
        raise


def _run_on_dask(
    client: Any,
    tasks: Sequence[Task],
    inputs: list[tuple[BuildInput, ExposureFrame | None]],
    run: Runner,
    results: dict[tuple[int, int], CellCoadd],
    bar: tqdm,
) -> None:
    """Build the blocks of ``tasks`` (cells, indices of their candidate inputs) with ``run``
    on the dask cluster of ``client`` into ``results``; on the first failure, cancel the blocks
    not yet built and raise a CellBuildError naming the cell.

    Every input is sent once to the workers, then copied to all of them; a task's
    arguments are its cells and the futures of its inputs, which the worker resolves
    from its own memory, so no pixels travel with a task. The inputs are released at
    the end.
    """
    from distributed import as_completed as dask_as_completed  # optional: the dask extra

    # each input to one worker (hash=False: no tokenizing of pixels, keys private to this
    # build); copying them to every worker comes after the tasks are queued, so the first
    # blocks build during the copy instead of after it, as they would with a broadcast
    table = client.scatter(inputs, hash=False)
    pending: dict[str, tuple[Any, list[Cell]]] = {}
    try:
        for cells, indices in tasks:
            candidates = [table[i] for i in indices]
            future = client.submit(run, cells, candidates, pure=False)
            pending[future.key] = (future, cells)
        _replicate(client, table)
        for future in dask_as_completed([future for future, _ in pending.values()]):
            _, cells = pending.pop(future.key)  # dropped once read: frees the worker's copy
            try:
                _collect(cells, future.result(), results)
            except CellBuildError:
                raise
            except Exception as err:  # e.g. KilledWorker: names the block's first cell
                raise _cell_failed(cells[0], err) from err
            bar.update(len(cells))
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


def _died_message(
    submitted: list[tuple[Future, list[Cell]]], err: BaseException, workers: int
) -> str:
    """Name the cell a dead worker process was building, as far as it can be known.

    A broken process pool fails every unfinished future at once without saying which
    task killed its worker. Tasks start in submission order, so the task that died is one
    of the ``workers`` earliest-submitted unfinished blocks: the first cell of the first
    is named, with every other cell of those blocks.
    """
    unfinished = [cells for future, cells in submitted if _broken_or_pending(future)]
    running = unfinished[: max(1, workers)] or [submitted[0][1]]
    first = running[0][0]
    suspects = [str(cell.index) for cells in running for cell in cells if cell is not first]
    after = f" or one built with or after it ({', '.join(suspects)})" if suspects else ""
    return (
        f"cell {first.index} of tract {first.tract} failed: a worker process died while "
        f"building it{after}: {type(err).__name__}: {err}"
    )


def _broken_or_pending(future: Future) -> bool:
    if not future.done():
        return True
    return not future.cancelled() and isinstance(future.exception(), BrokenExecutor)


def _task_count(pool: Executor | None, client: Any, workers: int, sources: bool) -> int:
    """How many blocks to cut a patch into: one in this process; else one per worker when
    the inputs are sources (each block loads every exposure it needs once, at a fixed
    cost of ~20 ms per file, so fewer, larger blocks), two per worker for in-memory
    exposures (to balance blocks of unequal cost). Results do not depend on it."""
    if client is not None:
        n_workers = max(1, sum(client.nthreads().values()))
    elif pool is None:
        return 1
    else:
        n_workers = max(1, int(getattr(pool, "_max_workers", workers)))
    return n_workers if sources else 2 * n_workers


def _chosen_cells(patch: Patch, cells: Collection[tuple[int, int]] | None) -> list[Cell]:
    """The cells of ``patch`` named by ``cells`` (all when None), in the patch's order."""
    if cells is None:
        return list(patch.cells)
    wanted = {(int(c[0]), int(c[1])) for c in cells}
    chosen = [cell for cell in patch.cells if cell.index in wanted]
    if len(chosen) != len(wanted):
        missing = sorted(wanted - {cell.index for cell in chosen})
        raise ConfigError(
            f"cells {missing[:5]} are not cells of patch {patch.index} of tract {patch.tract.id}"
        )
    return chosen


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
    cells: Collection[tuple[int, int]] | None = None,
) -> PatchCoadd:
    """Build every cell (inner and border) of ``patch`` from ``exposures``, or only
    ``cells`` of them.

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
    InputError
        On duplicate ``(visit, detector)`` inputs or mixed bands (a ValueError too).

    Notes
    -----
    Dask workers started by a nanny (``LocalCluster``, ``dask worker``) get
    ``MALLOC_TRIM_THRESHOLD_=65536`` from dask's ``distributed.nanny.pre-spawn-environ``
    setting, which makes glibc map and unmap every array above 128 kB: cells then build
    up to ~1.9x slower than in a plain process; dask's profiler and monitors add 10-14%
    CPU. :data:`~cellcoadd.builder.executors.DASK_WORKER_CONFIG` restores the speed; set
    it before the cluster starts::

        dask.config.set(DASK_WORKER_CONFIG)
        cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1)

    or, for workers started elsewhere (``dask worker``, a job script), put
    :func:`~cellcoadd.builder.executors.dask_worker_environment` in their environment.
    Results are identical either way.
    """
    config = config or BuildConfig()
    chosen = _chosen_cells(patch, cells)
    build = prepare(
        chosen, exposures, config, seed, one_band=True, area=patch.outer_bbox, record_distant=False
    )
    band = build.settings.band
    assert band is not None  # one_band
    # each exposure mapped once onto the patch, from its header: shared by every block
    framed = [(item, frame) for item, frame in zip(build.inputs, build.frames, strict=True)]
    client = pool = None
    if executor is None and scheduler is not None:
        client, release = dask_client(scheduler)
    else:
        pool, release = resolve_executor(
            executor, workers, scheduler, initializer=_install_inputs, initargs=(framed,)
        )
    # a pool made here holds the inputs and dask receives them once: tasks name them by
    # index; a given executor gets the inputs with each task
    owned = isinstance(pool, ProcessPoolExecutor) and release is not None
    tasks: list[Task] = []
    sources = any(item.source is not None for item in build.inputs)
    for block in blocks_of(chosen, _task_count(pool, client, workers, sources)):
        indices = build.candidates(block)  # only these can change the block's cells
        tasks.append(
            (block, indices if owned or client is not None else [framed[i] for i in indices])
        )
    run = functools.partial(_build_block, build.settings)
    results: dict[tuple[int, int], CellCoadd] = {}
    bar = tqdm(total=len(chosen), desc=f"patch {patch.index}", unit="cell", disable=not progress)
    try:
        if client is not None:
            _run_on_dask(client, tasks, framed, run, results, bar)
        elif pool is None:
            for block, candidates in tasks:
                _collect(block, run(block, candidates), results)
                bar.update(len(block))
        else:
            _run_on(pool, tasks, run, results, bar)
    finally:
        bar.close()
        if release is not None:
            release()
    metadata = PatchMetadata(
        skymap_config=patch.config,
        tract=patch.tract.id,
        tract_center=patch.tract.center,
        patch=patch.index,
        band=band,
        units=config.units,
        zero_point=config.zero_point,
        mask_bits=build.settings.mask_bits,
        build_config=build.settings.config,  # psf_size resolved
        software_version=__version__,
        format_version=FORMAT_VERSION,
    )
    ordered = {cell.index: results[cell.index] for cell in chosen}
    warn_truncated_psfs(ordered.values())  # here: warnings in worker processes are lost
    return PatchCoadd(metadata=metadata, cells=ordered)


def merge_patch_parts(parts: Sequence[PatchCoadd]) -> PatchCoadd:
    """The patch made of the cells of several partial builds of it (``build_patch(...,
    cells=...)`` with the same inputs, configuration and seed).

    The result is the patch built at once, bit for bit, when the parts hold every cell.

    Raises
    ------
    InvalidCoaddError
        When there is no part, the parts' metadata differ (another patch, inputs or
        settings) or a cell is in two parts.
    """
    if not parts:
        raise InvalidCoaddError("no part to merge into a patch")
    metadata = parts[0].metadata
    cells: dict[tuple[int, int], CellCoadd] = {}
    for part in parts:
        if part.metadata != metadata:
            raise InvalidCoaddError(
                f"parts of patch {metadata.patch} of tract {metadata.tract} were built with "
                f"different metadata (patch {part.metadata.patch}, tract {part.metadata.tract})"
            )
        for key, cell in part.cells.items():
            if key in cells:
                raise InvalidCoaddError(f"cell {key} is in two parts of patch {metadata.patch}")
            cells[key] = cell
    return PatchCoadd(metadata=metadata, cells=cells)
