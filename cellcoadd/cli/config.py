"""``cellcoadd config``: the build configuration as a file to start from."""

from __future__ import annotations

import click


@click.command("config")
@click.option("--show", is_flag=True, help="Print the default configuration.")
@click.option(
    "--check",
    "check_path",
    type=click.Path(exists=True, dir_okay=False),
    help="Validate a .toml or .json configuration and print it in full.",
)
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of TOML.")
def config_command(show: bool, check_path: str | None, as_json: bool) -> None:
    """Print the default build configuration, or check a configuration file.

    The output is a file `cellcoadd build --config` reads: every BuildConfig field, with
    units (schema: schemas/BuildConfig.v1.json). Unknown keys are refused.

    \b
    Examples:
      cellcoadd config --show > build.toml
      cellcoadd config --show --json > build.json
      cellcoadd config --check build.toml
    """
    from cellcoadd.io.exposures.manifest_io import build_config_toml, read_build_config
    from cellcoadd.model.build_config import BuildConfig

    if not show and check_path is None:
        raise click.UsageError("give --show or --check FILE")
    config = read_build_config(check_path) if check_path else BuildConfig()
    click.echo(config.model_dump_json(indent=2) if as_json else build_config_toml(config), nl=False)
    if as_json:
        click.echo()
