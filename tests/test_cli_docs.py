"""Every command has --help with examples, and docs/cli.md documents every command."""

from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from cellcoadd.cli.main import cli

CLI_DOC = (Path(__file__).resolve().parents[1] / "docs" / "cli.md").read_text()


def _commands(group: click.Group, prefix: str):
    for name in group.list_commands(None):  # type: ignore[arg-type]
        command = group.get_command(None, name)  # type: ignore[arg-type]
        yield f"{prefix} {name}", command
        if isinstance(command, click.Group):
            yield from _commands(command, f"{prefix} {name}")


COMMANDS = list(_commands(cli, "cellcoadd"))


@pytest.mark.parametrize(("name", "command"), COMMANDS, ids=[n for n, _ in COMMANDS])
def test_command_has_examples_and_is_documented(name, command):
    args = name.split()[1:] + ["--help"]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert "Examples:" in result.output, f"{name} --help has no examples"
    assert f"## `{name}`" in CLI_DOC, f"{name} is missing from docs/cli.md"
