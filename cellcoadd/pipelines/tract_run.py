"""Tract runs: plan the patches of a tract from an exposure index, build them on
dask.distributed (or here), each worker reading its own inputs and writing its own patch
file, with a ledger that makes runs resumable, idempotent and aware of stale outputs.

The calling process only plans and keeps the books: it queries the exposure index for
the inputs that may touch the tract (no file is opened), assigns them to patches from
their stored footprints, and sends each patch as one small task (the patch, the index
rows of its inputs, the configuration and the output path). A worker reads the rows'
stored headers from the index (no header is parsed), checks that every input file is
still the one indexed, builds the patch with :func:`~cellcoadd.builder.build_patch`
(serially: one patch per worker at a time bounds its memory by one patch), writes it
with :func:`cellcoadd.io.api.write` (atomic) and returns a summary of a few kB. When
the patches do not share out evenly among the workers (nine patches on two), the last
ones are cut into parts of equal estimated cost (cells x the inputs covering them, from
the index's footprints) built as separate tasks and put together by the worker that
writes the file (the cells never come here). A patch's file is
therefore byte-identical to ``cellcoadd build`` of that patch with the same inputs, in
the same order (visit, detector), configuration and seed.

Failures are retried (``retries`` times: a damaged file, a worker killed, a lost
connection), then recorded as failed with the reason; the other patches go on. See
:mod:`cellcoadd.pipelines.ledger` for the bookkeeping and the lock.
"""

from __future__ import annotations

import os
import resource
import socket
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cellcoadd._version import __version__
from cellcoadd.errors import ConfigError, InputError, MissingDependencyError
from cellcoadd.geometry.skymap import SkyMap
from cellcoadd.geometry.tract import Patch, Tract
from cellcoadd.io.exposures.index import ExposureIndex, IndexedExposure, file_sha256
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.patch_coadd import PatchCoadd
from cellcoadd.pipelines.ledger import Ledger, RunLock, config_hash, patch_signature
from cellcoadd.pipelines.run_report import write_report

#: Output formats: file ending of each.
FORMATS = {"fits": ".fits", "h5": ".h5"}


# -- planning ---------------------------------------------------------------------------


@dataclass(frozen=True)
class PatchPlan:
    """One patch to build and the index rows of its candidate inputs (visit, detector
    order), with the files they read as indexed (``[path, size, mtime_ns]``)."""

    patch: Patch
    inputs: tuple[int, ...]
    files: tuple[tuple[str, int, int], ...] = field(repr=False)
    #: each input's footprint on the tract: ``(4, 2)`` corners ``(x, y)``, tract pixels
    footprints: tuple[np.ndarray, ...] = field(default=(), repr=False, compare=False)

    @property
    def index(self) -> tuple[int, int]:
        return self.patch.index

    def cell_costs(self) -> dict[tuple[int, int], float]:
        """The relative cost of building each cell: 1 plus the number of inputs whose
        footprint covers the cell's outer box (those the cell may accept; an input that
        only grazes it is rejected early and costs little).

        The cost of a build is in its cell x input pairs, and they vary across a patch
        (its band beside a neighbouring detector can hold twice those of the far band):
        this is what cuts a patch into parts of equal cost. About 0.15 s for 484 cells
        and 800 inputs.
        """
        cells = self.patch.cells
        count = np.zeros(len(cells))
        if self.footprints:
            boxes = np.array(
                [
                    (b.x_start - 0.5, b.x_stop - 0.5, b.y_start - 0.5, b.y_stop - 0.5)
                    for b in (cell.outer_bbox for cell in cells)
                ]
            )
            xs, ys = boxes[:, [0, 1, 1, 0]], boxes[:, [2, 2, 3, 3]]
            points = np.stack([xs, ys], axis=-1).reshape(-1, 2)  # each box's 4 corners
            for start in range(0, len(self.footprints), 64):  # bounded memory
                quads = np.stack(self.footprints[start : start + 64])  # (m, 4, 2)
                edges = np.roll(quads, -1, axis=1) - quads
                rel = points[None, None, :, :] - quads[:, :, None, :]  # (m, 4, p, 2)
                cross = edges[:, :, None, 0] * rel[..., 1] - edges[:, :, None, 1] * rel[..., 0]
                # inside a convex quad: on the same side of its four edges (either winding)
                inside = np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)  # (m, p)
                count += inside.reshape(len(quads), len(cells), 4).all(axis=2).sum(axis=0)
        return {cell.index: 1.0 + n for cell, n in zip(cells, count, strict=True)}


@dataclass(frozen=True)
class TractPlan:
    """The patches of one tract that inputs of ``band`` may touch."""

    tract: Tract
    band: str | None
    patches: tuple[PatchPlan, ...]


def _region_corners(tract: Tract, x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    ra, dec = tract.pixel_to_sky(np.array([x0, x1, x1, x0]), np.array([y0, y0, y1, y1]))
    return np.column_stack([ra, dec])


def plan_tract(
    index: ExposureIndex,
    skymap: SkyMap,
    tract_id: int,
    patches: Sequence[tuple[int, int]] | None = None,
    band: str | None = None,
) -> TractPlan:
    """The patches of tract ``tract_id`` (or only ``patches``) that inputs may touch.

    An input may touch a patch when its footprint (the corners of its valid box, pushed
    outward, projected on the tract) overlaps the patch's outer box: the inputs of each
    patch are a superset of those its cells accept (the builder selects exactly).

    Raises
    ------
    ConfigError
        When inputs of several bands touch the tract and no ``band`` is given.
    """
    tract = skymap[tract_id]
    wanted = None if patches is None else {(int(p[0]), int(p[1])) for p in patches}
    if wanted is not None:
        for px, py in wanted:
            tract.patch(px, py)  # IndexError naming the tract for a patch outside it
    box = tract.bbox.grow(tract.config.cell_outer * (tract.config.patch_border_cells + 1))
    corners = _region_corners(
        tract, box.x_start - 0.5, box.x_stop - 0.5, box.y_start - 0.5, box.y_stop - 0.5
    )
    rows = index.query(corners, band)
    bands = sorted({row.band for row in rows})
    if band is None and len(bands) > 1:
        raise ConfigError(
            f"inputs of bands {bands} touch tract {tract_id} in {index.path}: give one band "
            "(a run builds one band)"
        )
    assigned: dict[tuple[int, int], list[tuple[IndexedExposure, np.ndarray]]] = {}
    side = tract.config.patch_inner
    n = tract.config.patches_per_tract
    reach = tract.config.cell_inner * tract.config.patch_border_cells + tract.config.cell_border
    for row in rows:
        x, y = tract.sky_to_pixel(row.corners[:, 0], row.corners[:, 1])
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            continue  # 90 deg or more from the tract's tangent point
        footprint = np.column_stack([x, y])  # shared by every patch it may touch
        # patches whose outer box (inner box + reach) overlaps the footprint's bounding box
        lo_x = int(np.floor((x.min() + 0.5 - reach) / side))
        hi_x = int(np.floor((x.max() + 0.5 + reach) / side))
        lo_y = int(np.floor((y.min() + 0.5 - reach) / side))
        hi_y = int(np.floor((y.max() + 0.5 + reach) / side))
        for py in range(max(lo_y, 0), min(hi_y, n - 1) + 1):
            for px in range(max(lo_x, 0), min(hi_x, n - 1) + 1):
                if wanted is None or (px, py) in wanted:
                    assigned.setdefault((px, py), []).append((row, footprint))
    keys = sorted(assigned if wanted is None else wanted, key=lambda k: (k[1], k[0]))
    plans = []
    for key in keys:
        members = assigned.get(key, [])
        plans.append(
            PatchPlan(
                patch=tract.patch(*key),
                inputs=tuple(row.id for row, _ in members),
                files=tuple((f.path, f.size, f.mtime_ns) for row, _ in members for f in row.files),
                footprints=tuple(quad for _, quad in members),
            )
        )
    return TractPlan(tract=tract, band=band or (bands[0] if bands else None), patches=tuple(plans))


# -- the task a worker runs ---------------------------------------------------------------


@dataclass(frozen=True)
class PatchTask:
    """Everything a worker needs to build one patch (a few kB, whatever the inputs)."""

    index_path: str
    patch: Patch
    inputs: tuple[int, ...]
    config_json: str
    seed: int
    output: str


def _task_inputs(task: PatchTask) -> list[Any]:
    """The task's inputs as described in the index (no header parsed), after checking
    that every file is still the one indexed.

    Raises
    ------
    InputError
        When an input file changed since it was indexed (names the file).
    """
    with ExposureIndex(task.index_path, readonly=True) as index:
        rows = index.by_ids(task.inputs)
    for row in rows:
        for stamp in row.files:
            reason = stamp.changed()
            if reason is not None:
                raise InputError(
                    f"input (visit={row.visit}, detector={row.detector}): {reason} since it "
                    f"was indexed in {task.index_path}; run `cellcoadd index` again"
                )
    return [row.described() for row in rows]


def build_part_task(
    task: PatchTask, cells: tuple[tuple[int, int], ...] | None = None
) -> tuple[PatchCoadd, dict[str, Any]]:
    """Build ``cells`` of the task's patch (all when None), in a worker: the partial patch
    (each cell bit-identical to the same cell of the whole patch) and what it cost.

    Raises
    ------
    InputError
        When an input file changed since it was indexed (names the file).
    CellBuildError, CellCoaddFormatError
        From the build or the reads (naming the cell and the file).
    """
    from cellcoadd.builder import build_patch

    wall, cpu = time.perf_counter(), time.process_time()
    inputs = _task_inputs(task)
    config = BuildConfig.model_validate_json(task.config_json)
    coadd = build_patch(task.patch, inputs, config, task.seed, progress=False, cells=cells)
    cost = {
        "inputs": len(inputs),
        "wall_s": time.perf_counter() - wall,
        "cpu_s": time.process_time() - cpu,
        "peak_rss_mb": _peak_rss_mb(),
        "worker": f"{socket.gethostname()}:{os.getpid()}",
    }
    return coadd, cost


def write_patch_task(task: PatchTask, *parts: tuple[PatchCoadd, dict[str, Any]]) -> dict[str, Any]:
    """Put the parts of the task's patch together, write its file (atomically, in a
    worker) and return the summary of what it did (a few kB).

    ``wall_s`` and ``cpu_s`` add up the parts' and the writing's (worker seconds);
    ``peak_rss_mb`` is the largest of the processes involved.
    """
    from cellcoadd.builder.patch import merge_patch_parts
    from cellcoadd.io.api import write

    wall, cpu = time.perf_counter(), time.process_time()
    coadd = parts[0][0] if len(parts) == 1 else merge_patch_parts([part for part, _ in parts])
    write(coadd, task.output, overwrite=True)
    checksum = file_sha256(task.output)
    used: set[tuple[int, int]] = set()
    rejected: dict[str, int] = {}
    depth = []
    for index_, cell in coadd.cells.items():
        depth.append([index_[0], index_[1], cell.n_used])
        for record in cell.inputs:
            if record.is_used:
                used.add((record.visit, record.detector))
            else:
                status = str(getattr(record.status, "value", record.status))
                rejected[status] = rejected.get(status, 0) + 1
    inner = set(coadd.inner_cell_indices)
    costs = [cost for _, cost in parts]
    return {
        "patch": list(task.patch.index),
        "output": task.output,
        "checksum": checksum,
        "size": os.path.getsize(task.output),
        "cells": len(coadd.cells),
        "inner_cells": len(inner),
        "empty_cells": sum(cell.is_empty for cell in coadd.cells.values()),
        "empty_inner_cells": sum(coadd.cells[i].is_empty for i in inner),
        "inputs": costs[0]["inputs"],
        "inputs_used": len(used),
        "rejected_records": dict(sorted(rejected.items())),
        "depth": depth,
        "parts": len(parts),
        "parts_cpu_s": [round(c["cpu_s"], 4) for c in costs],
        "wall_s": round(sum(c["wall_s"] for c in costs) + time.perf_counter() - wall, 4),
        "cpu_s": round(sum(c["cpu_s"] for c in costs) + time.process_time() - cpu, 4),
        "peak_rss_mb": round(max(_peak_rss_mb(), *(c["peak_rss_mb"] for c in costs)), 1),
        "worker": f"{socket.gethostname()}:{os.getpid()}",
    }


def build_patch_task(task: PatchTask) -> dict[str, Any]:
    """Build one patch and write its file (in a worker): the summary of what it did.

    Raises
    ------
    InputError
        When an input file changed since it was indexed (names the file).
    CellBuildError, CellCoaddFormatError
        From the build or the reads (naming the cell and the file).
    """
    return write_patch_task(task, build_part_task(task))


def parts_per_patch(patches: int, workers: int, most: int = 8) -> list[int]:
    """Into how many parts to cut each of ``patches`` patches, in the order they are
    submitted (largest first), so that ``workers`` stay busy to the end.

    Whole patches are the cheapest tasks (a part maps its patch's inputs again, and a
    worker gathers the parts to write the file), so only the last ``patches % workers``
    patches are cut, each into ``workers`` parts (at most ``most``): the whole ones keep
    every worker busy, and the parts share the remainder out. Nine patches on two
    workers: eight whole, the ninth in two parts (4.5 patches per worker instead of 5
    and 4); 100 on two: all whole; one on eight: eight parts.
    """
    if patches <= 0:
        return []
    if workers <= 1:
        return [1] * patches
    cut = patches % workers
    return [1] * (patches - cut) + [min(workers, most)] * cut


def _peak_rss_mb() -> float:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1024.0 if sys.platform != "darwin" else peak / 2**20  # KiB on Linux


# -- running ------------------------------------------------------------------------------


@dataclass
class RunResult:
    """What a run did: patches built now, already up to date, failed (with the reason),
    without inputs; the report's path."""

    out_dir: Path
    planned: list[tuple[int, int]] = field(default_factory=list)
    built: list[tuple[int, int]] = field(default_factory=list)
    up_to_date: list[tuple[int, int]] = field(default_factory=list)
    failed: dict[tuple[int, int], str] = field(default_factory=dict)
    no_inputs: list[tuple[int, int]] = field(default_factory=list)
    retries: int = 0
    wall_s: float = 0.0
    report: Path | None = None
    figure: Path | None = None

    def as_report(self) -> dict[str, Any]:
        """What this run did, as ``report.json`` lists it under ``this_run``."""
        return {
            "planned": len(self.planned),
            "built": [list(p) for p in self.built],
            "up_to_date": len(self.up_to_date),
            "failed": {f"{p[0]},{p[1]}": why for p, why in self.failed.items()},
            "no_inputs": [list(p) for p in self.no_inputs],
            "retries": self.retries,
            "wall_s": round(self.wall_s, 3),
        }

    def summary(self) -> str:
        return (
            f"{self.out_dir}: {len(self.planned)} patches planned, {len(self.built)} built, "
            f"{len(self.up_to_date)} up to date, {len(self.failed)} failed, "
            f"{len(self.no_inputs)} without inputs, {self.retries} retries "
            f"({self.wall_s:.1f} s)"
        )


def output_path(
    out_dir: str | os.PathLike[str], tract: int, patch: tuple[int, int], fmt: str
) -> Path:
    """``DIR/tract_T/patch_X_Y.fits`` (or ``.h5``)."""
    if fmt not in FORMATS:
        raise ConfigError(f"unknown output format {fmt!r}; choose one of {sorted(FORMATS)}")
    return Path(out_dir) / f"tract_{tract}" / f"patch_{patch[0]}_{patch[1]}{FORMATS[fmt]}"


def run_tract(
    index_path: str | os.PathLike[str],
    skymap: SkyMap,
    tract_id: int,
    out_dir: str | os.PathLike[str],
    *,
    config: BuildConfig | None = None,
    seed: int = 0,
    patches: Sequence[tuple[int, int]] | None = None,
    band: str | None = None,
    fmt: str = "fits",
    workers: int = 1,
    scheduler: object | None = None,
    retries: int = 2,
    verify: bool = False,
    progress: bool = True,
    figure: bool = True,
    command: str | None = None,
) -> RunResult:
    """Build the patches of a tract that inputs may touch (or ``patches``) into
    ``out_dir``, skipping those already built from the same inputs and settings.

    Parameters
    ----------
    index_path : path-like
        Exposure index (``cellcoadd index``).
    skymap : SkyMap
        Any sky map; ``tract_id`` is one of its tracts.
    out_dir : path-like
        Output directory: ``tract_T/patch_X_Y.fits|.h5``, ``ledger.sqlite``,
        ``report.json``, ``coverage.png``. Created if needed.
    config, seed
        Build configuration (default ``BuildConfig()``) and noise seed.
    patches : sequence of (int, int), optional
        Only these patches (default: every patch an input may touch).
    band : str, optional
        The band to build (required when inputs of several bands touch the tract).
    fmt : {"fits", "h5"}
        Output format (uncompressed, as ``cellcoadd build`` writes by default).
    workers : int
        1: build here, one patch after the other. More: a dask ``LocalCluster`` of
        ``workers`` processes with one thread each.
    scheduler : str or distributed.Client, optional
        A dask.distributed scheduler address (or client) instead of a local cluster.
    retries : int
        Further attempts of a failing patch before it is recorded as failed.
    verify : bool
        Check the SHA-256 of outputs recorded as done (default: their size).
    progress : bool
        Show a progress bar across patches.
    figure : bool
        Draw ``coverage.png``.
    command : str, optional
        What started the run (recorded in the ledger and the lock).

    Returns
    -------
    RunResult
        ``failed`` names each patch that failed and why; the caller decides the exit code.

    Raises
    ------
    RunLockedError
        When another run holds ``out_dir``.
    """
    start = time.perf_counter()
    if workers > 1 or scheduler is not None:
        _import_distributed()  # a clear error before any work
    config = config or BuildConfig()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    result = RunResult(out_dir=out_dir)
    index_path = os.path.abspath(os.fspath(index_path))
    with RunLock(out_dir, command), Ledger(out_dir) as ledger:
        with ExposureIndex(index_path, readonly=True) as index:
            plan = plan_tract(index, skymap, tract_id, patches, band)
        config_json = config.model_dump_json()
        common = {
            "config_hash": config_hash(config_json),
            "seed": seed,
            "version": __version__,
            "band": plan.band,
            "format": fmt,
            "skymap": skymap.config.model_dump(mode="json"),
            "tract_center": list(plan.tract.center),
        }
        known = ledger.rows(tract_id)
        tasks: list[tuple[PatchTask, dict[str, Any]]] = []
        plans: dict[tuple[int, int], PatchPlan] = {}
        for item in plan.patches:
            target = output_path(out_dir, tract_id, item.index, fmt)
            files = [list(f) for f in item.files]
            fields = {**common, "patch": list(item.index), "inputs": files}
            record: dict[str, Any] = {
                "band": plan.band,
                "signature": patch_signature(fields),
                "config_hash": common["config_hash"],
                "seed": seed,
                "version": __version__,
                "inputs": files,
                "output": str(target),
            }
            result.planned.append(item.index)
            if not item.inputs:
                result.no_inputs.append(item.index)
                target.unlink(missing_ok=True)  # built before from inputs now gone: stale
                ledger.set(tract_id, item.index, state="no_inputs", **record)
                continue
            old = known.get((tract_id, item.index))
            if old is not None and old.is_current(record["signature"], verify):
                result.up_to_date.append(item.index)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            _remove_temporaries(target)
            ledger.set(tract_id, item.index, state="pending", **record)
            task = PatchTask(index_path, item.patch, item.inputs, config_json, seed, str(target))
            tasks.append((task, record))
            plans[item.index] = item
        run_id = ledger.start_run(command or " ".join(sys.argv), len(plan.patches))

        def done(task: PatchTask, record: dict[str, Any], outcome: Any, attempts: int) -> None:
            key = task.patch.index
            if isinstance(outcome, dict):
                result.built.append(key)
                ledger.set(
                    tract_id,
                    key,
                    state="done",
                    checksum=outcome["checksum"],
                    size=outcome["size"],
                    attempts=attempts,
                    summary={**outcome, "attempts": attempts},
                    **record,
                )
            else:
                message = _error_text(outcome)
                result.failed[key] = message
                Path(task.output).unlink(missing_ok=True)  # never an old file beside "failed"
                ledger.set(
                    tract_id, key, state="failed", attempts=attempts, error=message, **record
                )
            result.retries += attempts - 1

        if tasks:
            execute = _run_here if workers <= 1 and scheduler is None else _run_on_dask
            execute(tasks, done, retries=retries, workers=workers, scheduler=scheduler,
                    progress=progress, plans=plans)  # fmt: skip
        ledger.finish_run(run_id, len(result.built), len(result.failed))
        result.wall_s = time.perf_counter() - start
        result.report, result.figure = write_report(
            ledger, plan.tract, out_dir, result.as_report(), figure=figure
        )
    return result


def _remove_temporaries(target: Path) -> None:
    """Temporary files of killed writers of ``target`` (on this host)."""
    from cellcoadd.io._files.atomic import remove_stale_temporaries

    remove_stale_temporaries(target)


def _error_text(err: BaseException) -> str:
    """One short paragraph: the error's type and message (without a carried traceback)."""
    text = str(err).split("\nTraceback", 1)[0].strip()
    return f"{type(err).__name__}: {text}"[:2000]


Done = Callable[[PatchTask, dict[str, Any], Any, int], None]


def _bar(total: int, progress: bool) -> Any:
    from tqdm.auto import tqdm

    return tqdm(total=total, desc="patches", unit="patch", disable=not progress)


def _run_here(
    tasks: list[tuple[PatchTask, dict[str, Any]]],
    done: Done,
    *,
    retries: int,
    progress: bool,
    **_: Any,
) -> None:
    """Build the patches in this process, one after the other."""
    with _bar(len(tasks), progress) as bar:
        for task, record in tasks:
            attempt = 0
            while attempt <= retries:
                attempt += 1
                try:
                    outcome: Any = build_patch_task(task)
                    break
                except Exception as err:  # recorded: the run goes on with the others
                    outcome = err
            done(task, record, outcome, attempt)
            bar.update(1)


def dask_cluster(workers: int) -> tuple[Any, Callable[[], None]]:
    """A ``distributed.Client`` on a new ``LocalCluster`` of ``workers`` processes (one
    thread each) and how to close both.

    A worker that dies fails its task at once (``allowed-failures`` 0), so that the run's
    own retries count it; the workers keep arrays above 128 kB on the heap (see
    :func:`cellcoadd.builder.build_patch`, notes).

    Raises
    ------
    MissingDependencyError
        When dask.distributed is not installed.
    """
    distributed = _import_distributed()
    import dask

    from cellcoadd.builder.executors import DASK_WORKER_CONFIG

    with dask.config.set({**DASK_WORKER_CONFIG, "distributed.scheduler.allowed-failures": 0}):
        cluster = distributed.LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",  # any free port: no clash with another cluster
        )
        client = distributed.Client(cluster)

    def close() -> None:
        client.close()
        cluster.close()

    return client, close


def _import_distributed() -> Any:
    try:
        import distributed
    except ImportError:
        raise MissingDependencyError(
            "runs on several workers or a scheduler need dask.distributed: "
            "pip install 'cellcoadd[dask]' (or run with --workers 1)",
            package="distributed",
        ) from None
    return distributed


def _run_on_dask(
    tasks: list[tuple[PatchTask, dict[str, Any]]],
    done: Done,
    *,
    retries: int,
    workers: int,
    scheduler: object | None,
    progress: bool,
    plans: dict[tuple[int, int], PatchPlan],
) -> None:
    """Build the patches as dask tasks, one per patch, largest first, the last ones cut into
    parts of equal estimated cost when the patches do not share out evenly
    (:func:`parts_per_patch`; :meth:`PatchPlan.cell_costs` of ``plans``: runs of cells
    built by :func:`build_part_task`, gathered and written by :func:`write_patch_task`
    on a worker, never here); a failed patch is submitted again (``retries`` times);
    results are recorded as they arrive."""
    from cellcoadd.builder.patch import parts_by_cost

    distributed = _import_distributed()
    if scheduler is None:
        client, close = dask_cluster(workers)
    elif isinstance(scheduler, distributed.Client):
        client, close = scheduler, (lambda: None)
    else:
        client = distributed.Client(scheduler)
        close = client.close
    try:
        attempts: dict[str, int] = {}
        meta: dict[str, tuple[PatchTask, dict[str, Any]]] = {}
        # the largest first (inputs: the cost scales with them), the cut ones last; only
        # those are costed cell by cell (~0.15 s for 484 cells and 800 inputs)
        tasks = sorted(tasks, key=lambda item: -len(item[0].inputs))
        n_parts = dict(
            zip(
                (task.patch.index for task, _ in tasks),
                parts_per_patch(len(tasks), sum(client.nthreads().values())),
                strict=True,
            )
        )

        def submit(task: PatchTask, record: dict[str, Any], attempt: int) -> Any:
            px, py = task.patch.index
            key = f"cellcoadd-patch-{task.patch.tract.id}-{px}-{py}-{attempt}-{os.urandom(4).hex()}"
            if n_parts[task.patch.index] == 1:
                future = client.submit(build_patch_task, task, key=key, pure=False)
            else:
                # the parts stay on the workers: the one writing the patch gathers them
                parts = [
                    client.submit(
                        build_part_task,
                        task,
                        tuple(c.index for c in cells),
                        key=f"{key}-part{k}",
                        pure=False,
                    )  # fmt: skip
                    for k, cells in enumerate(
                        parts_by_cost(
                            task.patch.cells,
                            plans[task.patch.index].cell_costs(),
                            n_parts[task.patch.index],
                        )
                    )
                ]
                future = client.submit(write_patch_task, task, *parts, key=key, pure=False)
            attempts[future.key] = attempt
            meta[future.key] = (task, record)
            return future

        futures = [submit(task, record, 1) for task, record in tasks]
        queue = distributed.as_completed(futures)
        with _bar(len(tasks), progress) as bar:
            for future in queue:
                task, record = meta.pop(future.key)
                attempt = attempts.pop(future.key)
                try:
                    outcome: Any = future.result()
                except Exception as err:  # a failed build, a killed worker (KilledWorker)
                    if attempt <= retries:
                        queue.add(submit(task, record, attempt + 1))
                        continue
                    outcome = err
                finally:
                    future.release()
                done(task, record, outcome, attempt)
                bar.update(1)
    finally:
        close()
