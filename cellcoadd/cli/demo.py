"""``cellcoadd demo``: the end-to-end demonstration (what ``make demo`` runs)."""

from __future__ import annotations

import os

import click

from cellcoadd.cli.options import check_output_path, quiet_option

#: The coadd files the demo writes into its folder.
DEMO_COADDS = ("coadd.fits", "coadd.h5")


@click.command()
@click.option(
    "--out",
    "out_dir",
    default="demo-output",
    show_default=True,
    type=click.Path(file_okay=False),
    help="Folder for every file the demo writes.",
)
@click.option("--visits", type=click.IntRange(1, 100), default=10, show_default=True)
@click.option("--seed", type=click.IntRange(0), default=42, show_default=True)
@click.option(
    "--workers",
    type=click.IntRange(1),
    default=min(2, os.cpu_count() or 1),
    show_default="min(2, CPUs)",
    help="Processes for building the patch.",
)
@click.option("--overwrite", is_flag=True, help="Replace the files of an earlier run in --out.")
@click.option(
    "--keep-exposures",
    is_flag=True,
    help="Also write the simulated exposure files (~4 MB each) into --out/exposures/.",
)
@quiet_option
def demo(
    out_dir: str,
    visits: int,
    seed: int,
    workers: int,
    overwrite: bool,
    keep_exposures: bool,
    quiet: bool,
) -> None:
    """Simulate a small field, build, store, check and plot its cell coadds.

    Writes the coadd as FITS and HDF5, the truth catalog and its trimmed copy, the sky
    map, a report and PNG figures into --out (about 130 MB for 10 visits), and prints
    the report. The simulated exposures stay in memory unless --keep-exposures is
    given. The first run compiles the builder's numba kernels (once, cached on disk).

    \b
    Examples:
      cellcoadd demo
      cellcoadd demo --out /tmp/demo --visits 20 --seed 7 --overwrite
    """
    from cellcoadd.pipelines.demo import run_demo

    # before any work: names the coadd writers would refuse, an earlier run's files
    for name in DEMO_COADDS:
        check_output_path(os.path.join(out_dir, name), True, directory_may_be_created=True)
    if os.path.isdir(out_dir) and any(os.scandir(out_dir)) and not overwrite:
        raise click.ClickException(
            f"{out_dir} exists and is not empty; pass --overwrite to replace its files"
        )

    result = run_demo(
        out_dir,
        n_visits=visits,
        seed=seed,
        workers=workers,
        progress=not quiet,
        keep_exposures=keep_exposures,
        log=None if quiet else lambda line: click.echo(line, err=True),
    )
    click.echo(result.report)
    click.echo(f"everything is in {result.out_dir}/")
