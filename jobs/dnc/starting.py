"""Where a run starts: at the top, or restarted from a block with its modal state rebuilt.

The restart is planned when the run is asked for, so a point the scan cannot be sure of is
refused to the user at once, and the runner only sends what was planned.
"""

from __future__ import annotations

from dataclasses import dataclass

from jobs.dnc import programs, restart
from jobs.dnc.modal import MachineKind
from jobs.dnc.runs import Restart
from jobs.errors import ContractError, ErrorCode
from jobs.settings import Settings


@dataclass(frozen=True)
class RestartAsked:
    """The restart point as asked, or none: from the top (jobs.dnc.restart.RestartPoint)."""

    from_block: str | None = None  # "N1234"
    from_line: int | None = None  # 48213, 1-based line of the file
    from_tool: str | None = None  # "T7": its first change, or its last before from_line
    machine_kind: MachineKind | None = None  # mill or lathe; None: read from the program

    @property
    def given(self) -> bool:
        return (self.from_block, self.from_line, self.from_tool) != (None, None, None)


def plan(settings: Settings, program: programs.ProgramInfo,
         asked: RestartAsked) -> Restart | None:
    """The restart for `asked`, scanned from the stored program; None to start at the top.

    Raises a ContractError (20001, or 158 for a point the program does not have) with the
    reason, the line it is about where there is one.
    """
    if not asked.given:
        return None
    try:
        point = restart.RestartPoint.parse(from_block=asked.from_block,
                                           from_line=asked.from_line,
                                           from_tool=asked.from_tool)
        planned = restart.plan_restart(programs.text_lines(settings, program.id), point,
                                       machine_kind=asked.machine_kind)
    except restart.RestartPointNotFound as exc:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, _said(exc)) from None
    except restart.RestartError as exc:
        raise ContractError(ErrorCode.BAD_PARAMETER, _said(exc)) from None
    return Restart(start_line=planned.start_line, header=list(planned.header),
                   asked=point.describe())


def _said(exc: restart.RestartError) -> str:
    """The refusal once: a scan's reason already says it cannot restart, and from which
    line (it read `cannot restart: cannot restart from line 23: line 23 is … (line 23)`)."""
    said = exc.reason if exc.reason.startswith("cannot restart") \
        else f"cannot restart: {exc.reason}"
    if exc.line is not None and f"line {exc.line}" not in said:
        said += f" (line {exc.line})"
    return said
