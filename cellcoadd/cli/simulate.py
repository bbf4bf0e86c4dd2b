"""``cellcoadd simulate``: write the paper's simulations as exposure files."""

from __future__ import annotations

import json
from pathlib import Path

import click
from tqdm import tqdm

from cellcoadd.cli.options import load_skymap, parse_pair, quiet_option
from cellcoadd.io._files.atomic import atomic_write_text
from cellcoadd.pipelines.simulation_files import write_field_simulation, write_stamps
from cellcoadd.sim import (
    DEMO_PATCH,
    FieldConfig,
    SimConfig,
    demo_skymap,
    simulate_field,
    simulate_object,
)

#: radial SIP coefficient used by --sip: about 0.7 pixel at the corner of the default plane
SIP_K = 1e-9


@click.command()
@click.option(
    "--mode",
    type=click.Choice(["field", "stamps"]),
    default="field",
    show_default=True,
    help="field: CCD exposures over a patch; stamps: isolated galaxies, 10 epochs each.",
)
@click.option(
    "--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output directory."
)
@click.option(
    "--visits", type=click.IntRange(min=1), default=10, show_default=True, help="field mode"
)
@click.option(
    "--objects", type=click.IntRange(min=1), default=100, show_default=True, help="stamps mode"
)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--shear", "shear_text", default="0.02,0.0", show_default=True, help="G1,G2")
@click.option(
    "--noise", type=float, help="Pixel noise sigma, counts (default: the paper's DES-like level)."
)
@click.option(
    "--skymap",
    "skymap_path",
    type=click.Path(exists=True, dir_okay=False),
    help="field mode: sky map JSON (default: a demo tract of 3 x 3 patches of 4 x 4 cells).",
)
@click.option("--tract", "tract_id", type=int, default=0, show_default=True, help="field mode")
@click.option("--patch", "patch_text", help="field mode: PX,PY (default: the demo patch 1,1).")
@click.option(
    "--ccd-pixels",
    type=click.IntRange(min=32),
    default=FieldConfig().ccd_nx,
    show_default=True,
    help="field mode: CCD side, pixels (3 x 3 CCDs per visit). Cells lose the visits whose "
    "CCD edges cross them: much smaller CCDs leave cells empty.",
)
@click.option(
    "--dither", type=click.Choice(["random", "spiral", "none"]), default="random", show_default=True
)
@click.option("--rotate", is_flag=True, help="field mode: random focal-plane rotation per visit.")
@click.option("--sip", is_flag=True, help="field mode: small radial SIP distortion.")
@click.option("--psf-variation", is_flag=True, help="field mode: PSF varying over the focal plane.")
@click.option("--overwrite", is_flag=True, help="Replace existing files.")
@quiet_option
def simulate(
    mode: str,
    out_dir: str,
    visits: int,
    objects: int,
    seed: int,
    shear_text: str,
    noise: float | None,
    skymap_path: str | None,
    tract_id: int,
    patch_text: str | None,
    ccd_pixels: int,
    dither: str,
    rotate: bool,
    sip: bool,
    psf_variation: bool,
    overwrite: bool,
    quiet: bool,
) -> None:
    """Simulate exposures as in the paper (section 3) and write them as FITS files.

    Field mode writes visit{V:04d}-det{D:02d}.fits, skymap.json, truth.fits, visits.fits
    and simulation.json; stamps mode writes object{I:05d}/epoch{E:02d}.fits, truth.fits
    and epochs.fits. Everything is fixed by --seed.

    \b
    Examples:
      cellcoadd simulate --mode field --out sim-field
      cellcoadd simulate --mode field --out sim-spiral --visits 20 --dither spiral --rotate --sip
      cellcoadd simulate --mode stamps --out sim-plus --objects 200 --seed 7
      cellcoadd simulate --mode stamps --out sim-minus --objects 200 --seed 7 --shear -0.02,0
    """
    shear = parse_pair(shear_text, float)
    field = FieldConfig(
        ccd_nx=ccd_pixels,
        ccd_ny=ccd_pixels,
        dither=dither,
        rotate=rotate,
        sip_k=SIP_K if sip else 0.0,
        psf_fwhm_edge=0.05 if psf_variation else 0.0,
        psf_g_edge=0.01 if psf_variation else 0.0,
    )
    settings: dict = {"shear": shear, "field": field}
    if noise is not None:
        settings["noise_sigma"] = noise
    config = SimConfig(**settings)
    out = Path(out_dir)
    if not overwrite and (out / "simulation.json").exists():
        raise click.ClickException(f"{out} already holds a simulation; use --overwrite")
    try:
        if mode == "stamps":
            message = _write_stamps(config, out, objects, seed, overwrite, quiet)
        else:
            if skymap_path is None:
                skymap = demo_skymap(config.ra, config.dec)
                patch = DEMO_PATCH if patch_text is None else parse_pair(patch_text)
            else:
                skymap = load_skymap(skymap_path)
                patch = (0, 0) if patch_text is None else parse_pair(patch_text)
            result = simulate_field(
                config, skymap, tract_id, patch, visits, seed, progress=not quiet
            )
            write_field_simulation(result, out, overwrite=overwrite)
            message = (
                f"wrote {len(result.exposures)} exposures ({visits} visits x "
                f"{len(result.exposures) // visits} CCDs), {len(result.truth)} objects, "
                f"tract {tract_id} patch {patch[0]},{patch[1]} to {out}"
            )
    except FileExistsError as err:
        raise click.ClickException(f"{err}; use --overwrite") from None
    if not quiet:
        click.echo(message)


def _write_stamps(
    config: SimConfig, out: Path, n_objects: int, seed: int, overwrite: bool, quiet: bool
) -> str:
    simulated = [
        simulate_object(config, seed, index)
        for index in tqdm(range(n_objects), desc="objects", disable=quiet)
    ]
    paths = write_stamps(simulated, out, overwrite=overwrite)
    description = {"mode": "stamps", "seed": seed, "n_objects": n_objects}
    description["config"] = config.model_dump(mode="json")
    text = json.dumps(description, indent=2) + "\n"
    atomic_write_text(out / "simulation.json", text, overwrite=True)  # refused up front
    return f"wrote {len(paths) - 2} exposures of {n_objects} objects to {out}"
