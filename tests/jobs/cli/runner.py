"""The `dncq` command run in this process, as the CLI tests call it."""

from __future__ import annotations

import re

from typer.testing import CliRunner, Result

from jobs.cli import main as cli
from jobs.cli.common import out

TERMINAL_COLUMNS = 80  # what the CLI prints into where a test does not say


def dncq(*args: str, answer: str | None = None, width: int = TERMINAL_COLUMNS) -> Result:
    """Run `dncq args...` in this process; `answer` is what the user types at a prompt,
    `width` the terminal's columns."""
    # Set on the console itself: Rich reads COLUMNS once, when the console is made.
    out.width = width
    return CliRunner().invoke(cli.app, list(args), input=answer)


PROGRAM = "G21 G90\nG0 X0 Y0\nM30\n"  # what the `program` fixture's file holds


def table_rows(output: str, which: int = 0) -> list[dict[str, str]]:
    """The rows of a table in `output` (`jobs.cli.common.listing`; the first, or the one
    `which` counts from 0), each a cell by its column's header, a cell wrapped over lines
    joined with spaces. The header must fit on one line: see `width`."""
    lines = output.splitlines()
    rules = [i for i, line in enumerate(lines) if line.strip() and set(line.strip()) == {"─"}]
    rule = rules[which]
    header = lines[rule - 1]
    starts = [m.start() for m in re.finditer(r"\S+(?: \S+)*", header)]
    spans = list(zip(starts, [*starts[1:], None], strict=True))
    names = [header[a:b].strip() for a, b in spans]
    rows: list[dict[str, str]] = []
    for line in lines[rule + 1:]:
        if not line.strip():
            break  # the table's end
        cells = [line[a:b].strip() for a, b in spans]
        if cells[0] or not rows:
            rows.append(dict(zip(names, cells, strict=True)))
        else:  # the same row, its wrapped cells
            rows[-1] = {name: f"{rows[-1][name]} {cell}".strip()
                        for name, cell in zip(names, cells, strict=True)}
    return rows
