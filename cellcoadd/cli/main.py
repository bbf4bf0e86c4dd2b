"""The ``cellcoadd`` command group."""

import click

from cellcoadd._version import __version__


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="cellcoadd")
def cli() -> None:
    """Build, store and inspect cell-based coadds."""


def main() -> None:
    cli()
