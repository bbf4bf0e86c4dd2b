"""``cellcoadd run``: every patch of a tract from an exposure index, on dask, resumable."""

from __future__ import annotations

import sys

import click

from cellcoadd.cli.options import load_skymap, parse_pair, quiet_option, skymap_option


@click.command("run")
@click.option(
    "--index", "index_path", required=True, type=click.Path(exists=True, dir_okay=False),
    help="Exposure index (.sqlite) written by `cellcoadd index`.",
)  # fmt: skip
@skymap_option
@click.option("--tract", "tract_id", type=int, required=True, help="Tract id.")
@click.option(
    "--patch", "patch_texts", multiple=True,
    help="Only patch PX,PY (repeatable; default: every patch an input may touch).",
)  # fmt: skip
@click.option("--out-dir", required=True, type=click.Path(file_okay=False), help="Output folder.")
@click.option(
    "--config", "config_path", type=click.Path(exists=True, dir_okay=False),
    help="BuildConfig fields in a .toml or .json file (see `cellcoadd config --show`).",
)  # fmt: skip
@click.option("--band", help="Band to build (needed when the tract has several).")
@click.option("--seed", type=int, default=0, show_default=True, help="Noise realization seed.")
@click.option(
    "--workers",
    type=int,
    default=1,
    show_default=True,
    help="Local dask worker processes (1: here).",
)
@click.option("--scheduler", help="dask.distributed scheduler address (instead of --workers).")
@click.option("--format", "fmt", type=click.Choice(["fits", "h5"]), default="fits")
@click.option("--retries", type=int, default=2, show_default=True, help="Retries per patch.")
@click.option("--verify", is_flag=True, help="Check SHA-256s of patches already built.")
@click.option("--no-figure", is_flag=True, help="Do not draw coverage.png.")
@quiet_option
def run_command(
    index_path: str,
    skymap_path: str | None,
    tract_id: int,
    patch_texts: tuple[str, ...],
    out_dir: str,
    config_path: str | None,
    band: str | None,
    seed: int,
    workers: int,
    scheduler: str | None,
    fmt: str,
    retries: int,
    verify: bool,
    no_figure: bool,
    quiet: bool,
) -> None:
    """Build the patches of a tract from an exposure index into --out-dir, on dask.

    Plans every patch of the tract that an input of the index may touch (or only the
    --patch ones), and builds each as one task: the worker reads the stored headers and
    the pixels itself and writes DIR/tract_T/patch_X_Y.fits (or .h5) atomically, the
    same bytes as `cellcoadd build` of that patch. A ledger in DIR records what each
    patch was built from: running the same command again builds only what is missing,
    failed or stale (changed config, seed or input files). Failing patches are retried,
    then recorded; the command then exits non-zero naming them. Writes DIR/report.json
    and DIR/coverage.png.

    \b
    Examples:
      cellcoadd index sim/visit*-det*.fits --db inputs.sqlite
      cellcoadd run --index inputs.sqlite --skymap sim/skymap.json --tract 0 --patch 0,0 \\
          --out-dir run --workers 2
      cellcoadd run --index inputs.sqlite --skymap sim/skymap.json --tract 0 --out-dir run-h5 \\
          --format h5 --scheduler tcp://127.0.0.1:8786
    """
    from cellcoadd.errors import TractRunError
    from cellcoadd.io.exposures.manifest_io import read_build_config
    from cellcoadd.model.build_config import BuildConfig
    from cellcoadd.pipelines.tract_run import run_tract

    if workers < 1:
        raise click.BadParameter("must be at least 1", param_hint="--workers")
    if scheduler is not None and workers != 1:
        raise click.UsageError("give --workers or --scheduler, not both")
    config = read_build_config(config_path) if config_path else BuildConfig()
    patches = [parse_pair(text) for text in patch_texts] or None
    result = run_tract(
        index_path,
        load_skymap(skymap_path),
        tract_id,
        out_dir,
        config=config,
        seed=seed,
        patches=patches,
        band=band,
        fmt=fmt,
        workers=workers,
        scheduler=scheduler,
        retries=retries,
        verify=verify,
        progress=not quiet,
        figure=not no_figure,
        command=" ".join(["cellcoadd", *sys.argv[1:]]),
    )
    click.echo(result.summary())
    click.echo(f"report: {result.report}")
    if result.failed:
        lines = [f"  patch {p[0]},{p[1]}: {why}" for p, why in sorted(result.failed.items())]
        raise TractRunError(f"{len(result.failed)} patches failed:\n" + "\n".join(lines))
