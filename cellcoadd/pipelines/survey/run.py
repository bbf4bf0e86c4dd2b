"""Survey runs: every band and tract an exposure index touches (or those asked for),
planned and built on dask.distributed (or here), each worker reading its own inputs and
writing its own patch file, with one ledger that makes the run resumable, idempotent
and aware of stale outputs.

The calling process keeps the books and little else: it finds the tracts from the
index's HEALPix key (:func:`~cellcoadd.pipelines.survey.plan.candidate_tracts`), sends
one planning task per tract (the workers query the index and ``stat`` the input files),
then one small task per patch and band (:mod:`~cellcoadd.pipelines.survey.tasks`).
When the patches do not share out evenly among the workers, the last ones are cut into
parts of equal estimated cost, chosen for the workers there are when they are reached
(:func:`cellcoadd.execution.run_on_dask`). A patch's file is byte-identical to
``cellcoadd build`` of that patch with the same inputs, in the same order (visit,
detector), configuration and seed.

Outputs: ``DIR/<band>/tract_<T>/patch_<X>_<Y>.fits`` (or ``.h5``), one ledger
``DIR/ledger.sqlite``, one ``DIR/report.json`` for the run (per band and per tract), and
per tract ``DIR/<band>/tract_<T>/report.json`` (every patch) and ``coverage.png``.
Failures are retried (``retries`` times: a damaged file, a worker killed, a lost
connection; never a changed or refused input), then recorded as failed with the reason;
the other patches go on. See :mod:`~cellcoadd.pipelines.survey.ledger`.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cellcoadd._version import __version__
from cellcoadd.errors import CellCoaddRuntimeError, ConfigError
from cellcoadd.execution import (
    Outcome,
    error_text,
    import_distributed,
    local_cluster,
    run_here,
    run_on_dask,
)
from cellcoadd.geometry.footprint import check_region
from cellcoadd.geometry.skymap import SkyMap
from cellcoadd.io.exposures.index import ExposureIndex, UnusableFile
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.pipelines.survey.ledger import (
    LEDGER_NAME,
    Ledger,
    RunLock,
    config_hash,
    is_current,
    patch_signature,
)
from cellcoadd.pipelines.survey.plan import (
    PatchPlan,
    Region,
    TractPlan,
    candidate_tracts,
    plan_tract_task,
)
from cellcoadd.pipelines.survey.records import PatchKey, PatchRecord, PatchState, PatchSummary
from cellcoadd.pipelines.survey.report import coverage_lines, totals, write_reports
from cellcoadd.pipelines.survey.tasks import PatchTask, build_part_task, build_patch_task

#: Output formats: file ending of each.
FORMATS = {"fits": ".fits", "h5": ".h5"}


@dataclass
class RunResult:
    """What a run did: patches built now, already up to date, failed (with the reason),
    without inputs; tracts whose planning failed; the unusable files that may touch the
    run; the reports' paths."""

    out_dir: Path
    planned: list[PatchKey] = field(default_factory=list)
    built: list[PatchKey] = field(default_factory=list)
    up_to_date: list[PatchKey] = field(default_factory=list)
    failed: dict[PatchKey, str] = field(default_factory=dict)
    no_inputs: list[PatchKey] = field(default_factory=list)
    plan_failed: dict[int, str] = field(default_factory=dict)
    bad_inputs: list[UnusableFile] = field(default_factory=list)
    retries: int = 0
    lost_workers: int = 0
    workers_left: list[str] = field(default_factory=list)
    wall_s: float = 0.0
    report: Path | None = None
    figures: list[Path] = field(default_factory=list)
    counts: dict[str, Any] = field(default_factory=dict)
    warnings: dict[PatchKey, list[str]] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """Whether every planned patch was built or up to date (or had no inputs)."""
        return not self.failed and not self.plan_failed

    def as_report(self) -> dict[str, Any]:
        """What this run did, as ``report.json`` lists it under ``this_run``."""
        return {
            "planned": len(self.planned),
            "built": [list(k) for k in self.built],
            "up_to_date": len(self.up_to_date),
            "failed": {str(k): why for k, why in self.failed.items()},
            "plan_failed": {str(t): why for t, why in self.plan_failed.items()},
            "no_inputs": [list(k) for k in self.no_inputs],
            "retries": self.retries,
            "lost_workers": self.lost_workers,
            "workers_left": self.workers_left,
            "wall_s": round(self.wall_s, 3),
        }

    def summary(self) -> str:
        text = (
            f"{self.out_dir}: {len(self.planned)} patches planned, {len(self.built)} built, "
            f"{len(self.up_to_date)} up to date, {len(self.failed)} failed, "
            f"{len(self.no_inputs)} without inputs, {self.retries} retries"
        )
        if self.lost_workers:
            text += f", {self.lost_workers} tasks moved after a worker died"
        if self.workers_left:
            text += f", {len(self.workers_left)} workers left during the run"
        if self.plan_failed:
            text += f", {len(self.plan_failed)} tracts not planned"
        return text + f" ({self.wall_s:.1f} s)"

    def summary_lines(self) -> list[str]:
        """:meth:`summary`, then what the planned patches hold (cells, empty cells, input
        records used and rejected by reason, as ``cellcoadd build`` says it) and the
        build's warnings of the patches built now, one line per kind."""
        lines = [self.summary()]
        if self.counts.get("cells"):
            lines += coverage_lines(self.counts)
        # one line per kind of warning, whatever the number of patches: the first said,
        # and how many patches said one (each patch's are in its tract's report.json)
        by_kind: dict[str, list[tuple[PatchKey, str]]] = {}
        for key, said in sorted(self.warnings.items()):
            for text in said:
                by_kind.setdefault(text.split(":", 1)[0], []).append((key, text))
        for items in by_kind.values():
            keys = {key for key, _ in items}
            key, text = items[0]
            more = f" (and {len(keys) - 1} more patches: see report.json)" if len(keys) > 1 else ""
            lines.append(f"warning: {key}: {text}{more}")
        return lines


def output_path(key: PatchKey, fmt: str) -> str:
    """``<band>/tract_<T>/patch_<X>_<Y>.fits`` (or ``.h5``): relative to the output
    directory."""
    if fmt not in FORMATS:
        raise ConfigError(f"unknown output format {fmt!r}; choose one of {sorted(FORMATS)}")
    return f"{key.band}/tract_{key.tract}/patch_{key.px}_{key.py}{FORMATS[fmt]}"


def _refuse_older_layout(out_dir: Path) -> None:
    """An output directory of the older layout (``tract_T/`` at its top, no band) is never
    mixed with this one."""
    if (out_dir / LEDGER_NAME).exists():
        return  # the ledger's own version check decides
    older = sorted(p.name for p in out_dir.glob("tract_*") if p.is_dir())
    if older:
        raise ConfigError(
            f"{out_dir} holds {', '.join(older[:3])} of an older layout (no band in the "
            "paths) without a ledger of this version: give a new --out-dir"
        )


def run_survey(
    index_path: str | os.PathLike[str],
    skymap: SkyMap,
    out_dir: str | os.PathLike[str],
    *,
    bands: Sequence[str] | None = None,
    tracts: Sequence[int] | None = None,
    region: Region | None = None,
    patches: Sequence[tuple[int, int]] | None = None,
    config: BuildConfig | None = None,
    seed: int = 0,
    fmt: str = "fits",
    workers: int = 1,
    scheduler: object | None = None,
    retries: int = 2,
    verify: bool = False,
    trust_psf: bool = False,
    progress: bool = True,
    figure: bool = True,
    command: str | None = None,
) -> RunResult:
    """Build every patch, in every band, that inputs of the index may touch (narrowed by
    ``bands``, ``tracts``, ``region``, ``patches``) into ``out_dir``, skipping those
    already built from the same inputs and settings.

    Parameters
    ----------
    index_path : path-like
        Exposure index (``cellcoadd index``).
    skymap : SkyMap
        Any sky map; an output directory holds one sky map's patches.
    out_dir : path-like
        Output directory: ``<band>/tract_<T>/patch_<X>_<Y>.fits|.h5``, ``ledger.sqlite``,
        ``report.json``, per tract ``report.json`` and ``coverage.png``. Created if needed.
    bands : sequence of str, optional
        Only these bands (each must be in the index).
    tracts : sequence of int, optional
        Only these tracts (default: every tract the index's inputs may touch).
    region : (ra0, ra1, dec0, dec1), optional
        Only patches whose inner region meets this RA/Dec box (deg; ``ra0 > ra1`` wraps
        through RA 0).
    patches : sequence of (int, int), optional
        Only these patches of each tract (each planned even without inputs).
    config, seed
        Build configuration (default ``BuildConfig()``) and noise seed.
    fmt : {"fits", "h5"}
        Output format (uncompressed, as ``cellcoadd build`` writes by default).
    workers : int
        1: plan and build here, one patch after the other. More: a dask ``LocalCluster``
        of ``workers`` processes with one thread each.
    scheduler : str or distributed.Client, optional
        A dask.distributed scheduler address (or client) instead of a local cluster.
    retries : int
        Further attempts of a failing patch before it is recorded as failed.
    verify : bool
        Check the SHA-256 of outputs recorded as done (default: their size).
    trust_psf : bool
        Load pickle-bearing PSF model files (Piff): only for files you trust. Never taken
        from the index.
    progress : bool
        Show progress bars (planning, patches).
    figure : bool
        Draw each tract's ``coverage.png``.
    command : str, optional
        What started the run (recorded in the ledger and the lock).

    Returns
    -------
    RunResult
        ``failed`` names each patch that failed and why, ``plan_failed`` each tract that
        could not be planned; the caller decides the exit code.

    Raises
    ------
    RunLockedError
        When another run holds ``out_dir``.
    ConfigError
        For a band not in the index, a tract not in the sky map, a bad region, an output
        directory of an older layout or another sky map.
    """
    start = time.perf_counter()
    if retries < 0:
        raise ConfigError(f"retries must be >= 0, not {retries}")
    if workers < 1:
        raise ConfigError(f"workers must be >= 1, not {workers}")
    on_dask = workers > 1 or scheduler is not None
    if on_dask:
        import_distributed()  # a clear error before any work
    region = check_region(region) if region is not None else None
    config = config or BuildConfig()
    out_dir = Path(out_dir).absolute()
    out_dir.mkdir(parents=True, exist_ok=True)
    _refuse_older_layout(out_dir)
    index_path = os.path.abspath(os.fspath(index_path))
    result = RunResult(out_dir=out_dir)
    skymap_json = skymap.to_json()
    with RunLock(out_dir, command), Ledger(out_dir, skymap_json) as ledger:
        with ExposureIndex(index_path, readonly=True) as index:
            index.check_footprints()
            known_bands = index.bands()
            if bands is not None:
                unknown = sorted(set(bands) - set(known_bands))
                if unknown:
                    raise ConfigError(
                        f"band(s) {unknown} have no usable input in {index_path}; its bands "
                        f"are {known_bands}"
                    )
                bands = sorted(set(bands))
            if tracts is not None:
                for tract_id in tracts:
                    skymap[int(tract_id)]  # CellCoaddIndexError naming the sky map's size
                tract_ids = sorted({int(t) for t in tracts})
            else:
                tract_ids = candidate_tracts(index, skymap, bands, region)
            unusable = index.unusable()
        client, close = _client(workers, scheduler) if on_dask else (None, lambda: None)
        try:
            plans = _plan(
                client, index_path, skymap, tract_ids, bands, patches, region, result, progress,
                retries,
            )  # fmt: skip
            result.bad_inputs = _bad_inputs_near(unusable, plans, bands)
            tasks, records = _to_build(
                plans, skymap, ledger, result, out_dir, index_path, config, seed, fmt, verify,
                trust_psf,
            )  # fmt: skip
            run_id = ledger.start_run(command or " ".join(sys.argv), len(result.planned))
            done = _recorder(ledger, records, result, out_dir)
            if tasks:
                with _bar(len(tasks), progress, "patches", "patch") as bar:
                    if client is None:
                        run_here(tasks, build_patch_task, done, retries=retries, progress=bar)
                    else:
                        result.workers_left = _run_patches_on_dask(
                            client, tasks, plans, done, retries, bar
                        )
            ledger.finish_run(run_id, len(result.built), len(result.failed))
            planned = set(result.planned)
            result.counts = totals(r for k, r in ledger.records().items() if k in planned)
            result.wall_s = time.perf_counter() - start
            result.report, result.figures = write_reports(
                ledger, plans, out_dir, result.as_report(), result.plan_failed,
                result.bad_inputs, figure=figure, client=client,
            )  # fmt: skip
        finally:
            close()
    result.wall_s = time.perf_counter() - start
    return result


def run_tract(
    index_path: str | os.PathLike[str],
    skymap: SkyMap,
    tract_id: int,
    out_dir: str | os.PathLike[str],
    *,
    band: str | None = None,
    **options: Any,
) -> RunResult:
    """:func:`run_survey` of one tract (and one band, when given)."""
    return run_survey(
        index_path,
        skymap,
        out_dir,
        tracts=[tract_id],
        bands=None if band is None else [band],
        **options,
    )


def _client(workers: int, scheduler: object | None) -> tuple[Any, Callable[[], None]]:
    """The dask client to use and how to release it."""
    from cellcoadd.execution import dask_client

    if scheduler is None:
        return local_cluster(workers)
    client, release = dask_client(scheduler)
    return client, release or (lambda: None)


def _bar(total: int, progress: bool, desc: str, unit: str) -> Any:
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit=unit, disable=not progress)


def _plan(
    client: Any,
    index_path: str,
    skymap: SkyMap,
    tract_ids: list[int],
    bands: Sequence[str] | None,
    patches: Sequence[tuple[int, int]] | None,
    region: Region | None,
    result: RunResult,
    progress: bool,
    retries: int,
) -> list[TractPlan]:
    """Every tract's plans: on the cluster, one task per tract (here without one), with
    the run's retries; a tract whose planning fails is recorded in ``result.plan_failed``."""
    band_arg = None if bands is None else tuple(bands)
    patch_arg = None if patches is None else tuple((int(p[0]), int(p[1])) for p in patches)
    plans: list[TractPlan] = []

    def done(outcome: Outcome[int]) -> None:
        if outcome.ok:
            plans.extend(outcome.result)
        else:
            result.plan_failed[outcome.item] = error_text(
                outcome.error or CellCoaddRuntimeError("no plan returned")
            )
        result.retries += outcome.attempts - 1
        result.lost_workers += outcome.lost_workers

    with _bar(len(tract_ids), progress and len(tract_ids) > 1, "tracts planned", "tract") as bar:
        if client is None:

            def plan_here(tract_id: int) -> list[TractPlan]:
                return plan_tract_task(index_path, skymap, tract_id, band_arg, patch_arg, region)

            run_here(tract_ids, plan_here, done, retries=retries, progress=bar)
        else:
            scattered = client.scatter(skymap, broadcast=True)

            def submit(tract_id: int, attempt: int, parts: int, key: str) -> list[Any]:
                return [
                    client.submit(
                        plan_tract_task,
                        index_path,
                        scattered,
                        tract_id,
                        band_arg,
                        patch_arg,
                        region,
                        key=key,
                        pure=False,
                    )  # fmt: skip
                ]

            run_on_dask(
                client, tract_ids, submit, done, retries=retries, name="cellcoadd-plan",
                progress=bar, cut=False,
            )  # fmt: skip
    return sorted(plans, key=lambda p: (p.band, p.tract.id))


def _bad_inputs_near(
    unusable: list[UnusableFile], plans: list[TractPlan], bands: Sequence[str] | None
) -> list[UnusableFile]:
    """The unusable files that may touch the planned tracts: those whose stored footprint
    projects onto a planned tract's box, and those whose place is unknown."""
    import numpy as np

    near = []
    for item in unusable:
        if bands is not None and item.band is not None and item.band not in bands:
            continue
        if item.corners is None or item.corners.shape != (4, 2):
            near.append(item)
            continue
        for plan in plans:
            if item.band is not None and item.band != plan.band:
                continue
            x, y = plan.tract.sky_to_pixel(item.corners[:, 0], item.corners[:, 1])
            box = plan.tract.bbox
            if np.all(np.isfinite(x)) and (
                x.max() >= box.x_start and x.min() < box.x_stop
                and y.max() >= box.y_start and y.min() < box.y_stop
            ):  # fmt: skip
                near.append(item)
                break
    return near


def _to_build(
    plans: list[TractPlan],
    skymap: SkyMap,
    ledger: Ledger,
    result: RunResult,
    out_dir: Path,
    index_path: str,
    config: BuildConfig,
    seed: int,
    fmt: str,
    verify: bool,
    trust_psf: bool,
) -> tuple[list[PatchTask], dict[PatchKey, PatchRecord]]:
    """The tasks of the patches to build now (their records marked pending); patches up
    to date, without inputs or with changed inputs are recorded here."""
    from cellcoadd.io._files.atomic import remove_stale_temporaries

    config_json = config.model_dump_json()
    common = {
        "config_hash": config_hash(config_json),
        "seed": seed,
        "version": __version__,
        "format": fmt,
        "skymap": skymap.config.model_dump(mode="json"),
    }
    tasks: list[PatchTask] = []
    records: dict[PatchKey, PatchRecord] = {}
    immediate: list[PatchRecord] = []
    for plan in plans:
        known = ledger.records(plan.band, plan.tract.id)
        for item in plan.patches:
            key = item.key
            output = output_path(key, fmt)
            fields = {
                **common,
                "band": key.band,
                "tract": key.tract,
                "tract_center": list(plan.tract.center),
                "patch": list(item.index),
                "inputs": [stamp.checksum for stamp in item.inputs],
            }
            record = PatchRecord(
                band=key.band, tract=key.tract, px=key.px, py=key.py,
                state=PatchState.PENDING, signature=patch_signature(fields),
                config_hash=common["config_hash"], seed=seed, version=__version__,
                inputs=list(item.inputs), output=output,
            )  # fmt: skip
            result.planned.append(key)
            target = out_dir / output
            in_the_way = _not_a_patch_file(target)
            if in_the_way is not None:  # never removed, never written through: this patch fails
                result.failed[key] = in_the_way
                immediate.append(
                    record.model_copy(update={"state": PatchState.FAILED, "error": in_the_way})
                )
                continue
            if not item.inputs:
                result.no_inputs.append(key)
                target.unlink(missing_ok=True)  # built before from inputs now gone: stale
                immediate.append(record.model_copy(update={"state": PatchState.NO_INPUTS}))
                continue
            if item.changed:
                message = (
                    "InputError: "
                    + "; ".join(item.changed[:3])
                    + (f" (and {len(item.changed) - 3} more)" if len(item.changed) > 3 else "")
                )
                result.failed[key] = message
                target.unlink(missing_ok=True)  # never an old file beside "failed"
                immediate.append(
                    record.model_copy(update={"state": PatchState.FAILED, "error": message})
                )
                continue
            old = known.get(key)
            if old is not None and is_current(old, record.signature, out_dir, verify):
                result.up_to_date.append(key)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            remove_stale_temporaries(target)
            immediate.append(record)
            records[key] = record
            tasks.append(
                PatchTask(
                    index_path,
                    key,
                    item.patch,
                    item.rows,
                    config_json,
                    seed,
                    str(out_dir),
                    output,
                    trust_psf,
                )  # fmt: skip
            )
    ledger.put_many(immediate)
    for key, why in ledger.unreadable_patches.items():  # said once, with the patch
        if key in records:
            result.warnings.setdefault(key, []).append(f"unreadable ledger row: {why}")
    # the costliest first (inputs: the cost scales with them), in a stable order
    tasks.sort(key=lambda task: (-len(task.inputs), task.key))
    return tasks, records


def _not_a_patch_file(target: Path) -> str | None:
    """Why the patch output ``target`` cannot be checked, removed or replaced (a directory,
    a link, a FIFO or a device in its place), as a failed patch's error; None if it is a
    regular file or absent."""
    from cellcoadd.errors import CellCoaddFormatError
    from cellcoadd.io._files.path_gate import gate_create

    try:
        gate_create(target, what="patch file")
    except CellCoaddFormatError as err:
        return error_text(err)
    return None


def _recorder(
    ledger: Ledger, records: dict[PatchKey, PatchRecord], result: RunResult, out_dir: Path
) -> Callable[[Outcome[PatchTask]], None]:
    """What to do with each patch's outcome: record it in the ledger and the result."""

    def done(outcome: Outcome[PatchTask]) -> None:
        task = outcome.item
        record = records[task.key]
        update: dict[str, Any] = {
            "attempts": outcome.attempts,
            "retried": outcome.retried,
            "lost_workers": outcome.lost_workers,
        }
        summary = outcome.result
        if outcome.ok and isinstance(summary, PatchSummary):
            result.built.append(task.key)
            if summary.warnings:
                result.warnings.setdefault(task.key, []).extend(summary.warnings)
            update.update(
                state=PatchState.DONE, checksum=summary.checksum, size=summary.size,
                summary=summary,
            )  # fmt: skip
        else:
            message = error_text(outcome.error or CellCoaddRuntimeError("no summary returned"))
            result.failed[task.key] = message
            (out_dir / task.output).unlink(missing_ok=True)  # never an old file beside it
            update.update(state=PatchState.FAILED, error=message)
        result.retries += outcome.attempts - 1
        result.lost_workers += outcome.lost_workers
        ledger.put(record.model_copy(update=update))

    return done


def _run_patches_on_dask(
    client: Any,
    tasks: list[PatchTask],
    plans: list[TractPlan],
    done: Callable[[Outcome[PatchTask]], None],
    retries: int,
    bar: Any,
) -> list[str]:
    """The patches as dask tasks; the workers that left during them are returned. A
    patch cut into parts builds each run of cells of equal estimated cost
    (:meth:`PatchPlan.cell_costs`, ``parts_by_cost``) as a task, and the task writing
    the file gathers them from the workers that hold them."""
    from cellcoadd.builder.patch import parts_by_cost
    from cellcoadd.pipelines.survey.tasks import write_patch_task

    by_key: dict[PatchKey, PatchPlan] = {p.key: p for plan in plans for p in plan.patches}

    def submit(task: PatchTask, attempt: int, parts: int, key: str) -> list[Any]:
        if parts <= 1:
            return [client.submit(build_patch_task, task, key=key, pure=False)]
        cells = parts_by_cost(task.patch.cells, by_key[task.key].cell_costs(), parts)
        futures = [
            client.submit(
                build_part_task, task, tuple(c.index for c in run), key=f"{key}-part{k}", pure=False
            )  # fmt: skip
            for k, run in enumerate(cells)
        ]
        # the parts stay on the workers: the one writing the patch gathers them
        return [*futures, client.submit(write_patch_task, task, *futures, key=key, pure=False)]

    return run_on_dask(
        client, tasks, submit, done, retries=retries, name="cellcoadd-patch", progress=bar
    )
