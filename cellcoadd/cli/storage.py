"""Command-line tools for stored coadds: ``info``, ``convert`` and ``schemas``."""

from __future__ import annotations

import json
import os
import statistics
from collections import Counter
from typing import Any

import click

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.io import api
from cellcoadd.model import planes as cell_planes
from cellcoadd.model.inputs import REJECTION_REASONS
from cellcoadd.model.patch_coadd import PatchMetadata
from cellcoadd.model.schemas import schema_documents

_ERRORS = (CellCoaddFormatError, OSError, ValueError)


def patch_summary(
    path: str, legacy_zero_point: float | None = None, skymap: str | None = None
) -> dict[str, Any]:
    """Summary of a patch file without reading pixel data (used by ``cellcoadd info``).

    ``legacy_zero_point``: for an lsst.cell_coadds file in ``legacy`` units that does not
    record its zero point; ``skymap``: the name of the sky map of an lsst.cell_coadds file
    whose ``SKYMAP`` cellcoadd does not know (see :func:`cellcoadd.io.api.open`).

    Keys: file, format, format_version, size_bytes, software_version, tract, patch, band,
    units, zero_point (AB mag of the pixel values), n_noise, psf_size, planes, cells
    (counts), inputs (totals by status), per_cell (one entry per cell: index, kind, used,
    rejected by reason).
    """
    with api.open(path, legacy_zero_point=legacy_zero_point, skymap=skymap) as coadd_file:
        meta = coadd_file.metadata
        table = coadd_file.read_inputs()
        layout = coadd_file.format_name
        layout_version = getattr(coadd_file, "layout_version", None)  # foreign layouts
        indices = list(coadd_file.cell_indices)
    inner = set(meta.inner_cell_indices)
    statuses: dict[tuple[int, int], Counter[str]] = {index: Counter() for index in indices}
    for cx, cy, status in zip(table["cell_x"], table["cell_y"], table["status"], strict=True):
        statuses[(int(cx), int(cy))][str(status)] += 1
    per_cell: list[dict[str, Any]] = []
    for index in indices:
        counts = statuses[index]
        per_cell.append(
            {
                "index": list(index),
                "kind": "inner" if index in inner else "border",
                "used": counts["used"],
                "rejected": {r: counts[r] for r in REJECTION_REASONS if counts[r]},
            }
        )
    used = [entry["used"] for entry in per_cell]
    totals = Counter(str(status) for status in table["status"])
    summary: dict[str, Any] = {
        "file": os.fspath(path),
        "format": layout,
        "format_version": meta.format_version,
        "size_bytes": os.path.getsize(path),
        "software_version": meta.software_version,
        "tract": meta.tract,
        "patch": list(meta.patch),
        "band": meta.band,
        "units": meta.units,
        "zero_point": meta.zero_point,
        "n_noise": meta.n_noise,
        "psf_size": meta.psf_size,
        "planes": stored_planes(meta),
        "cells": {
            "total": len(indices),
            "inner": sum(index in inner for index in indices),
            "border": sum(index not in inner for index in indices),
            "empty": sum(n == 0 for n in used),
            "missing_inner": len(inner - set(indices)),
        },
        "inputs": {
            "total": len(table),
            "used": totals["used"],
            "rejected": {r: totals[r] for r in REJECTION_REASONS if totals[r]},
            "used_per_cell": {
                "min": min(used, default=0),
                "median": statistics.median(used) if used else 0,
                "max": max(used, default=0),
            },
        },
        "per_cell": per_cell,
    }
    if layout_version is not None:  # e.g. the VERSION of an lsst.cell_coadds file
        summary["layout_version"] = layout_version
    return summary


def stored_planes(meta: PatchMetadata) -> list[str]:
    """What each cell of a patch file stores, for ``cellcoadd info``: the planes of
    :data:`~cellcoadd.model.planes.PLANES` (with their number of realizations or stamp size;
    per-realization planes left out when there are none, optional ones when the build
    configuration did not ask for them), then the inputs table."""
    described = []
    optional = {
        name: bool(getattr(meta.build_config, flag))
        for name, flag in cell_planes.optional_plane_flags().items()
    }
    for spec in cell_planes.PLANES:
        if spec.optional and not optional.get(spec.name, False):
            continue
        if spec.per_input:
            side = "x".join(str(n) for n in spec.per_input)
            described.append(f"{spec.name} (per used input, {side})")
        elif spec.layers:
            described.append(f"{spec.name} ({spec.layers}x{meta.psf_size}x{meta.psf_size})")
        elif spec.per_realization:
            if meta.n_noise:
                described.append(f"{spec.name} ({meta.n_noise} realizations)")
        elif spec.stamp:
            described.append(f"{spec.name} ({meta.psf_size}x{meta.psf_size})")
        else:
            described.append(spec.name)
    return [*described, cell_planes.INPUTS]


def _format_size(n_bytes: int) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n_bytes >= scale:
            return f"{n_bytes / scale:.1f} {unit}"
    return f"{n_bytes} B"


def _reasons(rejected: dict[str, int]) -> str:
    return ", ".join(f"{reason} {n}" for reason, n in rejected.items()) or "none"


def _summary_text(summary: dict[str, Any], per_cell: bool) -> str:
    cells, inputs = summary["cells"], summary["inputs"]
    per = inputs["used_per_cell"]
    lines = [
        f"file      {summary['file']} ({summary['format'].upper()}, "
        f"{_format_size(summary['size_bytes'])}, format "
        f"{summary.get('layout_version', summary['format_version'])}, "
        f"cellcoadd {summary['software_version']})",
        f"patch     tract {summary['tract']}, patch ({summary['patch'][0]}, "
        f"{summary['patch'][1]}), band {summary['band']}, units {summary['units']}"
        + (f" (AB zero point {summary['zero_point']:g})" if summary["units"] == "count" else ""),
        f"cells     {cells['total']} ({cells['inner']} inner + {cells['border']} border), "
        f"{cells['empty']} empty, {cells['missing_inner']} inner missing",
        f"planes    {', '.join(summary['planes'])}",
        f"inputs    {inputs['total']} records: {inputs['used']} used, rejected: "
        f"{_reasons(inputs['rejected'])}",
        f"per cell  used inputs min {per['min']}, median {per['median']}, max {per['max']}",
    ]
    if per_cell:
        lines.append("cell          kind    used  rejected")
        for entry in summary["per_cell"]:
            cx, cy = entry["index"]
            lines.append(
                f"({cx:>4}, {cy:>4})  {entry['kind']:<6} {entry['used']:>5}  "
                f"{_reasons(entry['rejected'])}"
            )
    return "\n".join(lines)


_legacy_zero_point_option = click.option(
    "--legacy-zero-point",
    type=float,
    default=None,
    help="AB zero point of an lsst.cell_coadds file in 'legacy' units (counts) that does "
    "not record one (Rubin's are usually 27); refused when the file records another.",
)

_skymap_name_option = click.option(
    "--skymap",
    "skymap_name",
    default=None,
    metavar="NAME",
    help="Sky map of an lsst.cell_coadds file whose SKYMAP keyword cellcoadd does not know "
    "(lsst_cells_v1, lsst_cells_v2, DC2_cells_v1, lsst); checked against the file's grid "
    "and WCS.",
)


@click.command("info")
@click.argument("path", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@click.option("--cells", "per_cell", is_flag=True, help="Also list every cell's inputs.")
@_legacy_zero_point_option
@_skymap_name_option
def info_command(
    path: str,
    as_json: bool,
    per_cell: bool,
    legacy_zero_point: float | None,
    skymap_name: str | None,
) -> None:
    """Summarise a stored patch coadd (no pixel data is read).

    \b
    Examples:
      cellcoadd info patch.fits
      cellcoadd info patch.h5 --cells
      cellcoadd info patch.h5 --json > summary.json
    """
    try:
        summary = patch_summary(path, legacy_zero_point, skymap_name)
    except _ERRORS as err:
        raise click.ClickException(str(err)) from err
    if as_json:
        click.echo(json.dumps(summary, indent=2, ensure_ascii=False))
    else:
        click.echo(_summary_text(summary, per_cell))


@click.command("convert")
@click.argument("source", type=click.Path(dir_okay=False))
@click.argument("destination", type=click.Path(dir_okay=False))
@click.option(
    "--compression",
    type=click.Choice(["none", "lossless"]),
    default=None,
    help="Lossless compression (default: only for .fits.fz names).",
)
@click.option("--overwrite", is_flag=True, help="Replace DESTINATION if it exists.")
@click.option(
    "--layout",
    type=click.Choice(["cell_coadds"]),
    default=None,
    help="Write the LSST lsst.cell_coadds FITS layout (a .fits DESTINATION).",
)
@_legacy_zero_point_option
@_skymap_name_option
def convert_command(
    source: str,
    destination: str,
    compression: api.Compression | None,
    overwrite: bool,
    layout: api.Layout | None,
    legacy_zero_point: float | None,
    skymap_name: str | None,
) -> None:
    """Copy a patch coadd into another layout (chosen by the file name), bit for bit.

    An lsst.cell_coadds SOURCE is recognised by its headers; --layout cell_coadds writes
    that layout.

    \b
    Examples:
      cellcoadd convert patch.fits patch.h5
      cellcoadd convert patch.h5 patch.fits.fz
      cellcoadd convert patch.fits small.h5 --compression lossless --overwrite
      cellcoadd convert patch.h5 lsst_cells.fits --layout cell_coadds
      cellcoadd convert lsst_cells.fits from_lsst.h5
    """
    try:
        written = api.convert(
            source,
            destination,
            compression=compression,
            overwrite=overwrite,
            layout=layout,
            legacy_zero_point=legacy_zero_point,
            skymap=skymap_name,
        )
    except FileExistsError as err:
        raise click.ClickException(f"{destination} exists; use --overwrite to replace it") from err
    except _ERRORS as err:
        raise click.ClickException(str(err)) from err
    click.echo(f"wrote {written} ({_format_size(os.path.getsize(written))})")


@click.command("schemas")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    default="schemas",
    show_default=True,
    help="Directory to write the JSON Schema files into.",
)
def schemas_command(out_dir: str) -> None:
    """Write the JSON Schemas of the metadata models (<Model>.v<MAJOR>.json).

    \b
    Examples:
      cellcoadd schemas --out schemas/
      cellcoadd schemas --out /tmp/schemas && diff -r /tmp/schemas schemas
    """
    from pathlib import Path

    from cellcoadd.io._files.atomic import atomic_write_text

    try:  # atomically, replacing a link in the folder, never writing through it
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        written = [
            atomic_write_text(Path(out_dir) / name, text, overwrite=True)
            for name, text in schema_documents().items()
        ]
    except (OSError, CellCoaddFormatError) as err:
        raise click.ClickException(str(err)) from err
    for path in written:
        click.echo(str(path))
