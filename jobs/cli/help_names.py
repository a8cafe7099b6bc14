"""What `--help` calls the values a command takes: `MACHINE`, `[FOLDER]`, `--limit N`.

Typer (0.27 on) writes a required argument as `{machine}` and the value of an argument or
an option as its Python type, `<str>`, `<int range>`, `<bool>` even for a flag that takes
none. The commands of `Cli` show a name instead: the metavar given where one is, else the
argument's name in capitals, a number's `N`, a choice's words.
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Any

import typer
from typer.core import TyperArgument, TyperCommand, TyperGroup, TyperOption


class NamedArgument(TyperArgument):
    """An argument shown by its name alone: `MACHINE` when it must be given, `[FOLDER]` when
    it may be left out, as a Unix synopsis writes them."""

    def _usage_display_name(self) -> str:
        name = self.display_name_raw if self.required else f"[{self.display_name_raw}]"
        return f"{name}..." if self.nargs != 1 else name

    def display_type_rich(self, ctx: Any) -> str | None:
        return None  # its name says what it is; `<str>` beside it said nothing more


_UNITS = {"s": "SECONDS", "bytes": "BYTES", "days": "DAYS", "port": "PORT"}


def _value_name(option: TyperOption) -> str:
    """The word for an option's value when its declaration gives none."""
    described = option.type_descriptor
    if described.is_choice:
        return "|".join(str(c.value if isinstance(c, Enum) else c)
                        for c in described.choices or ())
    if described.annotation in (int, float):  # a unit in the name says what it counts
        return _UNITS.get((option.name or "").rpartition("_")[2], "N")
    if described.is_path or described.annotation is Path:
        return "PATH"
    return (option.name or "value").upper()


def named(param: Any) -> Any:
    """`param` made to show a readable name in the help (in place; any number of times)."""
    if isinstance(param, TyperArgument):
        if param.metavar is None:
            param.metavar = (param.name or "value").upper()
        param.__class__ = NamedArgument  # the same argument; only how it is shown changes
    elif isinstance(param, TyperOption) and param.metavar is None:
        # A flag takes no value: nothing is shown where Typer wrote <bool>.
        param.metavar = "" if param.is_flag or param.count else _value_name(param)
    return param


class NamedCommand(TyperCommand):
    """A command whose help names its arguments and options' values (`named`)."""

    def get_params(self, ctx: Any) -> list[Any]:
        return [named(p) for p in super().get_params(ctx)]


class NamedGroup(TyperGroup):
    """A group of commands whose own help names its options' values (`named`)."""

    def get_params(self, ctx: Any) -> list[Any]:
        return [named(p) for p in super().get_params(ctx)]


class Cli(typer.Typer):
    """A Typer app whose commands and groups show readable names in their help."""

    def __init__(self, **options: Any) -> None:
        super().__init__(cls=NamedGroup, **options)

    def command(self, name: str | None = None, **options: Any) -> Any:  # type: ignore[override]
        """Typer's `command`, made a `NamedCommand`."""
        return super().command(name, cls=NamedCommand, **options)
