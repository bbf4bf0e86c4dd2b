"""``cellcoadd demo``: the end-to-end demonstration (what ``make demo`` runs)."""

from __future__ import annotations

import os

import click

from cellcoadd.cli.options import quiet_option


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
@quiet_option
def demo(out_dir: str, visits: int, seed: int, workers: int, quiet: bool) -> None:
    """Simulate a small field, build, store, check and plot its cell coadds.

    Writes the simulated exposures, the coadd as FITS and HDF5, the trimmed truth
    catalog, a report and PNG figures into --out, and prints the report.

    \b
    Examples:
      cellcoadd demo
      cellcoadd demo --out /tmp/demo --visits 20 --seed 7
    """
    from cellcoadd.pipelines.demo import run_demo

    result = run_demo(out_dir, n_visits=visits, seed=seed, workers=workers, progress=not quiet)
    click.echo(result.report)
    click.echo(f"everything is in {result.out_dir}/")
