"""The `dncq` command run in this process, as the CLI tests call it."""

from __future__ import annotations

from typer.testing import CliRunner, Result

from jobs.cli import main as cli


def dncq(*args: str, answer: str | None = None) -> Result:
    """Run `dncq args...` in this process; `answer` is what the user types at a prompt."""
    return CliRunner().invoke(cli.app, list(args), input=answer)


PROGRAM = "G21 G90\nG0 X0 Y0\nM30\n"  # what the `program` fixture's file holds
