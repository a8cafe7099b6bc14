"""What a received text asks for, as steps: the seed's command semantics, run in order.

A small state machine over the recognised commands: set-path changes the folder for what
follows (relative to the sources), set-file remembers a file (the last command: send it),
tool-break holds a restart block for the next send. One bad command (a path that leaves
the sources, a name that is not a file name) refuses the whole request: nothing is done.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field

from jobs.dnc.restart import RestartError, RestartPoint
from jobs.fleet.request_settings import Action, RequestSettings
from jobs.requests.naming import file_name, path_of, relative_folder
from jobs.requests.recognise import Command, Recognised, recognise

_NOT_RUN = (None, Action.SKIP, Action.RECEIVED_NAME)  # not something the request asks for
# A refusal quotes what was typed at most this long: on the control's screen the reason
# after it must still show (the report is 40 lines of 60 characters).
QUOTED_CHARS = 40
_QUOTED = re.compile(r"'[^']*'|\"[^\"]*\"")


@dataclass(frozen=True)
class Step:
    """One thing to do for a request.

    Attributes:
        action: SEND, LIST, DELETE, RENAME, COMPARE or DIRECTORY.
        folder: relative to the sources (`VIPROS`, "" for the top), `/`-separated; for
            DIRECTORY, the library folder received programs go to.
        name: the file (None for LIST and DIRECTORY; for COMPARE, None: the file named
            as the received program).
        new_name: RENAME's new name.
        restart_block: SEND: restart the program from this block (`N100`) or at the
            change to this tool (`T7`).
        note: the command it comes from (`PRG=0010, line 3`).
    """

    action: Action
    folder: str
    name: str | None
    new_name: str | None = None
    restart_block: str | None = None
    note: str = ""


@dataclass
class Plan:
    """What to do with a received text.

    Attributes:
        is_request: the text asks for something; else it is a program to receive.
        received_name: for a program to receive, the file name to store it under (None
            when it gives no usable name).
        steps: in the order asked.
        log: what was not run (skipped and unknown commands) and other notes.
        refused: why nothing is done (the request, or the text, is refused).
        program_name: the name the program gives itself (`O8888`).
    """

    is_request: bool
    received_name: str | None = None
    steps: list[Step] = field(default_factory=list)
    log: list[str] = field(default_factory=list)
    refused: str | None = None
    program_name: str | None = None


@dataclass(frozen=True)
class Outcome:
    """What one command does, for `explain`.

    Attributes:
        command: the command.
        result: in words (`send VIPROS/0010`, `skipped`, `refused: ...`).
        folder: the folder it resolved to, if any.
        name: the file name it resolved to, if any.
    """

    command: Command
    result: str
    folder: str | None = None
    name: str | None = None


def plan(text: bytes, settings: RequestSettings) -> Plan:
    """The plan for a received text (never raises for what a control may send)."""
    return planned(recognise(text, settings), settings)[0]


def planned(recognised: Recognised, settings: RequestSettings) -> tuple[Plan, list[Outcome]]:
    """The plan for recognised commands, and what each command does."""
    result = Plan(is_request=recognised.is_request, log=list(recognised.notes),
                  program_name=recognised.program_name, refused=recognised.refused)
    if recognised.refused:
        return result, []
    if not recognised.is_request:
        return _received(recognised, settings, result)
    run = _Run(settings, recognised.commands)
    outcomes = run.all()
    result.log += run.log
    if run.refused:
        result.refused = run.refused
    elif not run.steps:
        result.refused = "the request has no command dncq runs"
    else:
        result.steps = run.steps
    return result, outcomes


def _received(recognised: Recognised, settings: RequestSettings,
              result: Plan) -> tuple[Plan, list[Outcome]]:
    """A program to receive: its name from a received-name command, else its own."""
    outcomes: list[Outcome] = []
    given: str | None = None
    for command in recognised.commands:
        if command.action is Action.RECEIVED_NAME:
            given = command.body or given
            outcomes.append(Outcome(command, "names the program received"))
        else:
            result.log.append(f"{_written(command)}: not run, the program is not a request")
            outcomes.append(Outcome(command, "not run: the program is not a request"))
    name = given or recognised.program_name
    if name is None:
        result.log.append("the program gives no name")
        return result, outcomes
    try:
        result.received_name = file_name(name, settings.naming)
    except ValueError as exc:
        result.log.append(f"the program's name {name!r} is not usable: {exc}")
    return result, outcomes


def _cut(text: str) -> str:
    """`text` cut to `QUOTED_CHARS` with an ellipsis, for a refusal to quote."""
    return text if len(text) <= QUOTED_CHARS else text[:QUOTED_CHARS - 3] + "..."


def _cut_quoted(message: str) -> str:
    """`message` with each text it quotes (`file name '...'`) cut as `_cut` cuts."""
    return _QUOTED.sub(lambda m: m[0][0] + _cut(m[0][1:-1]) + m[0][0], message)


def _written(command: Command) -> str:
    return f"{command.name}={command.body} ({command.where}, line {command.line})"


class _Run:
    """The commands of one request run in order, the state they share."""

    def __init__(self, settings: RequestSettings, commands: list[Command]) -> None:
        self.settings = settings
        self.commands = commands
        self.folder = ""  # set-path's, relative to the sources
        self.file: tuple[str, str] | None = None  # set-file's (folder, name)
        self.restart: tuple[str, Command] | None = None  # tool-break's, for the next send
        self.steps: list[Step] = []
        self.log: list[str] = []
        self.refused: str | None = None
        runnable = [i for i, c in enumerate(commands) if c.action not in _NOT_RUN]
        self.last = runnable[-1] if runnable else -1
        self.index = 0
        self.handlers: dict[Action, Callable[[Command], Outcome]] = {
            Action.SEND: self._send, Action.LIST: self._list, Action.SET_PATH: self._set_path,
            Action.SET_FILE: self._set_file, Action.RENAME: self._rename,
            Action.DELETE: self._delete, Action.TOOLBREAK: self._toolbreak,
            Action.COMPARE: self._compare, Action.DIRECTORY: self._directory,
        }

    def all(self) -> list[Outcome]:
        """Run every command; what each did. A refusal clears the steps."""
        outcomes: list[Outcome] = []
        for index, command in enumerate(self.commands):
            self.index = index
            if self.refused:
                outcomes.append(Outcome(command, "not run: the request is refused"))
                continue
            try:
                outcomes.append(self._one(command))
            except ValueError as exc:
                self.refused = (f"{command.name}={_cut(command.body)} (line {command.line}): "
                                f"{_cut_quoted(str(exc))}")
                outcomes.append(Outcome(command, f"refused: {exc}"))
        if self.restart and not self.refused:
            _, command = self.restart
            self.refused = (f"{command.name}={_cut(command.body)} (line {command.line}): no "
                            f"program to send follows it")
        if self.refused:
            self.steps = []
        return outcomes

    def _one(self, command: Command) -> Outcome:
        if command.action is None:
            self.log.append(f"unknown command {_written(command)}: not run")
            return Outcome(command, "unknown command: not run")
        if command.action is Action.SKIP:
            self.log.append(f"skipped {_written(command)}")
            return Outcome(command, "skipped (logged)")
        if command.action is Action.RECEIVED_NAME:
            self.log.append(f"{_written(command)} names the request program: nothing to do")
            return Outcome(command, "names the request program: nothing to do")
        return self.handlers[command.action](command)

    def _add(self, command: Command, action: Action, folder: str, name: str | None,
             **extra: str | None) -> Step:
        step = Step(action=action, folder=folder, name=name,
                    note=f"{command.name}={command.body}, line {command.line}", **extra)
        self.steps.append(step)
        return step

    def _name(self, body: str) -> str:
        return file_name(body, self.settings.naming)

    def _send_file(self, command: Command, folder: str, name: str, why: str = "") -> Outcome:
        block = self.restart[0] if self.restart else None
        self.restart = None
        self._add(command, Action.SEND, folder, name, restart_block=block)
        restarted = f", restarted from {block}" if block else ""
        return Outcome(command, f"send {path_of(folder, name)}{restarted}{why}", folder, name)

    def _send(self, command: Command) -> Outcome:
        return self._send_file(command, self.folder, self._name(command.body))

    def _list(self, command: Command) -> Outcome:
        folder = relative_folder(command.body) if command.body else self.folder
        self._add(command, Action.LIST, folder, None)
        return Outcome(command, f"send the listing of {path_of(folder, None)}", folder)

    def _set_path(self, command: Command) -> Outcome:
        self.folder = relative_folder(command.body)
        return Outcome(command, f"folder for what follows: {path_of(self.folder, None)}",
                       self.folder)

    def _set_file(self, command: Command) -> Outcome:
        self.file = (self.folder, self._name(command.body))
        if self.index == self.last:  # the seed: as the last command, it asks for the file
            return self._send_file(command, *self.file, why=" (the last command)")
        return Outcome(command, f"file for what follows: {path_of(*self.file)}", *self.file)

    def _rename(self, command: Command) -> Outcome:
        if self.file is None:
            raise ValueError("no file to rename: set one first (the set-file command)")
        folder, name = self.file
        new_name = self._name(command.body)
        self._add(command, Action.RENAME, folder, name, new_name=new_name)
        self.file = (folder, new_name)
        return Outcome(command, f"rename {path_of(folder, name)} to {new_name}", folder, name)

    def _delete(self, command: Command) -> Outcome:
        if command.body:
            folder, name = self.folder, self._name(command.body)
        elif self.file:
            folder, name = self.file
        else:
            raise ValueError("no file to delete: name one")
        self._add(command, Action.DELETE, folder, name)
        return Outcome(command, f"delete {path_of(folder, name)}", folder, name)

    def _toolbreak(self, command: Command) -> Outcome:
        text = command.body.strip().upper()
        try:
            if text.startswith("T"):
                point = RestartPoint.parse(from_tool=text)
                block = f"T{point.number}"
            else:
                point = RestartPoint.parse(from_block=text)
                block = f"N{point.number}"
        except RestartError as exc:
            raise ValueError(str(exc)) from None
        self.restart = (block, command)
        return Outcome(command, f"the next program sent restarts from {point.describe()}")

    def _compare(self, command: Command) -> Outcome:
        name = self._name(command.body) if command.body else None
        self._add(command, Action.COMPARE, self.folder, name)
        against = path_of(self.folder, name) if name else "the file of its name"
        return Outcome(command, f"the next program received is compared with {against}",
                       self.folder, name)

    def _directory(self, command: Command) -> Outcome:
        folder = relative_folder(command.body)
        if not folder:
            raise ValueError("name the library folder received programs go to")
        self._add(command, Action.DIRECTORY, folder, None)
        expires_min = self.settings.directory_expires_s / 60
        return Outcome(command, f"programs received go to {folder} for {expires_min:g} min",
                       folder)
