"""Options and parsers shared by several commands."""

from __future__ import annotations

from pathlib import Path

import click

from cellcoadd.geometry import SkyMap, SkyMapConfig


def parse_pair(text: str, kind: type = int) -> tuple:
    """``"3,4"`` -> ``(3, 4)`` (used for patch and cell indices)."""
    try:
        first, second = (kind(part) for part in text.split(","))
    except ValueError:
        raise click.BadParameter(f"expected two comma-separated numbers, got {text!r}") from None
    return (first, second)


def load_skymap(path: str | None) -> SkyMap:
    """A sky map from a ``skymap.json`` file, or the default full-sky rings when None."""
    if path is None:
        return SkyMap.rings()
    try:
        return SkyMap.from_json(Path(path).read_text())
    except OSError as err:
        raise click.ClickException(f"cannot read sky map {path}: {err.strerror}") from None
    except ValueError as err:
        raise click.ClickException(f"{path} is not a valid sky map file: {err}") from None


skymap_option = click.option(
    "--skymap",
    "skymap_path",
    type=click.Path(exists=True, dir_okay=False),
    help="Sky map JSON file (default: the full-sky ring tessellation).",
)

quiet_option = click.option("--quiet", "-q", is_flag=True, help="No progress bars.")

__all__ = ["SkyMapConfig", "load_skymap", "parse_pair", "quiet_option", "skymap_option"]
