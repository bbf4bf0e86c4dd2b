"""``cellcoadd build``: exposure files -> one patch coadd file."""

from __future__ import annotations

import os
import time

import click

from cellcoadd.cli.options import load_skymap, parse_pair, quiet_option, skymap_option


@click.command()
@click.argument("exposure_files", nargs=-1, required=True, type=click.Path(exists=True))
@skymap_option
@click.option("--tract", "tract_id", type=int, required=True, help="Tract id.")
@click.option("--patch", "patch_text", required=True, help="Patch index PX,PY.")
@click.option("--out", required=True, type=click.Path(dir_okay=False), help=".fits or .h5 file")
@click.option("--workers", type=int, default=1, show_default=True, help="Local processes.")
@click.option("--scheduler", help="dask.distributed scheduler address (runs cells there).")
@click.option("--seed", type=int, default=0, show_default=True, help="Noise realization seed.")
@click.option("--n-noise", type=int, default=3, show_default=True, help="Noise realizations K.")
@click.option("--psf-size", type=int, default=35, show_default=True, help="PSF stamp side, px.")
@click.option("--compression", type=click.Choice(["none", "lossless"]), default="none")
@click.option("--overwrite", is_flag=True, help="Replace an existing output file.")
@quiet_option
def build(
    exposure_files: tuple[str, ...],
    skymap_path: str | None,
    tract_id: int,
    patch_text: str,
    out: str,
    workers: int,
    scheduler: str | None,
    seed: int,
    n_noise: int,
    psf_size: int,
    compression: str,
    overwrite: bool,
    quiet: bool,
) -> None:
    """Coadd EXPOSURE_FILES into the cells of one patch and write them to --out.

    \b
    Examples:
      cellcoadd build sim/visit*.fits --skymap sim/skymap.json --tract 0 --patch 0,0 \\
          --out patch.fits --workers 2
      cellcoadd build exp/*.fits --skymap skymap.json --tract 0 --patch 1,2 \\
          --out patch.h5 --scheduler tcp://127.0.0.1:8786
    """
    from tqdm.auto import tqdm

    from cellcoadd.builder import build_patch
    from cellcoadd.io.api import write
    from cellcoadd.io.exposure_io import read_exposure
    from cellcoadd.model.build_config import BuildConfig

    if os.path.exists(out) and not overwrite:  # fail before the work, not after
        raise click.ClickException(f"{out} exists; pass --overwrite to replace it")
    config = BuildConfig(n_noise=n_noise, psf_size=psf_size)
    the_map = load_skymap(skymap_path)
    patch = the_map[tract_id].patch(*parse_pair(patch_text))
    start = time.perf_counter()
    exposures = [
        read_exposure(path)
        for path in tqdm(exposure_files, desc="reading exposures", unit="file", disable=quiet)
    ]
    coadd = build_patch(
        patch, exposures, config, seed, progress=not quiet, workers=workers, scheduler=scheduler
    )
    write(
        coadd, out, compression=None if compression == "none" else compression, overwrite=overwrite
    )
    used = sum(r.status == "used" for c in coadd.cells.values() for r in c.inputs)
    empty = sum(c.is_empty for c in coadd.cells.values())
    click.echo(
        f"wrote {out}: {len(coadd.cells)} cells ({empty} empty), {used} cell inputs used, "
        f"{time.perf_counter() - start:.1f} s"
    )
