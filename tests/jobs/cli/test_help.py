"""What `dncq ... --help` shows of each command and option, as written."""

from __future__ import annotations

import inspect
from collections.abc import Iterator

import click
import typer
from typer.testing import CliRunner

from jobs.cli import main as cli

WIDE_COLUMNS = "1000"  # every help text on one line, so that it is found whole


def _commands(command: click.Command, path: tuple[str, ...] = ()) -> Iterator[
        tuple[tuple[str, ...], list[str]]]:
    """Each command's path and the help texts its --help shows: its own first paragraph,
    its options' and arguments'."""
    texts = [inspect.cleandoc(command.help).split("\n\n")[0]] if command.help else []
    texts += [text for param in command.params if (text := getattr(param, "help", None))]
    yield path, [" ".join(text.split()) for text in texts]
    for name, sub in getattr(command, "commands", {}).items():
        yield from _commands(sub, (*path, name))


def test_help_shows_every_word_of_every_command_and_option_as_written() -> None:
    # `[default: UTC]`, `NAME[@VERSION]`: words in brackets were read as Rich markup and
    # left out of the help.
    left_out = []
    for path, texts in _commands(typer.main.get_command(cli.app)):
        shown = CliRunner().invoke(cli.app, [*path, "--help"], env={"COLUMNS": WIDE_COLUMNS})
        assert shown.exit_code == 0, shown.output
        words = " ".join(shown.output.replace("│", " ").split())
        left_out += [f"dncq {' '.join(path)}: {text}" for text in texts if text not in words]

    assert left_out == []
