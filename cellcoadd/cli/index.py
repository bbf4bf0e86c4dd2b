"""``cellcoadd index``: exposure files -> the exposure index a tract run queries."""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import click

from cellcoadd.cli.options import quiet_option
from cellcoadd.geometry.footprint import MAX_NSIDE


@click.command("index")
@click.argument("exposure_files", nargs=-1, type=click.Path(dir_okay=False))
@click.option(
    "--manifest",
    "manifests",
    multiple=True,
    type=click.Path(exists=True, dir_okay=False),
    help="Inputs listed in a .toml, .json or .csv manifest (repeatable).",
)
@click.option("--db", required=True, type=click.Path(dir_okay=False), help="Index .sqlite file.")
@click.option("--checksum", is_flag=True, help="Also compare SHA-256s (reads every byte).")
@click.option("--workers", type=int, default=1, show_default=True, help="Processes reading.")
@click.option(
    "--nside",
    type=click.IntRange(1, MAX_NSIDE),
    default=None,
    help=f"HEALPix nside of a new index, a power of 2 up to {MAX_NSIDE} [512].",
)
@click.option(
    "--allow-bad", is_flag=True, help="Exit 0 even when files are bad (they are still listed)."
)
@click.option("--stats", is_flag=True, help="Summarise the index (files, bands, visits, area).")
@click.option("--json", "as_json", is_flag=True, help="--stats as JSON.")
@quiet_option
def index_command(
    exposure_files: tuple[str, ...],
    manifests: tuple[str, ...],
    db: str,
    checksum: bool,
    workers: int,
    nside: int | None,
    stats: bool,
    as_json: bool,
    allow_bad: bool,
    quiet: bool,
) -> None:
    """Index input files: read their headers once into SQLite, for `cellcoadd run`.

    Each input's identity, band, zero point, exact WCS, valid box, sky footprint (with
    HEALPix pixels for the queries), PSF model file and the size and mtime of its files
    go into one SQLite row. Running it again adds new files, re-reads changed ones and
    reports files that vanished. Files that cannot be read are stored with the reason
    and listed, one line each on stderr (also with -q); the command then exits with
    status 1 unless --allow-bad is given. Two files of the same (visit, detector) are
    refused: the second is bad. Survey files (LSST, DES, other layouts) come with their
    PSF model files in a --manifest. `cellcoadd run --index` builds patches from it.

    \b
    Examples:
      cellcoadd index sim/visit*-det*.fits --db inputs.sqlite --workers 2
      cellcoadd index sim/visit*-det*.fits --db inputs.sqlite --checksum
      cellcoadd index --db inputs.sqlite --stats
    """
    from tqdm.auto import tqdm

    from cellcoadd.geometry.footprint import check_nside
    from cellcoadd.io.exposures.index import DEFAULT_NSIDE, ExposureIndex, absolute_entry
    from cellcoadd.io.exposures.manifest_io import read_manifest
    from cellcoadd.model.manifest import ManifestEntry

    entries = [absolute_entry(ManifestEntry(path=p), ".") for p in exposure_files]
    for manifest in manifests:
        base = Path(manifest).parent
        entries += [absolute_entry(e, base) for e in read_manifest(manifest).exposures]
    if not entries and not stats:
        raise click.UsageError("give EXPOSURE_FILES, --manifest or --stats")
    if not entries and not Path(db).is_file():
        raise click.ClickException(f"{db}: no such exposure index")
    if nside is not None:
        check_nside(nside)  # a power of 2, before any file is touched
    bad = 0
    with ExposureIndex(db, nside=nside or DEFAULT_NSIDE) as index:
        if nside is not None and nside != index.nside:
            raise click.ClickException(f"{db} has nside {index.nside}, not {nside}")
        if entries:

            def bar(items: Iterable[Any], total: int) -> Iterable[Any]:
                return tqdm(items, total=total, desc="headers", unit="file", disable=quiet)

            update = index.update(entries, checksum=checksum, workers=workers, progress=bar)
            click.echo(f"{db}: {update.summary()}")
            for path, reason in update.bad:
                click.echo(f"bad: {path}: {reason}", err=True)
            bad = len(update.bad)
            for path in update.vanished:
                click.echo(f"vanished: {path}", err=True)
        if stats:
            summary = index.stats()
            if as_json:
                click.echo(json.dumps(summary, indent=2))
            else:
                click.echo(_stats_text(summary))
                for path, reason in index.bad_files():
                    click.echo(f"  not usable: {path}: {reason}")
    if bad and not allow_bad:
        raise click.ClickException(
            f"{bad} file{'s are' if bad > 1 else ' is'} bad (listed above; --allow-bad to exit 0)"
        )


def _stats_text(summary: dict) -> str:
    lines = [
        f"{summary['path']}: {summary['files']} files ({summary['ok']} usable, "
        f"{summary['bad']} bad, {summary['vanished']} vanished), {summary['visits']} visits, "
        f"HEALPix nside {summary['nside']}",
        f"  area: {summary['footprint_area_deg2']:.4f} deg^2 of footprints, "
        f"{summary['covered_area_deg2']:.4f} deg^2 covered (HEALPix pixels touched)",
    ]
    for band, row in summary["bands"].items():
        lines.append(
            f"  band {band}: {row['files']} files, {row['visits']} visits, "
            f"{row['area_deg2']:.4f} deg^2"
        )
    return "\n".join(lines)
