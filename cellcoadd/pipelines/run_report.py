"""The report of a tract run: ``DIR/report.json`` and the coverage figure ``DIR/coverage.png``.

The report covers every patch of the tract the ledger knows (built by this run or an
earlier one): its state, cells, empty cells, inputs given, used, and the cell input
records rejected by reason, CPU and wall time, peak memory of its worker, attempts and
the error of a failed patch; then totals, and what this run did.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from cellcoadd._version import __version__
from cellcoadd.geometry.tract import Tract
from cellcoadd.pipelines.ledger import Ledger

REPORT_NAME = "report.json"
FIGURE_NAME = "coverage.png"

_PATCH_FIELDS = (
    "cells",
    "inner_cells",
    "empty_cells",
    "empty_inner_cells",
    "inputs",
    "inputs_used",
    "rejected_records",
    "cpu_s",
    "wall_s",
    "peak_rss_mb",
    "worker",
    "parts",
    "parts_cpu_s",
)


def report_data(ledger: Ledger, tract: Tract, this_run: dict[str, Any]) -> dict[str, Any]:
    """The content of ``report.json`` (JSON-able); ``this_run`` says what the run that
    writes it did (:meth:`cellcoadd.pipelines.tract_run.RunResult.as_report`)."""
    rows = sorted(ledger.rows(tract.id).values(), key=lambda r: (r.patch[1], r.patch[0]))
    patches = []
    totals: dict[str, Any] = {
        "patches": len(rows),
        "done": 0,
        "failed": 0,
        "no_inputs": 0,
        "pending": 0,
        "cells": 0,
        "empty_cells": 0,
        "inner_cells": 0,
        "empty_inner_cells": 0,
        "input_records_used": 0,
        "rejected_records": {},
        "cpu_s": 0.0,
        "wall_s": 0.0,
        "retries": 0,
    }
    for row in rows:
        summary = row.summary or {}
        entry: dict[str, Any] = {
            "patch": list(row.patch),
            "state": row.state,
            "output": row.output if row.state == "done" else None,
            "checksum": row.checksum,
            "attempts": row.attempts,
            "retries": max(row.attempts - 1, 0),
            "error": row.error,
            "inputs_indexed": len({f[0] for f in row.inputs}),
        }
        entry.update({name: summary.get(name) for name in _PATCH_FIELDS if name in summary})
        patches.append(entry)
        totals[row.state] = totals.get(row.state, 0) + 1
        totals["retries"] += entry["retries"]
        for name in ("cells", "empty_cells", "inner_cells", "empty_inner_cells"):
            totals[name] += int(summary.get(name, 0))
        for name in ("cpu_s", "wall_s"):
            totals[name] = round(totals[name] + float(summary.get(name, 0.0)), 4)
        totals["input_records_used"] += sum(int(n) for _, _, n in summary.get("depth", []))
        for reason, count in (summary.get("rejected_records") or {}).items():
            totals["rejected_records"][reason] = totals["rejected_records"].get(reason, 0) + count
    return {
        "tract": tract.id,
        "band": rows[0].band if rows else None,
        "library_version": __version__,
        "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "this_run": this_run,
        "totals": totals,
        "failures": [
            {"patch": p["patch"], "error": p["error"]} for p in patches if p["state"] == "failed"
        ],
        "patches": patches,
    }


def write_report(
    ledger: Ledger, tract: Tract, out_dir: Path, this_run: dict[str, Any], *, figure: bool = True
) -> tuple[Path, Path | None]:
    """Write ``report.json`` (and ``coverage.png``) in ``out_dir``; their paths."""
    from cellcoadd.io._files.atomic import atomic_write, atomic_write_text

    data = report_data(ledger, tract, this_run)
    report = out_dir / REPORT_NAME
    atomic_write_text(report, json.dumps(data, indent=1) + "\n", overwrite=True)
    if not figure:
        return report, None
    from cellcoadd.plots.run_coverage import plot_tract_coverage

    rows = ledger.rows(tract.id).values()
    items = [
        {"patch": list(r.patch), "state": r.state, "depth": (r.summary or {}).get("depth")}
        for r in rows
    ]
    path = out_dir / FIGURE_NAME
    band = data["band"]
    title = f"tract {tract.id}{f', band {band}' if band else ''}: inputs used per cell"

    def draw(temporary: Path) -> None:
        plot_tract_coverage(tract, items, temporary, title=title)

    atomic_write(path, draw, overwrite=True)
    return report, path
