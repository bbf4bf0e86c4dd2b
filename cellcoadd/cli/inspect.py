"""``cellcoadd show`` (one cell's planes as a PNG) and ``cellcoadd trim`` (catalog flags)."""

from __future__ import annotations

import os
from pathlib import Path

import click
import numpy as np

from cellcoadd.cli.options import load_skymap, parse_pair


@click.command()
@click.argument("path", type=click.Path(exists=True, dir_okay=False))
@click.option("--cell", "cell_text", required=True, help="Cell index CX,CY (tract-global).")
@click.option("--out", type=click.Path(dir_okay=False), help="PNG (default cell_CX_CY.png).")
@click.option("--noise-index", type=int, default=0, show_default=True)
def show(path: str, cell_text: str, out: str | None, noise_index: int) -> None:
    """Draw one cell of a coadd file (image, noise, PSF, mask, mfrac) and list its inputs.

    \b
    Examples:
      cellcoadd show demo-output/coadd.h5 --cell 5,6
      cellcoadd show patch.fits --cell 41,17 --out cell.png --noise-index 2
    """
    from cellcoadd.io import api as coadd_io
    from cellcoadd.plots import plot_cell_planes

    index = parse_pair(cell_text)
    with coadd_io.open(path) as stored:
        if index not in stored.cell_indices:
            raise click.ClickException(
                f"{path} has no cell {index}; it holds cells {min(stored.cell_indices)} to "
                f"{max(stored.cell_indices)}"
            )
        cell = stored.read_cell(index)
        meta = stored.metadata
    if not 0 <= noise_index < max(cell.n_noise, 1):
        raise click.BadParameter(f"the cell has {cell.n_noise} noise realizations")
    out = out or f"cell_{index[0]}_{index[1]}.png"
    plot_cell_planes(
        cell,
        out,
        mask_bits=meta.mask_bits,
        noise_index=noise_index,
        units=meta.units,
        zero_point=meta.zero_point,
    )
    for line in input_lines(cell):
        click.echo(line)
    click.echo(f"wrote {out}")


def _number(value: float, spec: str, width: int, suffix: str = "") -> str:
    """``value`` formatted, or "-" (right-aligned in ``width``) when it does not exist."""
    text = f"{value:{spec}}{suffix}" if np.isfinite(value) else "-"
    return f"{text:>{width}}"


def input_lines(cell) -> list[str]:
    """One line per input record of ``cell``; values a rejected input lacks show as "-"."""
    lines = []
    for record in cell.inputs:
        weight = record.weight if record.weight > 0 else float("nan")  # 0: not weighed
        lines.append(
            f"visit {record.visit:5d} det {record.detector:3d}  {record.status:15s} "
            f"weight {_number(weight, '.4g', 10)}  "
            f"overlap {_number(record.overlap_fraction, '.2f', 5)}  "
            f"PSF FWHM {_number(record.psf_fwhm, '.3f', 6, chr(34))}"
        )
    return lines


@click.command()
@click.argument("catalog", type=click.Path(exists=True, dir_okay=False))
@click.option("--coadd", "coadd_path", required=True, type=click.Path(exists=True))
@click.option("--cell", "cell_text", help="Flag for this cell CX,CY (default: all its cells).")
@click.option(
    "--skymap",
    "skymap_path",
    type=click.Path(exists=True, dir_okay=False),
    help="Full sky map JSON (tract-inner flags need the other tracts' centres).",
)
@click.option("--out", type=click.Path(dir_okay=False), help="Output (default CATALOG_trim.fits)")
@click.option("--ra-col", default="ra", show_default=True)
@click.option("--dec-col", default="dec", show_default=True)
@click.option("--primary-only", is_flag=True, help="Keep only rows with is_primary.")
@click.option("--overwrite", is_flag=True)
def trim(
    catalog: str,
    coadd_path: str,
    cell_text: str | None,
    skymap_path: str | None,
    out: str | None,
    ra_col: str,
    dec_col: str,
    primary_only: bool,
    overwrite: bool,
) -> None:
    """Add is_cell_inner, is_patch_inner, is_tract_inner, is_primary to a catalog.

    The catalog (any format astropy reads: FITS, ECSV, CSV...) needs sky positions in
    deg. Half-open boundaries: an object on a cell boundary belongs to exactly one cell.
    Without --cell, is_primary marks the objects the coadd's patch owns.

    \b
    Examples:
      cellcoadd trim demo-output/truth.fits --coadd demo-output/coadd.h5
      cellcoadd trim cat.fits --coadd patch.fits --cell 12,40 --primary-only --out cell.fits
    """
    from astropy.table import Table

    from cellcoadd.geometry import SkyMap, flag_unique
    from cellcoadd.io import api as coadd_io
    from cellcoadd.io._files.atomic import atomic_write

    with coadd_io.open(coadd_path) as stored:
        meta = stored.metadata
        cells = list(stored.cell_indices)
    if skymap_path:
        the_map, tract_id = load_skymap(skymap_path), meta.tract
    else:  # one tract: tract-inner then means "inside the tract box"
        the_map, tract_id = SkyMap.from_centers([meta.tract_center], meta.skymap_config), 0
    table = Table.read(catalog)
    cell = parse_pair(cell_text) if cell_text else None
    flags = flag_unique(
        table, the_map, tract=tract_id, patch=meta.patch, cell=cell, ra=ra_col, dec=dec_col
    )
    where = the_map.locate(np.asarray(table[ra_col]), np.asarray(table[dec_col]))
    if cell is None:
        owned = {(int(x), int(y)) for x, y in cells}
        flags["is_cell_inner"] = flags["is_tract_inner"] & np.array(
            [
                (int(x), int(y)) in owned
                for x, y in zip(where["cell_x"], where["cell_y"], strict=True)
            ],
            dtype=bool,
        )
    table["cell_x"], table["cell_y"] = where["cell_x"], where["cell_y"]
    for name, values in flags.items():
        table[name] = values
    if primary_only:
        table = table[table["is_primary"]]
    out = out or str(Path(catalog).with_name(Path(catalog).stem + "_trim.fits"))

    def write(temporary: Path) -> None:
        # astropy picks the format (and compression, e.g. .fits.gz) from the end of the
        # name: write under a name ending like the output's, then take its place
        named = temporary.with_name(f"{temporary.name}-{Path(out).name}")
        try:
            table.write(named)
            os.replace(named, temporary)
        finally:
            named.unlink(missing_ok=True)

    atomic_write(out, write, overwrite=overwrite)
    click.echo(
        f"wrote {out}: {len(table)} rows, {int(np.sum(table['is_primary']))} primary "
        f"({int(np.sum(flags['is_patch_inner']))} in patch {meta.patch})"
    )
