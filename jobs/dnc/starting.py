"""Where a run starts: at the top, or restarted from a block with its modal state rebuilt.

The restart is planned when the run is asked for, so a point the scan cannot be sure of is
refused to the user at once, and the runner only sends what was planned.
"""

from __future__ import annotations

from dataclasses import dataclass

from jobs.dnc import programs
from jobs.dnc.runs import Restart
from jobs.errors import ContractError, ErrorCode
from jobs.settings import Settings


@dataclass(frozen=True)
class RestartAsked:
    """The restart point as asked (at most one of them), or none: from the top."""

    from_block: str | None = None  # "N1234"
    from_line: int | None = None  # 48213, 1-based line of the file
    from_tool: str | None = None  # "T7": the tool change before the point

    @property
    def text(self) -> str | None:
        given = [(f"--from {self.from_block}", self.from_block is not None),
                 (f"--from-line {self.from_line}", self.from_line is not None),
                 (f"--from-tool {self.from_tool}", self.from_tool is not None)]
        chosen = [text for text, on in given if on]
        if len(chosen) > 1:
            raise ContractError(ErrorCode.BAD_PARAMETER,
                                "give one restart point: " + " or ".join(chosen))
        return chosen[0] if chosen else None


def plan(settings: Settings, program: programs.ProgramInfo,
         asked: RestartAsked) -> Restart | None:
    """The restart for `asked`, scanned from the stored program; None to start at the top."""
    text = asked.text
    if text is None:
        return None
    from jobs.dnc import restart

    try:
        if asked.from_block is not None:
            point = restart.RestartPoint.parse(asked.from_block)
        elif asked.from_line is not None:
            point = restart.RestartPoint.parse(f"line {asked.from_line}")
        else:
            point = restart.RestartPoint.parse(str(asked.from_tool))
        planned = restart.plan_restart(programs.text_lines(settings, program.id), point)
    except restart.RestartRefused as exc:
        raise ContractError(ErrorCode.BAD_PARAMETER, f"cannot restart {text}: {exc}") from None
    except ValueError as exc:
        raise ContractError(ErrorCode.BAD_PARAMETER, f"{text}: {exc}") from None
    return Restart(start_line=planned.start_line, header=list(planned.header), asked=text)
