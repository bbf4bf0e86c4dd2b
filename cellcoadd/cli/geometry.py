"""``cellcoadd skymap`` and ``cellcoadd locate``."""

from __future__ import annotations

import json

import click
import numpy as np

from cellcoadd.cli.options import load_skymap, parse_pair, skymap_option
from cellcoadd.geometry import SkyMap, SkyMapConfig


@click.command()
@click.option("--rings", "kind", flag_value="rings", default=True, help="Our own full-sky rings.")
@click.option(
    "--lsst",
    "kind",
    flag_value="lsst",
    help="Rubin's ring sky map (lsst_cells_v1 with the default sizes; the tract size "
    "follows from them).",
)
@click.option(
    "--center", "centers", multiple=True, help="Explicit tract centre RA,DEC in deg (repeat)."
)
@click.option("--pixel-scale", type=float, default=0.2, show_default=True, help="arcsec/pixel")
@click.option("--cell-inner", type=int, default=150, show_default=True, help="pixels")
@click.option("--cell-border", type=int, default=50, show_default=True, help="pixels")
@click.option("--cells-per-patch", type=int, default=20, show_default=True)
@click.option("--patches-per-tract", type=int, default=10, show_default=True)
@click.option("--out", type=click.Path(dir_okay=False), help="Write the sky map JSON here.")
@click.option(
    "--layout",
    type=click.Path(dir_okay=False),
    help="Write a PNG of one patch's cell layout (paper Fig. 7).",
)
@click.option("--patch", "patch_text", default="0,0", show_default=True, help="PX,PY for --layout")
@click.option("--tract", "tract_id", type=int, default=0, show_default=True, help="for --layout")
def skymap(
    kind: str,
    centers: tuple[str, ...],
    pixel_scale: float,
    cell_inner: int,
    cell_border: int,
    cells_per_patch: int,
    patches_per_tract: int,
    out: str | None,
    layout: str | None,
    patch_text: str,
    tract_id: int,
) -> None:
    """Print a sky map summary; optionally save it and draw a patch layout.

    \b
    Examples:
      cellcoadd skymap
      cellcoadd skymap --lsst
      cellcoadd skymap --center 150.1,2.2 --cells-per-patch 4 --out skymap.json
      cellcoadd skymap --layout layout.png --patch 3,4
    """
    config = SkyMapConfig(
        pixel_scale=pixel_scale,
        cell_inner=cell_inner,
        cell_border=cell_border,
        cells_per_patch=cells_per_patch,
        patches_per_tract=patches_per_tract,
    )
    if centers:
        the_map = SkyMap.from_centers([parse_pair(c, float) for c in centers], config)
    elif kind == "lsst":
        if config == SkyMapConfig():
            the_map = SkyMap.named("lsst_cells_v1")
        else:  # Rubin's algorithm derives the tract size: drop the default patch count
            sizes = config.model_dump(exclude={"patches_per_tract"})
            the_map = SkyMap.lsst(SkyMapConfig(**sizes))
    else:
        the_map = SkyMap.rings(config)
    click.echo(the_map.summary())
    if out:
        from cellcoadd.io._files.atomic import atomic_write_text  # loads cellcoadd.io: only here

        atomic_write_text(out, the_map.to_json(), overwrite=True)
        click.echo(f"wrote {out}")
    if layout:
        from cellcoadd.plots import plot_patch_layout

        patch = the_map[tract_id].patch(*parse_pair(patch_text))
        plot_patch_layout(patch, layout)
        click.echo(f"wrote {layout}")


@click.command(context_settings={"ignore_unknown_options": True})
@click.argument("ra", type=float)
@click.argument("dec", type=float)
@skymap_option
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def locate(ra: float, dec: float, skymap_path: str | None, as_json: bool) -> None:
    """Print the tract, patch and cell whose inner regions hold RA DEC (deg).

    Negative coordinates need no `--`: `cellcoadd locate 10.0 -30.0` works.

    \b
    Examples:
      cellcoadd locate 10.0 -30.0
      cellcoadd locate 150.3 2.0 --skymap skymap.json --json
      cellcoadd locate 53.16 -28.1 --skymap lsst
    """
    if not 0.0 <= ra <= 360.0:  # NaN fails both checks too
        raise click.BadParameter(f"{ra} is outside [0, 360] deg", param_hint="RA")
    if not -90.0 <= dec <= 90.0:
        raise click.BadParameter(f"{dec} is outside [-90, 90] deg", param_hint="DEC")
    the_map = load_skymap(skymap_path)
    where = the_map.locate(np.array([ra]), np.array([dec]))[0]
    result = {name: where[name].item() for name in where.dtype.names}
    for name, value in result.items():  # outside every tract: no pixel position
        if isinstance(value, float) and not np.isfinite(value):
            result[name] = None
    if as_json:
        click.echo(json.dumps(result))
    elif result["tract"] < 0:
        click.echo(f"({ra}, {dec}) is in no tract of this sky map")
    else:
        click.echo(
            f"tract {result['tract']}  patch ({result['patch_x']}, {result['patch_y']})  "
            f"cell ({result['cell_x']}, {result['cell_y']})  "
            f"tract pixel ({result['x']:.2f}, {result['y']:.2f})  "
            f"Rubin: patch {result['patch_id']}, cell "
            f"({result['rubin_cell_x']}, {result['rubin_cell_y']})"
        )
