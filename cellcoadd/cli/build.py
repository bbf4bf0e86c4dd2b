"""``cellcoadd build``: exposure files (listed, or in a manifest) -> one patch coadd file."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

import click

from cellcoadd.cli.options import (
    check_output_not_an_input,
    check_output_path,
    load_skymap,
    parse_pair,
    quiet_option,
    skymap_option,
)


@click.command()
@click.argument("exposure_files", nargs=-1, type=click.Path(exists=True, dir_okay=False))
@click.option(
    "--manifest",
    type=click.Path(exists=True, dir_okay=False),
    help="Inputs listed in a .toml, .json or .csv file (path, layout, psf, background...).",
)
@click.option(
    "--config",
    "config_path",
    type=click.Path(exists=True, dir_okay=False),
    help="BuildConfig fields in a .toml or .json file (see `cellcoadd config --show`).",
)
@skymap_option
@click.option("--tract", "tract_id", type=int, required=True, help="Tract id.")
@click.option("--patch", "patch_text", required=True, help="Patch index PX,PY.")
@click.option("--out", required=True, type=click.Path(dir_okay=False), help=".fits or .h5 file")
@click.option("--workers", type=int, default=1, show_default=True, help="Local processes.")
@click.option("--scheduler", help="dask.distributed scheduler address (runs cells there).")
@click.option("--seed", type=int, default=0, show_default=True, help="Noise realization seed.")
@click.option("--n-noise", type=int, help="Noise realizations K (overrides --config).")
@click.option("--psf-size", type=int, help="PSF stamp side, px (overrides --config).")
@click.option(
    "--psf-corners/--no-psf-corners",
    default=None,
    help="Also the coadd PSF at each cell's inner corners, for cell.psf_at (overrides "
    "--config; costs ~20-30% more).",
)
@click.option(
    "--psf-phase/--no-psf-phase",
    default=None,
    help="Also each input's resampling phase term, so cell.psf_at gives a star's PSF at "
    "any pixel (overrides --config; ~5% more; with --psf-corners matches stars to ~1e-4).",
)
@click.option("--compression", type=click.Choice(["none", "lossless"]), default="none")
@click.option("--overwrite", is_flag=True, help="Replace an existing output file.")
@quiet_option
def build(
    exposure_files: tuple[str, ...],
    manifest: str | None,
    config_path: str | None,
    skymap_path: str | None,
    tract_id: int,
    patch_text: str,
    out: str,
    workers: int,
    scheduler: str | None,
    seed: int,
    n_noise: int | None,
    psf_size: int | None,
    psf_corners: bool | None,
    psf_phase: bool | None,
    compression: str,
    overwrite: bool,
    quiet: bool,
) -> None:
    """Coadd exposure files into the cells of one patch and write them to --out.

    Inputs are cellcoadd exposure files given as EXPOSURE_FILES, and/or survey files
    (LSST, DES, other multi-extension layouts) listed in a --manifest with their PSF
    model files. Everything that can be checked is checked before the build: the output
    path, every input's headers, the mask bits the configuration needs. Pixels are read
    by the workers, one exposure cut to one block of cells at a time.

    \b
    Examples:
      cellcoadd build sim/visit*-det*.fits --skymap sim/skymap.json --tract 0 --patch 0,0 \\
          --out patch.fits --workers 2
      cellcoadd build --manifest des.toml --config des_build.toml --skymap skymap.json \\
          --tract 0 --patch 1,2 --out patch.h5 --scheduler tcp://127.0.0.1:8786
    """
    from tqdm.auto import tqdm

    from cellcoadd.builder import stream_patch
    from cellcoadd.io.api import write_cells
    from cellcoadd.io.exposures.exposure_source import ExposureFile
    from cellcoadd.io.exposures.manifest_io import (
        read_build_config,
        read_manifest,
        sources_from_manifest,
    )
    from cellcoadd.model.build_config import BuildConfig
    from cellcoadd.model.sources import describe
    from cellcoadd.pipelines.coverage import count_cell_inputs, counts_warning

    if not exposure_files and manifest is None:
        raise click.UsageError("give EXPOSURE_FILES or --manifest")
    check_output_path(out, overwrite)
    config = read_build_config(config_path) if config_path else BuildConfig()
    given_settings = (
        ("n_noise", n_noise),
        ("psf_size", psf_size),
        ("psf_corners", psf_corners),
        ("psf_phase", psf_phase),
    )
    overrides = {k: v for k, v in given_settings if v is not None}
    if overrides:
        config = BuildConfig.model_validate({**config.model_dump(), **overrides})
    the_map = load_skymap(skymap_path)
    patch = the_map[tract_id].patch(*parse_pair(patch_text))
    start = time.perf_counter()
    sources: list[Any] = [ExposureFile(path) for path in exposure_files]
    if manifest is not None:
        sources += sources_from_manifest(read_manifest(manifest), Path(manifest).parent)
    given = [manifest, config_path, skymap_path, *(_source_files(s) for s in sources)]
    check_output_not_an_input(out, [p for group in given for p in _as_list(group)])
    # headers read once, now: a missing HDU or keyword is found before the build
    inputs = [describe(s) for s in tqdm(sources, desc="headers", unit="file", disable=quiet)]
    # each block of cells written as it is built, then let go: the patch is never held whole
    stream = stream_patch(
        patch, inputs, config, seed, progress=not quiet, workers=workers, scheduler=scheduler
    )
    kept: list[_CellInputs] = []  # what the summary needs of each cell

    def cells() -> Iterator[Any]:
        for cell in stream:
            kept.append(_CellInputs(cell.inputs, cell.is_empty))
            yield cell

    with stream:
        write_cells(
            stream.metadata,
            cells(),
            out,
            compression=None if compression == "none" else "lossless",
            overwrite=overwrite,
        )
    counts = count_cell_inputs(kept)
    click.echo(
        f"wrote {out}: {counts.n_cells} cells ({counts.n_empty} empty), "
        f"{counts.records['used']} input records used, {time.perf_counter() - start:.1f} s"
    )
    warning = counts_warning(counts, stream.metadata.skymap_config)
    if warning:
        click.echo(warning, err=True)


class _CellInputs(NamedTuple):
    inputs: list[Any]
    is_empty: bool


def _as_list(group: Any) -> list[str]:
    if group is None:
        return []
    return [group] if isinstance(group, str) else list(group)


def _source_files(source: Any) -> list[str]:
    """The files an exposure source reads: image, background, PSF model file."""
    files = [getattr(source, "path", None), getattr(source, "background", None)]
    files.append(getattr(getattr(source, "psf", None), "source", None))
    return [str(f) for f in files if f is not None]
