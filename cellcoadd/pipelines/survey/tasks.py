"""What a worker does for one patch: read its inputs as the index describes them (after
checking them against their files), build the patch (or a part of it), write its file.

A task carries the patch, the index rows of its inputs, the configuration, the output
path and the trust given to PSF model files by the run's own configuration: a few kB.
The worker opens the index read-only, checks each row against its checksum, checks that
each input file is still the one indexed (size and mtime) and that the fields the build
uses (identity, band, zero point, shape, valid box, mask bits, WCS) are what the file
says now, builds with :func:`~cellcoadd.builder.build_patch` (serially: one patch per
worker at a time bounds its memory by one patch), writes with
:func:`cellcoadd.io.api.write` (atomic) and returns a :class:`PatchSummary`.
"""

from __future__ import annotations

import os
import resource
import socket
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cellcoadd.geometry.tract import Patch
from cellcoadd.io._files.stamps import file_sha256
from cellcoadd.io.exposures.index import ExposureIndex
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.patch_coadd import PatchCoadd
from cellcoadd.model.sources import DescribedSource
from cellcoadd.pipelines.survey.records import PatchKey, PatchSummary


@dataclass(frozen=True)
class PatchTask:
    """Everything a worker needs to build one patch (a few kB, whatever the inputs).

    ``output`` is relative to ``out_dir``; ``trust_psf`` comes from the run's
    configuration (never from the index)."""

    index_path: str
    key: PatchKey
    patch: Patch
    inputs: tuple[int, ...]
    config_json: str
    seed: int
    out_dir: str
    output: str
    trust_psf: bool = False

    @property
    def target(self) -> Path:
        return Path(self.out_dir) / self.output


def task_inputs(task: PatchTask) -> list[DescribedSource]:
    """The task's inputs as described in the index, each checked against its checksum,
    its files (size and mtime) and its file's header.

    Raises
    ------
    InputError
        When an input file changed or vanished since it was indexed (names the file).
    IndexRowError
        When a row disagrees with its checksum or its file (names the file and fields).
    """
    with ExposureIndex(task.index_path, readonly=True) as index:
        rows = index.by_ids(task.inputs)
    sources = []
    for row in rows:
        changed = row.not_as_indexed(task.index_path)
        if changed is not None:
            raise changed
        sources.append(row.cross_check(row.source(task.trust_psf)))
    return sources


def build_part_task(
    task: PatchTask, cells: tuple[tuple[int, int], ...] | None = None
) -> tuple[PatchCoadd, dict[str, Any]]:
    """Build ``cells`` of the task's patch (all when None), in a worker: the partial patch
    (each cell bit-identical to the same cell of the whole patch) and what it cost.

    Raises
    ------
    InputError, IndexRowError
        When an input is not the one indexed (see :func:`task_inputs`).
    CellBuildError, CellCoaddFormatError
        From the build or the reads (naming the cell and the file).
    """
    from cellcoadd.builder import build_patch

    wall, cpu = time.perf_counter(), time.process_time()
    inputs = task_inputs(task)
    config = BuildConfig.model_validate_json(task.config_json)
    # the build's warnings travel with the result: a worker's stderr is nobody's to read
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        coadd = build_patch(task.patch, inputs, config, task.seed, progress=False, cells=cells)
    cost = {
        "warnings": [f"{w.category.__name__}: {w.message}" for w in caught],
        "inputs": len(inputs),
        "wall_s": time.perf_counter() - wall,
        "cpu_s": time.process_time() - cpu,
        "peak_rss_mb": peak_rss_mb(),
    }
    return coadd, cost


def write_patch_task(task: PatchTask, *parts: tuple[PatchCoadd, dict[str, Any]]) -> PatchSummary:
    """Put the parts of the task's patch together, write its file (atomically, in a
    worker) and return the summary of what it did.

    ``wall_s`` and ``cpu_s`` add up the parts' and the writing's (worker seconds);
    ``peak_rss_mb`` is the largest of the processes involved.
    """
    from cellcoadd.builder.patch import merge_patch_parts
    from cellcoadd.io.api import write

    wall, cpu = time.perf_counter(), time.process_time()
    coadd = parts[0][0] if len(parts) == 1 else merge_patch_parts([part for part, _ in parts])
    target = task.target
    target.parent.mkdir(parents=True, exist_ok=True)
    write(coadd, target, overwrite=True)
    used: set[tuple[int, int]] = set()
    rejected: dict[str, int] = {}
    depth = []
    for index_, cell in coadd.cells.items():
        depth.append((index_[0], index_[1], cell.n_used))
        for record in cell.inputs:
            if record.is_used:
                used.add((record.visit, record.detector))
            else:
                status = str(getattr(record.status, "value", record.status))
                rejected[status] = rejected.get(status, 0) + 1
    inner = set(coadd.inner_cell_indices)
    costs = [cost for _, cost in parts]
    said = [line for cost in costs for line in cost.get("warnings", [])]
    return PatchSummary(
        output=task.output,
        checksum=file_sha256(target),
        size=os.path.getsize(target),
        cells=len(coadd.cells),
        inner_cells=len(inner),
        empty_cells=sum(cell.is_empty for cell in coadd.cells.values()),
        empty_inner_cells=sum(coadd.cells[i].is_empty for i in inner),
        inputs=costs[0]["inputs"],
        inputs_used=len(used),
        rejected_records=dict(sorted(rejected.items())),
        depth=depth,
        parts=len(parts),
        parts_cpu_s=[round(c["cpu_s"], 4) for c in costs],
        wall_s=round(sum(c["wall_s"] for c in costs) + time.perf_counter() - wall, 4),
        cpu_s=round(sum(c["cpu_s"] for c in costs) + time.process_time() - cpu, 4),
        peak_rss_mb=round(max(peak_rss_mb(), *(c["peak_rss_mb"] for c in costs)), 1),
        worker=f"{socket.gethostname()}:{os.getpid()}",
        warnings=list(dict.fromkeys(said)),
    )


def build_patch_task(task: PatchTask) -> PatchSummary:
    """Build one patch and write its file (in a worker): the summary of what it did.

    Raises
    ------
    InputError, IndexRowError
        When an input is not the one indexed (see :func:`task_inputs`).
    CellBuildError, CellCoaddFormatError
        From the build or the reads (naming the cell and the file).
    """
    return write_patch_task(task, build_part_task(task))


def peak_rss_mb() -> float:
    """This process's peak resident memory (MB)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1024.0 if sys.platform != "darwin" else peak / 2**20  # KiB on Linux
