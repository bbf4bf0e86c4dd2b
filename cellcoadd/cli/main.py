"""The ``cellcoadd`` command group and its error handling.

Errors are reported as one line (``error: ...``; usage errors after the command's usage
line) unless ``--debug`` is given, in which case the traceback is shown.
"""

from __future__ import annotations

import sys
import warnings
from importlib import import_module
from typing import TextIO

import click

from cellcoadd._version import __version__

#: command name -> (module, attribute, one-line help shown by ``cellcoadd --help``). A
#: command's module is imported only when the command runs or shows its own help, so
#: ``cellcoadd --help`` stays fast; a test checks these lines against the commands'.
COMMANDS: dict[str, tuple[str, str, str]] = {
    "demo": ("demo", "demo", "Simulate a small field, build, store, check and plot it."),
    "skymap": ("geometry", "skymap", "Print a sky map summary; optionally save and draw it."),
    "locate": ("geometry", "locate", "Print the tract, patch and cell holding sky positions."),
    "simulate": ("simulate", "simulate", "Simulate exposures as in the paper (section 3)."),
    "build": ("build", "build", "Coadd exposure files into the cells of one patch."),
    "index": ("index", "index_command", "Index input files (headers, footprints) for tract runs."),
    "run": ("run", "run_command", "Build the patches of a tract on dask (resumable)."),
    "config": ("config", "config_command", "Print the default build configuration, or check one."),
    "init": ("init", "init_command", "Write a manifest and configuration for survey files."),
    "info": ("storage", "info_command", "Summarise a stored patch coadd (no pixels read)."),
    "show": ("inspect", "show", "Draw one cell of a coadd file."),
    "trim": ("inspect", "trim", "Add unique-area flags (is_primary, ...) to a catalog."),
    "convert": ("storage", "convert_command", "Copy a patch coadd into another layout."),
    "schemas": ("storage", "schemas_command", "Write the JSON Schemas of the metadata."),
    "validate-shear": ("shear", "validate_shear", "Measure the shear bias m, c on cells."),
    "analyze": ("analyze", "analyze", "Predict what edge-free cell coadds cost."),
}


class LazyGroup(click.Group):
    """A command group that imports a command's module only when the command is used."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in COMMANDS:
            return None
        module, attribute, _ = COMMANDS[cmd_name]
        command = getattr(import_module(f"cellcoadd.cli.{module}"), attribute)
        assert isinstance(command, click.Command)
        return command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = [(name, short) for name, (_, _, short) in COMMANDS.items()]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(
    cls=LazyGroup,
    context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100},
)
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


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``cellcoadd`` console script and ``python -m cellcoadd``."""
    args = sys.argv[1:] if argv is None else list(argv)
    from cellcoadd.cli.allocator import keep_freed_memory

    keep_freed_memory()  # this process's allocator: see the module
    shown = warnings.showwarning
    warnings.showwarning = show_warning
    try:
        cli.main(args=args, prog_name="cellcoadd", standalone_mode=False)
    except click.UsageError as err:  # click's usage lines, then our one error line
        if err.ctx is not None:
            click.echo(err.ctx.get_usage(), err=True)
            help_option = err.ctx.help_option_names[0]
            click.echo(f"Try '{err.ctx.command_path} {help_option}' for help.", err=True)
        click.echo(f"error: {one_line(err.format_message())}", err=True)
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
    finally:
        warnings.showwarning = shown


def show_warning(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: TextIO | None = None,
    line: str | None = None,
) -> None:
    """A warning as one line on stderr, ``warning: Category: message`` (the message says
    what to do), written above any progress bar, never with a source line."""
    from tqdm import tqdm

    text = one_line(str(message)) or category.__name__
    tqdm.write(f"warning: {category.__name__}: {text}", file=sys.stderr)


def one_line(message: str) -> str:
    """Fold a multi-line message (e.g. a pydantic report) into one line."""
    lines = [line.strip() for line in message.strip().splitlines()]
    text = ""
    for line in lines:
        if not line or line.startswith("For further"):
            continue
        # a line that announces a list runs into it ("2 failed: a; b"), never "failed:; a"
        text += line if not text else (" " if text.endswith(":") else "; ") + line
    return text
