"""What `dncq ... --help` shows of each command and option, as written."""

from __future__ import annotations

import inspect
import re
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


def _every_help() -> Iterator[tuple[str, str]]:
    """Each command's name and its --help, on a terminal wide enough for a line each."""
    for path, _ in _commands(typer.main.get_command(cli.app)):
        shown = CliRunner().invoke(cli.app, [*path, "--help"], env={"COLUMNS": WIDE_COLUMNS})
        assert shown.exit_code == 0, shown.output
        yield f"dncq {' '.join(path)}".strip(), shown.output


def test_help_names_every_value_a_command_takes_not_its_python_type() -> None:
    # Typer wrote `get [OPTIONS] {machine} {FILE}` and `--to <str>`, `--all <bool>`.
    typed = re.compile(r"\{\w[^}\s]*\}|<(?:str|int|float|bool|path|list\[|int range|float "
                       r"range)[^>]*>")
    found = [f"{command}: {', '.join(typed.findall(text))}" for command, text in _every_help()
             if typed.search(text)]

    assert found == []


def test_help_writes_an_argument_by_its_name_in_capitals_and_an_optional_one_in_brackets(
        ) -> None:
    usage = {command: text.split("Usage:")[1].split("\n")[0].strip()
             for command, text in _every_help()}

    assert usage["dncq get"].endswith("get [OPTIONS] MACHINE FILE")
    assert usage["dncq ls"].endswith("ls [OPTIONS] MACHINE [FOLDER]")
    assert usage["dncq send"].endswith("send [OPTIONS] [FILE]")
    assert usage["dncq stop"].endswith("stop [OPTIONS] JOB")


def test_an_argument_left_out_is_named_as_the_help_names_it() -> None:
    shown = CliRunner().invoke(cli.app, ["get"])

    assert shown.exit_code == 2
    assert "Missing argument 'MACHINE'" in shown.output
