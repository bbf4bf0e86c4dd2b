"""``cellcoadd init``: a commented manifest and build configuration for a directory of
survey exposure files."""

from __future__ import annotations

import os
from pathlib import Path

import click


@click.command("init")
@click.argument("directory", type=click.Path(exists=True, file_okay=False))
@click.option(
    "--survey",
    type=click.Choice(["des", "lsst"]),
    required=True,
    help="Layout of the files, and the bad-mask-bit preset of the configuration.",
)
@click.option("--overwrite", is_flag=True, help="Replace an existing manifest.toml, build.toml.")
def init_command(directory: str, survey: str, overwrite: bool) -> None:
    """Write DIRECTORY/manifest.toml and DIRECTORY/build.toml for the files found there.

    Each exposure file is matched by name to its PSF model file (PSFEx `.psf` or Piff) and,
    for DES, its `_bkg` background file; no file is opened. An exposure without a PSF file
    is written commented out. The configuration uses the survey's bad-mask-bit preset
    (`bad_mask_bits = "des"`). Edit both, then run `cellcoadd build`.

    \b
    Examples:
      cellcoadd init --survey des des-ccds/
      cellcoadd init --survey lsst visit_images/ --overwrite
      cellcoadd config --check des-ccds/build.toml
    """
    from cellcoadd.errors import CellCoaddFormatError
    from cellcoadd.io._files.atomic import atomic_write_text
    from cellcoadd.io._files.path_gate import gate_create
    from cellcoadd.io.exposures.manifest_io import build_config_toml
    from cellcoadd.io.exposures.survey_scan import find_survey_files, manifest_toml
    from cellcoadd.model.build_config import BuildConfig

    root = Path(directory)
    manifest_path, config_path = root / "manifest.toml", root / "build.toml"
    for path in (manifest_path, config_path):
        # a link (dangling or not) is refused, never written through: its target may lie
        # outside DIRECTORY; a FIFO or a device is refused before anything opens it
        try:
            gate_create(path, what=path.name)
        except CellCoaddFormatError as err:
            raise click.ClickException(str(err)) from None
        if os.path.lexists(path) and not overwrite:
            raise click.ClickException(f"{path} exists; pass --overwrite to replace it")
    found = find_survey_files(root, survey)  # type: ignore[arg-type]
    if not found:
        raise click.ClickException(f"{root}: no {survey.upper()} exposure files (.fits, .fits.fz)")
    texts = {
        manifest_path: manifest_toml(found, survey, root),  # type: ignore[arg-type]
        config_path: build_config_toml(BuildConfig.for_survey(survey), preset=survey),
    }
    for path, text in texts.items():
        # atomically: a reader sees the old file or the new one; a link or file that
        # appeared since the check is replaced (--overwrite) or kept (FileExistsError)
        try:
            atomic_write_text(path, text, overwrite=overwrite)
        except (CellCoaddFormatError, FileExistsError) as err:
            raise click.ClickException(str(err)) from None
    with_psf = sum(1 for f in found if f.psf is not None)
    click.echo(f"wrote {manifest_path} ({with_psf} of {len(found)} exposures with a PSF file)")
    for exposure in found:
        if exposure.psf is None:
            click.echo(f"  no PSF model file for {exposure.path.name}: its entry is commented out")
    click.echo(f"wrote {config_path} (bad_mask_bits = {survey!r})")
    click.echo(
        "next: `cellcoadd locate RA DEC` gives the tract and patch of a position, then\n"
        f"  cellcoadd build --manifest {manifest_path} --config {config_path} "
        "--tract T --patch PX,PY --out patch.h5"
    )
