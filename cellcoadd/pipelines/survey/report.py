"""The reports of a survey run.

* ``DIR/report.json``: the run as a whole, rewritten at the end of every run: what this
  run did, totals over every patch the ledger knows, the same per band and per tract
  (with the path of each tract's own report), every failed patch and tract with the
  reason, and the unusable files (bad or vanished in the index) that may touch the run.
* ``DIR/<band>/tract_<T>/report.json`` and ``coverage.png``, for each tract and band this
  run planned: every patch (state, output and its SHA-256, cells, empty cells, inputs
  given and used, cell input records rejected by reason, CPU and wall time, parts, peak
  memory, worker, attempts and why earlier ones failed, tasks moved after a worker died,
  the error of a failed patch) and the coverage figure. On a cluster they are written by
  tasks, one per tract, so the client stays free.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cellcoadd._version import __version__
from cellcoadd.geometry.tract import Tract
from cellcoadd.pipelines.survey.ledger import Ledger
from cellcoadd.pipelines.survey.records import PatchRecord, PatchState

if TYPE_CHECKING:
    from cellcoadd.io.exposures.index import UnusableFile
    from cellcoadd.pipelines.survey.plan import TractPlan

REPORT_NAME = "report.json"
FIGURE_NAME = "coverage.png"

_COUNTS = ("cells", "empty_cells", "inner_cells", "empty_inner_cells")


def totals(records: Iterable[PatchRecord]) -> dict[str, Any]:
    """Patches by state, cells, input records used and rejected by reason, worker
    seconds, retries and lost workers, summed over ``records``."""
    totals: dict[str, Any] = {
        "patches": 0,
        **{state.value: 0 for state in PatchState},
        **{name: 0 for name in _COUNTS},
        "input_records_used": 0,
        "rejected_records": {},
        "cpu_s": 0.0,
        "wall_s": 0.0,
        "retries": 0,
        "lost_workers": 0,
    }
    for record in records:
        totals["patches"] += 1
        totals[record.state.value] += 1
        totals["retries"] += max(record.attempts - 1, 0)
        totals["lost_workers"] += record.lost_workers
        summary = record.summary
        if summary is None:
            continue
        for name in _COUNTS:
            totals[name] += getattr(summary, name)
        totals["cpu_s"] = round(totals["cpu_s"] + summary.cpu_s, 4)
        totals["wall_s"] = round(totals["wall_s"] + summary.wall_s, 4)
        totals["input_records_used"] += sum(n for _, _, n in summary.depth)
        for reason, count in summary.rejected_records.items():
            totals["rejected_records"][reason] = totals["rejected_records"].get(reason, 0) + count
    return totals


def coverage_lines(counts: dict[str, Any]) -> list[str]:
    """What the patches of ``counts`` (:func:`totals`) hold, in ``cellcoadd build``'s
    words: cells and empty cells, input records used and rejected by reason; then a
    warning line when most cells are empty or most records that touch a cell are lost
    to CCD edges (the limits of :mod:`cellcoadd.pipelines.coverage`)."""
    from cellcoadd.pipelines.coverage import EDGE_FRACTION_LIMIT, EMPTY_FRACTION_LIMIT

    rejected = dict(counts["rejected_records"])
    touching = counts["input_records_used"] + sum(
        n for reason, n in rejected.items() if reason != "no_overlap"
    )
    reasons = ", ".join(f"{reason} {n}" for reason, n in sorted(rejected.items()))
    lines = [
        f"cells: {counts['cells']} ({counts['empty_cells']} empty; inner cells "
        f"{counts['inner_cells']}, {counts['empty_inner_cells']} empty); input records (one "
        f"per cell and overlapping exposure): used {counts['input_records_used']}, "
        f"rejected: {reasons or 'none'}"
    ]
    empty = counts["empty_inner_cells"] / counts["inner_cells"] if counts["inner_cells"] else 0.0
    edge = rejected.get("edge", 0) / touching if touching else 0.0
    found = []
    if empty > EMPTY_FRACTION_LIMIT:
        found.append(
            f"{counts['empty_inner_cells']} of {counts['inner_cells']} inner cells are empty"
        )
    if edge > EDGE_FRACTION_LIMIT:
        found.append(
            f"{100 * edge:.0f}% of the input records that overlap a cell were rejected "
            "because a CCD edge or gap crosses the cell"
        )
    if found:
        lines.append(
            f"warning: {' and '.join(found)}: edge-free cells need CCDs much larger than a "
            "cell's outer box. Look at each tract's coverage.png; add visits, or use "
            "smaller cells (SkyMapConfig cell_inner, cell_border)."
        )
    return lines


def patch_entry(record: PatchRecord) -> dict[str, Any]:
    """One patch as a tract's report lists it."""
    entry: dict[str, Any] = {
        "patch": [record.px, record.py],
        "state": record.state.value,
        "output": record.output if record.state == PatchState.DONE else None,
        "checksum": record.checksum,
        "attempts": record.attempts,
        "retries": max(record.attempts - 1, 0),
        "retried": record.retried,
        "lost_workers": record.lost_workers,
        "error": record.error,
        "inputs_indexed": len(record.inputs),
    }
    if record.summary is not None:
        entry.update(record.summary.model_dump(exclude={"output", "checksum", "size", "depth"}))
    return entry


def tract_report(tract: Tract, band: str, records: list[PatchRecord]) -> dict[str, Any]:
    """The content of a tract's ``report.json`` (JSON-able)."""
    records = sorted(records, key=lambda r: (r.py, r.px))
    return {
        "band": band,
        "tract": tract.id,
        "library_version": __version__,
        "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "totals": totals(records),
        "patches": [patch_entry(r) for r in records],
    }


def write_tract_outputs(
    out_dir: str, tract: Tract, band: str, records: list[PatchRecord], figure: bool
) -> list[str]:
    """Write a tract's ``report.json`` (and ``coverage.png``): their paths, relative to
    ``out_dir`` (in any process)."""
    from cellcoadd.io._files.atomic import atomic_write, atomic_write_text

    folder = f"{band}/tract_{tract.id}"
    (Path(out_dir) / folder).mkdir(parents=True, exist_ok=True)
    report = f"{folder}/{REPORT_NAME}"
    data = tract_report(tract, band, records)
    atomic_write_text(Path(out_dir) / report, json.dumps(data, indent=1) + "\n", overwrite=True)
    if not figure:
        return [report]
    from cellcoadd.plots.run_coverage import plot_tract_coverage

    items = [
        {
            "patch": [r.px, r.py],
            "state": r.state.value,
            "depth": None if r.summary is None else [list(d) for d in r.summary.depth],
        }
        for r in records
    ]
    path = f"{folder}/{FIGURE_NAME}"
    title = f"tract {tract.id}, band {band}: inputs used per cell"

    def draw(temporary: Path) -> None:
        plot_tract_coverage(tract, items, temporary, title=title)

    atomic_write(Path(out_dir) / path, draw, overwrite=True)
    return [report, path]


def write_reports(
    ledger: Ledger,
    plans: list[TractPlan],
    out_dir: Path,
    this_run: dict[str, Any],
    plan_failed: dict[int, str],
    bad_inputs: list[UnusableFile],
    *,
    figure: bool = True,
    client: Any = None,
) -> tuple[Path, list[Path]]:
    """Write each planned tract's report (and figure) and the run's ``report.json``
    (``this_run``: what this run did; the tracts whose planning failed; the unusable
    files that may touch the run): the run report's path and the figures' paths."""
    from cellcoadd.io._files.atomic import atomic_write_text

    records = ledger.records()
    by_tract: dict[tuple[str, int], list[PatchRecord]] = {}
    for record in records.values():
        by_tract.setdefault((record.band, record.tract), []).append(record)
    jobs = [(plan.tract, plan.band, by_tract.get((plan.band, plan.tract.id), [])) for plan in plans]
    if client is None or len(jobs) <= 1:
        written = [write_tract_outputs(str(out_dir), t, b, r, figure) for t, b, r in jobs]
    else:
        futures = [
            client.submit(write_tract_outputs, str(out_dir), t, b, r, figure, pure=False)
            for t, b, r in jobs
        ]
        written = client.gather(futures)
    figures = [out_dir / p for paths in written for p in paths if p.endswith(FIGURE_NAME)]
    bands: dict[str, list[PatchRecord]] = {}
    for record in records.values():
        bands.setdefault(record.band, []).append(record)
    data = {
        "library_version": __version__,
        "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "this_run": this_run,
        "totals": totals(records.values()),
        "bands": {band: totals(items) for band, items in sorted(bands.items())},
        "tracts": {
            f"{band}/{tract}": {
                "report": f"{band}/tract_{tract}/{REPORT_NAME}",
                **totals(items),
            }
            for (band, tract), items in sorted(by_tract.items())
        },
        "failures": [
            {"band": r.band, "tract": r.tract, "patch": [r.px, r.py], "error": r.error}
            for r in sorted(records.values(), key=lambda r: r.key)
            if r.state == PatchState.FAILED
        ],
        "plan_failures": [
            {"tract": tract, "error": why} for tract, why in sorted(plan_failed.items())
        ],
        "bad_inputs": [
            {"path": b.path, "status": b.status, "reason": b.reason, "band": b.band}
            for b in bad_inputs
        ],
    }
    report = out_dir / REPORT_NAME
    atomic_write_text(report, json.dumps(data, indent=1) + "\n", overwrite=True)
    return report, figures
