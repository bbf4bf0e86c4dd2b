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
finished cell travels back without its WCS (the receiving process makes it from its own
geometry: unpickling an astropy WCS costs ~2 ms, remaking it 0.04 ms).

:func:`stream_patch` gives the cells as their blocks are done, in the order of the patch
files (sorted ``(cx, cy)``: blocks are bands of whole columns), with the patch's metadata
known before any cell, so a writer stores each block and lets it go: the building process
holds a few blocks, not the patch, on a process pool as on dask (:func:`build_patch`
collects them into a :class:`~cellcoadd.model.patch_coadd.PatchCoadd`). A failing cell
stops the build with an error naming the cell and carrying the worker's traceback.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import itertools
import traceback
from collections.abc import Callable, Collection, Generator, Iterator, Mapping, Sequence
from concurrent.futures import (
    FIRST_COMPLETED,
    BrokenExecutor,
    Executor,
    Future,
    ProcessPoolExecutor,
    wait,
)
from typing import Any

from tqdm.auto import tqdm

from cellcoadd._version import __version__
from cellcoadd.builder.cell import CellBlock
from cellcoadd.builder.exposure_frame import ExposureFrame
from cellcoadd.builder.inputs import BuildInput, BuildSettings, PreparedBuild, prepare
from cellcoadd.builder.psf import PsfLoss, psf_loss, warn_psf_losses
from cellcoadd.errors import CellBuildError, ConfigError, InvalidCoaddError
from cellcoadd.execution.executors import dask_client, resolve_executor
from cellcoadd.geometry.tract import Cell, Patch
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.patch_coadd import FORMAT_VERSION, PatchCoadd, PatchMetadata
from cellcoadd.model.planes import INPUTS, plane_names
from cellcoadd.model.sources import DescribedSource, ExposureSource

#: Most cells built together in one block: bounds a block's memory, e.g. 64 cells of
#: 250 x 250 px with 3 noise realizations hold ~190 MB of float64 sums.
MAX_BLOCK_CELLS = 64
#: Blocks submitted to a pool and not yet handed on, per worker: bounds the finished cells
#: the building process holds (one block running in each worker, one waiting, and those
#: done out of order).
WINDOW_PER_WORKER = 2

# The inputs of the build and their frames, installed once in each process of a pool this
# module creates (its initializer), so that block tasks carry input indices instead of
# pixels. Per-process transport state only: every result depends on the task's arguments.
_pool_inputs: list[tuple[BuildInput, ExposureFrame | None]] = []


def _install_inputs(inputs: list[tuple[BuildInput, ExposureFrame | None]]) -> None:
    _pool_inputs[:] = inputs


#: One task: the cells of a block and their candidate inputs (with their frames), or the
#: indices of those in the pool's table.
Task = tuple[list[Cell], Sequence[tuple[BuildInput, ExposureFrame | None] | int]]
#: A built cell on its way back from a worker: its :class:`CellCoadd` fields but the WCS.
Parcel = dict[str, Any]
#: What runs one task: its cells and candidates in, their coadds (or parcels) out.
Runner = Callable[[list[Cell], Sequence[Any]], list[Any]]
#: The coadds of the blocks of a build, block after block in file order; closing it cancels
#: the blocks not yet built.
Blocks = Generator[list[CellCoadd], None, None]


def _build_block(
    settings: BuildSettings,
    cells: list[Cell],
    candidates: Sequence[tuple[BuildInput, ExposureFrame | None] | int],
    *,
    parcels: bool = False,
) -> list[Any]:
    """Build the cells of one block from their candidate inputs (or indices of them); as
    parcels (:func:`_parcel`) to send them to another process."""
    block = None
    try:
        block = CellBlock(cells, settings)
        for candidate in candidates:
            item, frame = _pool_inputs[candidate] if isinstance(candidate, int) else candidate
            block.add(item, frame)
        built = block.finish()
        return [_parcel(coadd) for coadd in built] if parcels else built
    except Exception as err:
        # the traceback text travels with the error across process boundaries
        cell = block.current if block is not None else cells[0]
        raise _cell_failed(cell, err, "\n" + traceback.format_exc()) from None


def parcel_fields() -> tuple[str, ...]:
    """What a parcel carries of a cell: every plane of
    :data:`~cellcoadd.model.planes.PLANES` (optional ones included, ``None`` when absent),
    its inputs table, then every other argument of :class:`CellCoadd` (identity and boxes)
    but the WCS (remade from the cell's geometry) and ``common`` (the patch's, attached by
    :class:`~cellcoadd.model.patch_coadd.PatchCoadd`). Derived, not listed, so that a plane
    or field added to a cell travels without a change here."""
    arguments = inspect.signature(CellCoadd).parameters
    return tuple(
        dict.fromkeys((*plane_names(), INPUTS, *(a for a in arguments if a not in _NOT_PARCELLED)))
    )


#: Arguments of :class:`CellCoadd` a parcel leaves out (see :func:`parcel_fields`).
_NOT_PARCELLED = frozenset({"wcs", "common"})


def _parcel(coadd: CellCoadd) -> Parcel:
    """The fields of ``coadd`` but its WCS (see :func:`parcel_fields`, :func:`_unparcel`)."""
    return {name: getattr(coadd, name) for name in parcel_fields()}


def _unparcel(cell: Cell, built: CellCoadd | Parcel) -> CellCoadd:
    """The coadd of ``cell`` from what its block returned: the coadd itself, or a parcel
    given the cell's WCS, made here from its geometry as the builder makes it."""
    if isinstance(built, CellCoadd):
        return built
    return CellCoadd(**built, wcs=cell.wcs)


def blocks_of(cells: Sequence[Cell], n_tasks: int) -> list[list[Cell]]:
    """Blocks of neighbouring cells in file order: bands of whole columns, cells sorted by
    ``(cx, cy)``, so the blocks one after the other list the cells in sorted order.

    A band has as many columns as fit in :data:`MAX_BLOCK_CELLS` cells, fewer to make
    about ``n_tasks`` bands when there are enough columns; a column taller than that is
    cut into pieces of at most :data:`MAX_BLOCK_CELLS` cells.
    """
    columns: dict[int, list[Cell]] = {}
    for cell in sorted(cells, key=lambda c: c.index):
        columns.setdefault(cell.index[0], []).append(cell)
    if not columns:
        return []
    tallest = max(len(column) for column in columns.values())
    if tallest > MAX_BLOCK_CELLS:
        return [
            column[start : start + MAX_BLOCK_CELLS]
            for column in columns.values()
            for start in range(0, len(column), MAX_BLOCK_CELLS)
        ]
    bands = list(columns.values())
    width = max(1, min(MAX_BLOCK_CELLS // tallest, -(-len(bands) // max(1, n_tasks))))
    return [
        [cell for column in bands[start : start + width] for cell in column]
        for start in range(0, len(bands), width)
    ]


def parts_by_cost(
    cells: Sequence[Cell], costs: Mapping[tuple[int, int], float], n_parts: int
) -> list[list[Cell]]:
    """Cut ``cells`` into at most ``n_parts`` runs of neighbouring cells of about equal
    total ``costs`` (any relative unit, > 0 per cell).

    The cells are taken in file order (sorted by ``(cx, cy)``: columns one after the
    other), so each part is a band of whole columns with at most a piece of a column at
    each end, and the parts one after the other list the cells in sorted order. Each cut
    falls where the running cost is nearest to its share, so that no part's cost exceeds
    the ideal ``sum / n_parts`` by more than the costliest cell's.
    """
    ordered = sorted(cells, key=lambda c: c.index)
    if not ordered:
        return []
    running = list(itertools.accumulate(float(costs[cell.index]) for cell in ordered))
    n = max(1, min(n_parts, len(ordered)))
    cuts = [0]
    for k in range(1, n):
        share = running[-1] * k / n
        # cut after the cell whose running cost is nearest the share (at least one cell
        # per part, and room for one in each of the parts still to come)
        after = min(range(len(ordered)), key=lambda i: abs(running[i] - share)) + 1
        cuts.append(min(max(after, cuts[-1] + 1), len(ordered) - (n - k)))
    cuts.append(len(ordered))
    return [ordered[a:b] for a, b in itertools.pairwise(cuts)]


def _cell_failed(cell: Cell, err: BaseException, details: str = "") -> CellBuildError:
    """The error naming ``cell`` for ``err`` (with ``details``, e.g. a traceback)."""
    return CellBuildError(
        f"cell {cell.index} of tract {cell.tract} failed: {type(err).__name__}: {err}{details}"
    )


def _collect(
    cells: list[Cell], built: list[Any], results: dict[tuple[int, int], CellCoadd]
) -> None:
    for cell, coadd in zip(cells, built, strict=True):
        results[cell.index] = _unparcel(cell, coadd)


def _run_on(pool: Executor, tasks: Sequence[Task], run: Runner) -> Blocks:
    """Build the blocks of ``tasks`` with ``run`` on ``pool``; yield their coadds block by
    block in the order of ``tasks``. At most ``WINDOW_PER_WORKER`` blocks per worker are
    submitted and not yet yielded, so finished cells do not pile up here. On the first
    failure, cancel what has not started and raise a CellBuildError naming the cell."""
    workers = max(1, int(getattr(pool, "_max_workers", 1)))
    window = WINDOW_PER_WORKER * workers
    # every block submitted, by number, with its future until its result is taken: a future
    # holds its result, so one kept here would keep the block's pixels for the whole build
    submitted: list[tuple[Future | None, list[Cell]]] = []
    done: dict[int, list[CellCoadd]] = {}  # finished blocks waiting for earlier ones
    numbers: dict[Future, int] = {}
    yielded = 0
    try:
        while yielded < len(tasks):
            while len(submitted) < len(tasks) and len(submitted) - yielded < window:
                cells, candidates = tasks[len(submitted)]
                try:
                    future = pool.submit(run, cells, candidates)
                except BrokenExecutor as err:  # a worker died since the last submission
                    raise CellBuildError(_died_message(submitted, err, workers)) from err
                numbers[future] = len(submitted)
                submitted.append((future, cells))
            if yielded not in done:
                finished, _ = wait(list(numbers), return_when=FIRST_COMPLETED)
                for future in sorted(finished, key=numbers.__getitem__):
                    number = numbers[future]
                    done[number] = _received(future, submitted, number, workers)
                    del numbers[future]
                    submitted[number] = (None, submitted[number][1])  # let its result go
                continue
            yield done.pop(yielded)
            yielded += 1
    except BaseException:
        for future in numbers:
            future.cancel()
        raise


def _received(
    future: Future,
    submitted: Sequence[tuple[Future | None, list[Cell]]],
    number: int,
    workers: int,
) -> list[CellCoadd]:
    """The coadds of finished block ``number``, or the CellBuildError naming its cell."""
    cells = submitted[number][1]
    try:
        results: dict[tuple[int, int], CellCoadd] = {}
        _collect(cells, future.result(), results)
        return list(results.values())
    except CellBuildError:
        raise
    except BrokenExecutor as err:
        raise CellBuildError(_died_message(submitted, err, workers)) from err
    except Exception as err:  # e.g. a result that could not be sent back
        raise _cell_failed(cells[0], err) from err


def _run_on_dask(
    client: Any,
    tasks: Sequence[Task],
    inputs: list[tuple[BuildInput, ExposureFrame | None]],
    run: Runner,
) -> Blocks:
    """Build the blocks of ``tasks`` (cells, indices of their candidate inputs) with ``run``
    on the dask cluster of ``client``; yield their coadds block by block in the order of
    ``tasks``. On the first failure, cancel the blocks not yet built and raise a
    CellBuildError naming the cell.

    Every input is sent once to the workers, then copied to all of them; a task's
    arguments are its cells and the futures of its inputs, which the worker resolves
    from its own memory, so no pixels travel with a task. At most ``WINDOW_PER_WORKER``
    blocks per worker thread are submitted and not yet yielded; a finished block stays on
    its worker until its turn comes, then is fetched here and released there. The inputs
    are released at the end.
    """
    from distributed import as_completed as dask_as_completed  # optional: the dask extra

    window = WINDOW_PER_WORKER * max(1, sum(client.nthreads().values()))
    # each input to one worker (hash=False: no tokenizing of pixels, keys private to this
    # build); copying them to every worker comes after the first tasks are queued, so those
    # build during the copy instead of after it, as they would with a broadcast
    table = client.scatter(inputs, hash=False)
    futures: dict[int, Any] = {}  # submitted and not yet yielded, by block number
    numbers: dict[str, int] = {}  # block number of each future not yet seen finished
    finished: set[int] = set()
    completed = dask_as_completed()
    yielded = 0
    try:
        while yielded < len(tasks):
            first = not futures and yielded == 0
            while len(futures) + yielded < len(tasks) and len(futures) < window:
                number = len(futures) + yielded
                cells, indices = tasks[number]
                futures[number] = client.submit(run, cells, [table[i] for i in indices], pure=False)
                numbers[futures[number].key] = number
                completed.add(futures[number])
            if first:
                _replicate(client, table)
            while yielded not in finished:
                finished.add(_dask_finished(next(completed), numbers, tasks))
            finished.remove(yielded)
            # its last future dropped here: the worker lets its copy go
            coadds = _dask_received(futures.pop(yielded), tasks[yielded][0])
            yield coadds
            del coadds
            yielded += 1
    except BaseException:
        client.cancel(list(futures.values()))
        raise
    finally:
        completed.clear()
        client.cancel(table)


def _dask_finished(future: Any, numbers: dict[str, int], tasks: Sequence[Task]) -> int:
    """The number of the block whose dask ``future`` is done (taken out of ``numbers``);
    the CellBuildError naming its cell if it failed (now, not when its turn comes)."""
    number = numbers.pop(future.key)
    if future.status != "finished":
        _dask_received(future, tasks[number][0])
    return number


def _dask_received(future: Any, cells: list[Cell]) -> list[CellCoadd]:
    """The coadds of the block of ``cells`` from its dask ``future``, or the CellBuildError
    naming its cell."""
    try:
        results: dict[tuple[int, int], CellCoadd] = {}
        _collect(cells, future.result(), results)
        return list(results.values())
    except CellBuildError:
        raise
    except Exception as err:  # e.g. KilledWorker: names the block's first cell
        raise _cell_failed(cells[0], err) from err


def _replicate(client: Any, futures: list[Any]) -> None:
    """Copy the data of ``futures`` to every worker of ``client``'s cluster, if possible.

    The copies save each worker fetching exposures task by task and keep them available
    if a worker dies. Without them (e.g. a worker died during the copy) tasks still get
    their exposures from where they are, so a failure here is not an error of the build.
    """
    with contextlib.suppress(Exception):  # an optimisation only, see above
        client.replicate(futures)


def _died_message(
    submitted: Sequence[tuple[Future | None, list[Cell]]], err: BaseException, workers: int
) -> str:
    """Name the cell a dead worker process was building, as far as it can be known.

    ``submitted`` lists every block submitted, in order, with its future (None once its
    result was taken: that block was built).

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


def _broken_or_pending(future: Future | None) -> bool:
    if future is None:  # its cells were received
        return False
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
    cells : collection of (int, int), optional
        Build only these cells (tract-global cell indices, all of ``patch``): each comes
        out bit-identical to the same cell of a build of the whole patch (the inputs are
        still mapped over the whole patch), so a patch built in parts and put together
        (:func:`merge_patch_parts`) equals the patch built at once.

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
    CPU. :data:`~cellcoadd.execution.settings.DASK_WORKER_CONFIG` restores the speed; set
    it before the cluster starts::

        dask.config.set(DASK_WORKER_CONFIG)
        cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1)

    or, for workers started elsewhere (``dask worker``, a job script), put
    :func:`~cellcoadd.execution.settings.dask_worker_environment` in their environment.
    Results are identical either way.
    """
    stream = stream_patch(
        patch,
        exposures,
        config,
        seed,
        executor,
        progress,
        workers=workers,
        scheduler=scheduler,
        cells=cells,
    )
    with stream:
        cells = {coadd.index: coadd for coadd in stream}
    return PatchCoadd(metadata=stream.metadata, cells=cells)


def stream_patch(
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
) -> PatchStream:
    """The cells of ``patch`` (or only ``cells`` of them) built from ``exposures``, given
    one by one as they are done.

    The parameters, the set-up (inputs checked, headers read, exposures mapped) and the
    errors are those of :func:`build_patch`, whose cells are the same bit for bit; the
    set-up happens here, the building while the result is iterated.

    Returns
    -------
    PatchStream
        Its ``metadata`` (known before any cell) and ``indices``; iterating it builds the
        cells and yields them in sorted ``(cx, cy)`` order, the order of the patch files,
        block after block: at most ``WINDOW_PER_WORKER`` blocks (of at most
        :data:`MAX_BLOCK_CELLS` cells) per worker (process, or dask worker thread) are
        submitted and not yet handed on (on dask, a finished block waits for its turn on
        its worker and is fetched here then). Use it as a context manager (or call
        ``close``): leaving it stops the workers.
    """
    config = config or BuildConfig()
    chosen = _chosen_cells(patch, cells)
    build = prepare(
        chosen, exposures, config, seed, one_band=True, area=patch.outer_bbox, record_distant=False
    )
    band = build.settings.band
    assert band is not None  # one_band
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
    blocks = _built_blocks(patch, chosen, build, executor, progress, workers, scheduler)
    return PatchStream(metadata, sorted(cell.index for cell in chosen), blocks)


class PatchStream:
    """The cells of a patch as they are built (see :func:`stream_patch`).

    Attributes
    ----------
    metadata : PatchMetadata
        The patch's metadata, as :func:`build_patch` gives it.
    indices : list of (int, int)
        The cells that will come, in the order they come (sorted).
    """

    def __init__(
        self,
        metadata: PatchMetadata,
        indices: list[tuple[int, int]],
        blocks: Iterator[list[CellCoadd]],
    ) -> None:
        self.metadata = metadata
        self.indices = indices
        self._blocks = blocks
        self._started = False

    def __iter__(self) -> Iterator[CellCoadd]:
        if self._started:
            raise CellBuildError(f"the cells of patch {self.metadata.patch} were already given")
        self._started = True
        losses: list[PsfLoss] = []
        for block in self._blocks:
            for coadd in block:
                losses += psf_loss(coadd)
            yield from block
            del block  # handed on: the last reference here
        warn_psf_losses(losses)  # here: warnings in worker processes are lost

    def close(self) -> None:
        """Stop building (cancel the blocks not started, shut down a pool made here)."""
        close = getattr(self._blocks, "close", None)
        if close is not None:
            close()

    def __enter__(self) -> PatchStream:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _built_blocks(
    patch: Patch,
    cells: list[Cell],
    build: PreparedBuild,
    executor: Executor | None,
    progress: bool,
    workers: int,
    scheduler: object | None,
) -> Iterator[list[CellCoadd]]:
    """Build the blocks of ``cells`` of ``patch`` (see :func:`stream_patch`); yield them in
    file order."""
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
    for block in blocks_of(cells, _task_count(pool, client, workers, sources)):
        indices = build.candidates(block)  # only these can change the block's cells
        tasks.append(
            (block, indices if owned or client is not None else [framed[i] for i in indices])
        )
    # a block built elsewhere comes back as parcels: no WCS to unpickle
    elsewhere = pool is not None or client is not None
    run = functools.partial(_build_block, build.settings, parcels=elsewhere)
    bar = tqdm(total=len(cells), desc=f"patch {patch.index}", unit="cell", disable=not progress)
    if client is not None:
        built = _run_on_dask(client, tasks, framed, run)
    elif pool is not None:
        built = _run_on(pool, tasks, run)
    else:
        built = _run_here(tasks, run)
    try:
        with contextlib.closing(built):  # leaving early cancels what was submitted
            for (block, _), coadds in zip(tasks, built, strict=False):
                bar.update(len(block))
                yield coadds
                del coadds  # handed on: not held while the next block is built
    finally:
        bar.close()
        if release is not None:
            release()


def _run_here(tasks: Sequence[Task], run: Runner) -> Blocks:
    """Build the blocks of ``tasks`` with ``run`` in this process, one after the other."""
    for block, candidates in tasks:
        built = run(block, candidates)
        coadds = [_unparcel(c, b) for c, b in zip(block, built, strict=True)]
        del built
        yield coadds
        del coadds  # handed on: not held while the next block is built


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
