"""The ``cellcoadd`` command group and its error handling.

Errors are reported as one line (``error: ...``) unless ``--debug`` is given, in which
case the traceback is shown.
"""

from __future__ import annotations

import sys

import click

from cellcoadd._version import __version__
from cellcoadd.cli.analyze import analyze
from cellcoadd.cli.build import build
from cellcoadd.cli.demo import demo
from cellcoadd.cli.geometry import locate, skymap
from cellcoadd.cli.inspect import show, trim
from cellcoadd.cli.shear import validate_shear
from cellcoadd.cli.simulate import simulate
from cellcoadd.cli.storage import convert_command, info_command, schemas_command


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="cellcoadd")
@click.option("--debug", is_flag=True, help="Show full tracebacks on errors.")
def cli(debug: bool) -> None:
    """Build, store and inspect cell-based coadds for weak-lensing shear.

    \b
    Examples:
      cellcoadd demo --out demo-output
      cellcoadd skymap --rings
      cellcoadd locate 150.1 2.2
      cellcoadd <command> --help
    """


for command in (
    demo,
    skymap,
    locate,
    simulate,
    build,
    info_command,
    show,
    trim,
    convert_command,
    schemas_command,
    validate_shear,
    analyze,
):
    cli.add_command(command)


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``cellcoadd`` console script and ``python -m cellcoadd``."""
    args = sys.argv[1:] if argv is None else list(argv)
    try:
        cli.main(args=args, prog_name="cellcoadd", standalone_mode=False)
    except click.UsageError as err:
        err.show()
        sys.exit(err.exit_code)
    except click.ClickException as err:
        click.echo(f"error: {one_line(err.format_message())}", err=True)
        sys.exit(err.exit_code)
    except click.exceptions.Exit as err:
        sys.exit(err.exit_code)
    except click.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except Exception as err:  # one clear line unless --debug
        if "--debug" in args:
            raise
        message = one_line(str(err)) or type(err).__name__
        click.echo(f"error: {message} (--debug shows the traceback)", err=True)
        sys.exit(1)


def one_line(message: str) -> str:
    """Fold a multi-line message (e.g. a pydantic report) into one line."""
    lines = [line.strip() for line in message.strip().splitlines()]
    return "; ".join(line for line in lines if line and not line.startswith("For further"))
