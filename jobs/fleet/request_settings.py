"""A machine's request settings: how the programs it sends are read as requests and answered.

The fleet file's `requests:` of a machine, validated at import. `resolve` gives the settings
for a controller: the preset of its family (`request_presets.py`) under what was given.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Literal, cast

from pydantic import Field, field_validator

from jobs.fleet import catalogue, request_presets
from jobs.fleet.request_formats import (
    HeaderFormat,
    ListingFormat,
    Model,
    NamingRules,
    ReportFormat,
    check_file_name,
    check_relative_folder,
    check_template,
    decode_marker,
)

__all__ = [
    "Action", "Dialect", "HeaderFormat", "ListingFormat", "NamingRules", "Preset",
    "ReportFormat", "RequestSettings", "Source", "check_file_name", "check_relative_folder",
    "check_template", "compile_pattern", "decode_marker", "family_of", "resolve",
]

Preset = Literal["fanuc", "haas", "heidenhain_iso", "siemens_iso"]
Dialect = Literal["fanuc", "heidenhain_iso", "siemens_iso"]

_COMMAND_NAME = re.compile(r"[!-~]+")  # printable ASCII, no spaces
_MACHINE_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")  # as the registry's MachineIn.id


class Action(StrEnum):
    """What a command asks of dncq."""

    SEND = "send"  # send the named file
    LIST = "list"  # send the listing of the current folder
    SET_PATH = "set_path"  # set the folder, relative to the sources, for what follows
    SKIP = "skip"  # ignore the command, and say so in the log
    SET_FILE = "set_file"  # remember a file for what follows; as the last command: send it
    RECEIVED_NAME = "received_name"  # the name of the program being received
    DELETE = "delete"  # delete the named file (or the remembered one)
    RENAME = "rename"  # rename the remembered file to the named one
    TOOLBREAK = "toolbreak"  # send the next program restarted from this block (N100, T7)
    COMPARE = "compare"  # compare the next program received with the server's copy
    DIRECTORY = "directory"  # received programs go to this library folder for a while


@dataclass(frozen=True)
class Source:
    """A folder programs are looked up in: a library folder, or a folder on a machine.

    Attributes:
        kind: `library` or `machine`.
        folder: the library folder (`VIPROS`, "" for the library's top), or the folder in
            the machine's notation (`//CNC_MEM/PROGS`, `TNC:\\nc_prog`).
        machine_id: the machine, for `machine`.
    """

    kind: Literal["library", "machine"]
    folder: str
    machine_id: str | None = None

    @classmethod
    def parse(cls, text: str) -> Source:
        """`library:VIPROS`, `library:` (the top) or `machine:ID:/path`.

        Raises:
            ValueError: any other form, or an unsafe folder.
        """
        kind, colon, rest = text.partition(":")
        if kind == "library" and (colon or not rest):
            return cls("library", check_relative_folder(rest.strip("/"), what="library folder"))
        if kind == "machine" and colon:
            machine_id, colon, folder = rest.partition(":")
            if not _MACHINE_ID.fullmatch(machine_id) or not colon or not folder:
                raise ValueError(f"source {text!r}: write machine:ID:/folder")
            if re.search(r"[\x00-\x1f\x7f]", folder) or ".." in re.split(r"[/\\]", folder):
                raise ValueError(f"source {text!r}: the folder has control characters or '..'")
            return cls("machine", folder, machine_id)
        raise ValueError(f"source {text!r} is not library:FOLDER or machine:ID:/folder")

    def __str__(self) -> str:
        return (f"library:{self.folder}" if self.kind == "library"
                else f"machine:{self.machine_id}:{self.folder}")


def _default_commands() -> dict[str, Action]:
    return {name: Action(action) for name, action in request_presets.COMMANDS.items()}


class RequestSettings(Model):
    """A machine's requests: where they are recognised, what their commands do, where the
    programs come from and go to, and how the answers are written."""

    enabled: bool = False
    """Listen for requests from this machine."""
    preset: Preset | None = None
    """The controller family the defaults came from (`resolve` sets it)."""
    dialect: Dialect = "fanuc"
    """How the control names and frames programs: fanuc (`%`, `O1234`; also Haas and most
    ISO controls), heidenhain_iso (`%1234 G71 *`), siemens_iso (`%_N_NAME_MPF`)."""
    where: Literal["body", "header", "both"] = "body"
    """Recognise commands in the program body, in the control header, or both."""
    header: HeaderFormat = HeaderFormat()
    """How header commands are cut out."""
    request_program: str = Field(default="O8888", min_length=1)
    """Body commands are searched only in the program of this name (or one a
    received-name command gives this name)."""
    body_syntax: Literal["comment", "slash", "both"] = "both"
    """Body commands as comments (`(PRG=0010)`, `;PRG=0010` where `;` comments), as
    slash words (`/REQ 111`), or both."""
    body_separator: str = Field(default="=", min_length=1)
    """Between name and body in a comment command."""
    patterns: list[str] = []
    """Advanced: regular expressions, each with two groups, the command and its body
    (or groups named `command` and `body`); when given, they replace the header and body
    syntax above. Matched with `re.MULTILINE`."""
    commands: dict[str, Action] = Field(default_factory=_default_commands)
    """Command name (case does not matter) to action."""
    naming: NamingRules = NamingRules(pad_to=4, number_letter="O")
    """How a body becomes a file name."""
    sources: list[str] = Field(default=["library:"], min_length=1)
    """Where programs are looked up, first match wins: `library:FOLDER` (`library:` is the
    library's top) or `machine:ID:/folder`."""
    receive_folder: str = "RECEIVED"
    """The library folder programs received from the machine are destined for."""
    listing: ListingFormat = ListingFormat()
    """The listing program, and how answer programs are written."""
    error_program: ReportFormat = ReportFormat()
    """The error and status report program."""
    switch_window_s: float = Field(default=180.0, gt=0)
    """How long the operator has to switch the control to receive the answer."""
    request_delay_s: float = Field(default=0.0, ge=0, le=600)
    """A pause before answering (controls that need a moment to switch)."""
    directory_expires_s: float = Field(default=3600.0, gt=0)
    """How long a directory runner sends received programs to its folder."""
    drop_folder: str | None = None
    """On a machine reached through a folder: where the control writes request programs."""
    answer_folder: str | None = None
    """Where answers are written on such a machine; None: the drop folder."""
    max_request_bytes: int = Field(default=64 * 1024, ge=256, le=16 * 1024 * 1024)
    """Larger received text is never read as a request."""

    @field_validator("commands")
    @classmethod
    def _command_names(cls, value: dict[str, Action]) -> dict[str, Action]:
        seen: dict[str, str] = {}
        for name in value:
            if not _COMMAND_NAME.fullmatch(name):
                raise ValueError(f"command name {name!r} must be printable ASCII without spaces")
            if name.upper() in seen:
                raise ValueError(f"command names {seen[name.upper()]!r} and {name!r} are one "
                                 f"name (case does not matter)")
            seen[name.upper()] = name
        return value

    @field_validator("patterns")
    @classmethod
    def _patterns_compile(cls, value: list[str]) -> list[str]:
        for pattern in value:
            compile_pattern(pattern)
        return value

    @field_validator("sources")
    @classmethod
    def _sources_parse(cls, value: list[str]) -> list[str]:
        return [str(Source.parse(text)) for text in value]

    @field_validator("receive_folder")
    @classmethod
    def _receive_folder(cls, value: str) -> str:
        if not check_relative_folder(value, what="receive_folder"):
            raise ValueError("receive_folder is required (a library folder such as RECEIVED)")
        return value

    @field_validator("drop_folder", "answer_folder")
    @classmethod
    def _machine_folder(cls, value: str | None) -> str | None:
        if value is not None and (not value or re.search(r"[\x00-\x1f\x7f]", value)):
            raise ValueError("a folder on the machine, without control characters")
        return value

    @property
    def parsed_sources(self) -> list[Source]:
        """`sources`, parsed, in order."""
        return [Source.parse(text) for text in self.sources]

    @property
    def answers_to(self) -> str | None:
        """The folder answers are written to on a folder-reached machine."""
        return self.answer_folder or self.drop_folder

    def action_of(self, name: str) -> Action | None:
        """The action of a command name (case does not matter); None for an unknown one."""
        return {key.upper(): action for key, action in self.commands.items()}.get(name.upper())


def compile_pattern(pattern: str) -> re.Pattern[str]:
    """A command pattern compiled, checked to have its two groups.

    Raises:
        ValueError: it does not compile, or has fewer than two groups.
    """
    try:
        compiled = re.compile(pattern, re.MULTILINE)
    except re.error as exc:
        raise ValueError(f"pattern {pattern!r} does not compile: {exc}") from None
    named = {"command", "body"} <= set(compiled.groupindex)
    if compiled.groups < 2 and not named:
        raise ValueError(f"pattern {pattern!r} has {compiled.groups} group(s); it needs two, "
                         f"the command and its body, such as \\((\\w+)=([^)]*)\\)")
    return compiled


_BRAND_PRESETS = {"haas": "haas", "heidenhain": "heidenhain_iso", "siemens": "siemens_iso"}


def family_of(model_family_or_model: str) -> Preset | None:
    """The preset for a controller: a preset's own name, or a catalogue model's family
    (None for a model with no preset of its own: the defaults, Fanuc-like, apply)."""
    key = model_family_or_model.strip().lower().replace("-", "_").replace(" ", "_")
    if key not in request_presets.PRESETS:
        try:
            row = catalogue.lookup(model_family_or_model)
        except catalogue.UnknownModel:
            return None
        key = "fanuc" if row.is_fanuc else _BRAND_PRESETS.get(row.name.split()[0].lower(), "")
    return cast(Preset, key) if key in request_presets.PRESETS else None


def resolve(model_family_or_model: str, given: dict[str, Any] | None) -> RequestSettings:
    """The request settings of a machine: its family's preset with `given` over it.

    `given["preset"]` chooses the preset over the model's family. Nested settings
    (`header`, `naming`, `listing`, `error_program`) are overridden field by field; lists
    and `commands` are replaced whole.

    Raises:
        pydantic.ValidationError: the merged settings are invalid (a ValueError).
    """
    given = dict(given or {})
    preset = given.get("preset") or family_of(model_family_or_model)
    merged: dict[str, Any] = _merged(request_presets.PRESETS.get(preset or "", {}), given)
    merged["preset"] = preset
    return RequestSettings.model_validate(merged)


def _merged(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict) and key != "commands":
            out[key] = _merged(base[key], value)
        else:
            out[key] = value
    return out
