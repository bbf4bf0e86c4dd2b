"""``cellcoadd run``: every band and tract of an exposure index, on dask, resumable."""

from __future__ import annotations

import sys

import click

from cellcoadd.cli.options import load_skymap, parse_pair, quiet_option, skymap_option


def _parse_region(
    ctx: click.Context, param: click.Parameter, text: str | None
) -> tuple[float, float, float, float] | None:
    if text is None:
        return None
    from cellcoadd.errors import ConfigError
    from cellcoadd.geometry.footprint import check_region

    expected = click.BadParameter(f"expected RA0,RA1,DEC0,DEC1 in degrees, got {text!r}")
    try:
        values = tuple(float(part) for part in text.split(","))
    except ValueError:
        raise expected from None
    if len(values) != 4:
        raise expected
    try:
        return check_region((values[0], values[1], values[2], values[3]))
    except ConfigError as err:
        raise click.BadParameter(str(err), param=param) from None


@click.command("run")
@click.option(
    "--index", "index_path", required=True, type=click.Path(exists=True, dir_okay=False),
    help="Exposure index (.sqlite) written by `cellcoadd index`.",
)  # fmt: skip
@skymap_option
@click.option("--out-dir", required=True, type=click.Path(file_okay=False), help="Output folder.")
@click.option(
    "--band", "bands", multiple=True,
    help="Only this band (repeatable; default: every band of the index).",
)  # fmt: skip
@click.option(
    "--tract", "tracts", type=click.IntRange(min=0), multiple=True,
    help="Only this tract (repeatable; default: every tract the inputs may touch).",
)  # fmt: skip
@click.option(
    "--region", callback=_parse_region,
    help="Only patches meeting this sky box: RA0,RA1,DEC0,DEC1 in degrees (RA0 > RA1 wraps "
    "through RA 0).",
)  # fmt: skip
@click.option(
    "--patch", "patch_texts", multiple=True,
    help="Only patch PX,PY of each tract (repeatable).",
)  # fmt: skip
@click.option(
    "--config", "config_path", type=click.Path(exists=True, dir_okay=False),
    help="BuildConfig fields in a .toml or .json file (see `cellcoadd config --show`).",
)  # fmt: skip
@click.option(
    "--seed", type=click.IntRange(min=0, max=2**63 - 1), default=0, show_default=True,
    help="Noise realization seed.",
)  # fmt: skip
@click.option(
    "--workers", type=click.IntRange(min=1), default=1, show_default=True,
    help="Local dask worker processes (1: here).",
)  # fmt: skip
@click.option("--scheduler", help="dask.distributed scheduler address (instead of --workers).")
@click.option("--format", "fmt", type=click.Choice(["fits", "h5"]), default="fits")
@click.option(
    "--retries", type=click.IntRange(min=0, max=100), default=2, show_default=True,
    help="Retries per patch (a changed or refused input is never retried).",
)  # fmt: skip
@click.option("--verify", is_flag=True, help="Check SHA-256s of patches already built.")
@click.option(
    "--trust-psf", is_flag=True,
    help="Load pickle-bearing PSF model files (Piff). Only for files you trust: the index "
    "never grants this.",
)  # fmt: skip
@click.option("--no-figure", is_flag=True, help="Do not draw the coverage figures.")
@quiet_option
def run_command(
    index_path: str,
    skymap_path: str | None,
    out_dir: str,
    bands: tuple[str, ...],
    tracts: tuple[int, ...],
    region: tuple[float, float, float, float] | None,
    patch_texts: tuple[str, ...],
    config_path: str | None,
    seed: int,
    workers: int,
    scheduler: str | None,
    fmt: str,
    retries: int,
    verify: bool,
    trust_psf: bool,
    no_figure: bool,
    quiet: bool,
) -> None:
    """Build every band and tract of an exposure index into --out-dir, on dask.

    Finds the tracts the index's inputs may touch (or takes --tract), plans each tract's
    patches per band (or only --band, --patch, --region), and builds each patch as one
    task: the worker reads the stored headers, checks them against the files, reads the
    pixels itself and writes DIR/BAND/tract_T/patch_X_Y.fits (or .h5) atomically, the
    same bytes as `cellcoadd build` of that patch. A ledger in DIR records what each
    patch was built from: running the same command again builds only what is missing,
    failed or stale (changed config, seed, index rows or input files). Failing patches
    are retried, then recorded; the command then exits non-zero naming them. Writes
    DIR/report.json (per band and tract, with the unusable files that may touch the run)
    and, per tract, DIR/BAND/tract_T/report.json and coverage.png.

    \b
    Examples:
      cellcoadd index sim/visit*-det*.fits --db inputs.sqlite
      cellcoadd run --index inputs.sqlite --skymap sim/skymap.json --out-dir run --workers 2
      cellcoadd run --index inputs.sqlite --skymap sim/skymap.json --out-dir run \\
          --band i --tract 0 --patch 0,0
      cellcoadd run --index inputs.sqlite --skymap sim/skymap.json --out-dir run-h5 \\
          --format h5 --scheduler tcp://127.0.0.1:8786
    """
    from cellcoadd.errors import TractRunError
    from cellcoadd.io.exposures.manifest_io import read_build_config
    from cellcoadd.model.build_config import BuildConfig
    from cellcoadd.pipelines.survey import run_survey

    if scheduler is not None and workers != 1:
        raise click.UsageError("give --workers or --scheduler, not both")
    config = read_build_config(config_path) if config_path else BuildConfig()
    patches = [parse_pair(text) for text in patch_texts] or None
    result = run_survey(
        index_path,
        load_skymap(skymap_path),
        out_dir,
        bands=list(bands) or None,
        tracts=list(tracts) or None,
        region=region,
        patches=patches,
        config=config,
        seed=seed,
        fmt=fmt,
        workers=workers,
        scheduler=scheduler,
        retries=retries,
        verify=verify,
        trust_psf=trust_psf,
        progress=not quiet,
        figure=not no_figure,
        command=" ".join(["cellcoadd", *sys.argv[1:]]),
    )
    for line in result.summary_lines():
        click.echo(line, err=line.startswith("warning"))
    if result.bad_inputs:
        click.echo(
            f"warning: {len(result.bad_inputs)} input files the index marks bad or vanished "
            "may touch this run (listed in report.json under bad_inputs):"
        )
        for item in result.bad_inputs[:10]:
            click.echo(f"  {item.path}: {item.reason}")
        if len(result.bad_inputs) > 10:
            click.echo(f"  ... and {len(result.bad_inputs) - 10} more")
    click.echo(f"report: {result.report}")
    if not result.ok:
        items = [f"{key}: {why}" for key, why in sorted(result.failed.items())]
        items += [f"tract {t} (planning): {why}" for t, why in sorted(result.plan_failed.items())]
        what = [
            _count(len(result.failed), "patch", "patches"),
            _count(len(result.plan_failed), "tract", "tracts"),
        ]
        raise TractRunError(
            " and ".join(w for w in what if w) + " failed (listed in report.json): "
            + "; ".join(items)
        )  # fmt: skip


def _count(n: int, one: str, many: str) -> str:
    """``"1 patch"``, ``"3 patches"``; ``""`` for none."""
    return "" if n == 0 else f"{n} {one if n == 1 else many}"
