"""Options and parsers shared by several commands."""

from __future__ import annotations

import os

import click

from cellcoadd.geometry import SkyMap, SkyMapConfig
from cellcoadd.geometry.skymap import LSST_SKYMAPS, SKYMAP_ALIASES


def parse_pair(text: str, kind: type = int) -> tuple:
    """``"3,4"`` -> ``(3, 4)`` (used for patch and cell indices)."""
    try:
        first, second = (kind(part) for part in text.split(","))
    except ValueError:
        raise click.BadParameter(f"expected two comma-separated numbers, got {text!r}") from None
    return (first, second)


def load_skymap(path: str | None) -> SkyMap:
    """A sky map from a ``skymap.json`` file or a sky map name (``lsst``,
    ``lsst_cells_v1``, ...: Rubin's ring sky map), or the default full-sky rings when None.

    A name is taken as a name only when no file of that name exists."""
    if path is None:
        return SkyMap.rings()
    if path in KNOWN_SKYMAP_NAMES and not os.path.exists(path):
        return SkyMap.named(path)
    from cellcoadd.errors import CellCoaddFormatError
    from cellcoadd.io._files.path_gate import read_bytes

    try:
        text = read_bytes(path, what="sky map", max_bytes=16 * 1024 * 1024).decode("utf-8")
        return SkyMap.from_json(text)
    except (OSError, CellCoaddFormatError) as err:
        raise click.ClickException(f"cannot read sky map {path}: {err}") from None
    except ValueError as err:
        raise click.ClickException(f"{path} is not a valid sky map file: {err}") from None


def check_output_path(out: str, overwrite: bool, *, directory_may_be_created: bool = False) -> None:
    """Refuse, before any work, a coadd output the command could not write.

    Raises
    ------
    click.ClickException
        For a missing directory (unless the command creates it), an unknown extension, a
        CFITSIO-style name (``x[1].fits``, ``!x.fits``, see
        :func:`cellcoadd.io._fits.paths.check_fits_path`) or an existing file without
        ``--overwrite``.
    """
    from cellcoadd.io._fits.paths import check_fits_path
    from cellcoadd.io.api import file_format

    directory = os.path.dirname(os.path.abspath(out))
    if not directory_may_be_created and not os.path.isdir(directory):
        raise click.ClickException(f"{out}: the directory {directory} does not exist")
    name = os.path.basename(out)
    if name.startswith("!") or "[" in name or "]" in name:
        raise click.ClickException(f"{out}: '!', '[' and ']' are not allowed in file names")
    try:
        if file_format(out) == "fits":
            check_fits_path(out)
    except ValueError as err:
        raise click.ClickException(str(err)) from None
    if os.path.exists(out) and not overwrite:
        raise click.ClickException(f"{out} exists; pass --overwrite to replace it")


def check_output_not_an_input(out: str, inputs: list[str]) -> None:
    """Refuse an output that is one of the command's input files (the same file, by
    device and inode, or the same resolved path): with ``--overwrite`` it would be lost.

    Raises
    ------
    click.ClickException
        Naming the input.
    """
    target = os.path.realpath(out)
    for name in inputs:
        same = os.path.realpath(name) == target
        if not same and os.path.exists(out) and os.path.exists(name):
            same = os.path.samefile(out, name)
        if same:
            raise click.ClickException(
                f"{out}: --out is the input file {name}; write the coadd elsewhere"
            )


#: Sky map names ``--skymap`` accepts besides JSON files.
KNOWN_SKYMAP_NAMES = (*SKYMAP_ALIASES, *LSST_SKYMAPS)

skymap_option = click.option(
    "--skymap",
    "skymap_path",
    type=str,
    help="Sky map JSON file, or a name: lsst (= lsst_cells_v1, Rubin's ring sky map), "
    "lsst_cells_v2, DC2_cells_v1 (default: our own full-sky ring tessellation).",
)

quiet_option = click.option("--quiet", "-q", is_flag=True, help="No progress bars.")

__all__ = [
    "SkyMapConfig",
    "check_output_path",
    "load_skymap",
    "parse_pair",
    "quiet_option",
    "skymap_option",
]
