"""Restart a drip-feed run from a block: find the point, rebuild the modal state, write a header.

`plan_restart` reads the program once, in order, keeping only the state in force (a 2 GB
program is scanned in constant memory), and stops at the restart point. The caller then
sends `plan.header`, then the program's own lines from `plan.start_line` on, reading the
file a second time (`RestartPlan.stream` does exactly that with the lines it is given).

Errors, all `ValueError`s with a `reason` a user can act on::

    RestartError
     ├── InvalidRestartPoint    the --from / --from-line / --from-tool text does not parse
     ├── RestartPointNotFound   no such block, line or tool change in the program
     └── RestartRefused         the scan cannot be sure of the state there (and says why)
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum

from jobs.dnc.blocks import Block, BlockKind, read_block
from jobs.dnc.modal import MachineKind, ModalScanner, ModalState, kind_evidence

# Cancel what must never carry into a restart: cutter compensation, canned cycles and,
# on a mill, the length offset (the header gives the tool its own G43 H again).
DEFAULT_SAFE_START: Mapping[MachineKind, tuple[str, ...]] = {
    MachineKind.MILL: ("G40 G49 G80",),
    MachineKind.LATHE: ("G40 G80",),
}
_BLOCK_TEXT = re.compile(r"N?(\d+)", re.IGNORECASE)
_TOOL_TEXT = re.compile(r"T?(\d+)", re.IGNORECASE)


class RestartError(ValueError):
    """A restart that cannot be planned; `reason` says why in words for the user."""

    def __init__(self, reason: str, *, line: int | None = None) -> None:
        """Keep the reason and the line of the program it is about, if any."""
        super().__init__(reason)
        self.reason = reason
        self.line = line


class InvalidRestartPoint(RestartError):
    """The restart point's text does not parse, or the options given do not go together."""


class RestartPointNotFound(RestartError):
    """The program has no such block, line or tool change."""


class RestartRefused(RestartError):
    """The scan cannot be sure of the modal state at the restart point."""


class PointKind(StrEnum):
    """How a restart point is named."""

    BLOCK = "block"  # --from N1234: the first block numbered N1234
    LINE = "line"  # --from-line 48213: the 48,213th line of the file, from 1
    TOOL = "tool"  # --from-tool T7: a block that changes to tool 7


@dataclass(frozen=True, slots=True)
class RestartPoint:
    """Where a run restarts.

    Attributes:
        kind: How the point is named.
        number: The block number, the line number (from 1) or the tool number.
        before_line: For a tool: look back from this line for the last change to the
            tool (at or before it); without it, the first change to the tool.
    """

    kind: PointKind
    number: int
    before_line: int | None = None

    @classmethod
    def parse(cls, *, from_block: str | None = None, from_line: str | int | None = None,
              from_tool: str | None = None) -> RestartPoint:
        """The point the CLI's options name.

        Args:
            from_block: `--from`: a block number, `N1234` or `1234`.
            from_line: `--from-line`: a line number of the file, from 1.
            from_tool: `--from-tool`: a tool, `T7` or `7`; with `from_line`, the last
                change to it at or before that line, else its first change.

        Raises:
            InvalidRestartPoint: nothing given, options that do not go together, or text
                that is not a number of its kind.
        """
        if from_block is None and from_line is None and from_tool is None:
            raise InvalidRestartPoint("give one of --from N…, --from-line L or --from-tool T…")
        if from_block is not None and (from_line is not None or from_tool is not None):
            raise InvalidRestartPoint("--from names the point alone: leave out --from-line "
                                      "and --from-tool")
        line = None if from_line is None else _line_number(from_line)
        if from_tool is not None:
            return cls(PointKind.TOOL, _number(from_tool, _TOOL_TEXT, "tool", "T7"), line)
        if from_block is not None:
            return cls(PointKind.BLOCK, _number(from_block, _BLOCK_TEXT, "block", "N1234"))
        assert line is not None
        return cls(PointKind.LINE, line)

    def describe(self) -> str:
        """The point in words: `block N1234`, `line 48213`, `the first change to T7`."""
        if self.kind is PointKind.BLOCK:
            return f"block N{self.number}"
        if self.kind is PointKind.LINE:
            return f"line {self.number}"
        if self.before_line is None:
            return f"the first change to T{self.number}"
        return f"the last change to T{self.number} at or before line {self.before_line}"


def _number(text: str, pattern: re.Pattern[str], what: str, example: str) -> int:
    match = pattern.fullmatch(text.strip())
    if not match:
        raise InvalidRestartPoint(f"{text!r} is not a {what} (write it like {example})")
    number = int(match.group(1))
    if what == "tool" and number == 0:
        raise InvalidRestartPoint("T0 selects no tool: name the tool to restart from")
    return number


def _line_number(value: str | int) -> int:
    text = str(value).strip()
    if not text.isdigit() or int(text) < 1:
        raise InvalidRestartPoint(f"{value!r} is not a line number (lines count from 1)")
    return int(text)


@dataclass(frozen=True, slots=True)
class RestartPlan:
    """What to send to restart a run.

    Attributes:
        start_line: The line of the file (from 1) the program resumes at: send it and
            every line after it, after the header.
        header: The blocks to send first, in order (see `build_header`).
        modal: The modal state in force just before `start_line`.
        machine_kind: How the program was read.
        block_number: The N number of the block at `start_line`, if it has one.
        point: The point asked for.
    """

    start_line: int
    header: list[str]
    modal: ModalState
    machine_kind: MachineKind
    block_number: int | None
    point: RestartPoint

    def stream(self, lines: Iterable[str]) -> Iterator[str]:
        """The restarted program: the header, then `lines` from `start_line` on.

        Args:
            lines: The program's lines again, from its first line (a second read of the
                file); lines before `start_line` are skipped, not kept.
        """
        yield from self.header
        for line_no, line in enumerate(lines, 1):
            if line_no >= self.start_line:
                yield line


def plan_restart(lines: Iterable[str], point: RestartPoint, *,
                 safe_start: Sequence[str] | None = None,
                 machine_kind: MachineKind | str | None = None) -> RestartPlan:
    """Plan a restart: scan the program up to the point and write the header.

    Args:
        lines: The program's lines from its first, in order; iterated once, never kept,
            and only as far as the point needs.
        point: Where to restart.
        safe_start: The blocks that open the header; default `DEFAULT_SAFE_START` for the
            machine kind. They should cancel cutter compensation and canned cycles.
        machine_kind: `mill` or `lathe`; `None` reads it from the program: the first
            block whose codes belong to one kind only (M6, G43, H… for a mill; G96, G50 S,
            U/W, a four-digit T word, G71 P…Q… for a lathe) decides.

    Raises:
        RestartPointNotFound: the program has no such point.
        RestartRefused: the scan cannot be sure of the state at the point.
    """
    kinds = [MachineKind(machine_kind)] if machine_kind else list(MachineKind)
    decided = kinds[0] if machine_kind else None
    hunts = {kind: _Hunt(kind, point, safe_start) for kind in kinds}
    line_no = 0
    for line_no, line in enumerate(lines, 1):
        block = read_block(line)
        if block.kind is BlockKind.HEIDENHAIN:
            raise RestartRefused(
                f"line {line_no} is Heidenhain plain text ({block.text}): restarting is for "
                "ISO (Fanuc-style) G-code programs only; restart it on the control",
                line=line_no)
        if decided is None and (evidence := kind_evidence(block)) is not None:
            decided = evidence
            hunts = {evidence: hunts[evidence]}
        done = True
        for hunt in hunts.values():
            hunt.step(line_no, block)
            done = done and hunt.done
        if done:
            break
    outcomes = [hunt.outcome for hunt in hunts.values() if hunt.outcome is not None]
    if not outcomes:
        raise RestartPointNotFound(
            f"the program has no {_missing(point)} (read {line_no:,} lines)")
    if decided is None:
        raise RestartRefused(
            "nothing in the program up to the restart point tells a mill program from a "
            "lathe one: give the machine kind", line=None)
    outcome = hunts[decided].outcome
    if outcome is None:
        raise RestartPointNotFound(
            f"the program has no {_missing(point)} (read {line_no:,} lines)")
    if isinstance(outcome, RestartRefused):
        raise outcome
    return outcome


def _missing(point: RestartPoint) -> str:
    if point.kind is PointKind.BLOCK:
        return f"block N{point.number}"
    if point.kind is PointKind.LINE:
        return f"line {point.number}"
    where = "" if point.before_line is None else f" at or before line {point.before_line}"
    return f"change to tool T{point.number}{where}"


class _Hunt:
    """One reading of the program for one machine kind, looking for the point."""

    def __init__(self, kind: MachineKind, point: RestartPoint,
                 safe_start: Sequence[str] | None) -> None:
        self.scanner = ModalScanner(kind)
        self.point = point
        self.safe_start = DEFAULT_SAFE_START[kind] if safe_start is None else safe_start
        self.outcome: RestartPlan | RestartRefused | None = None
        self.done = False

    def step(self, line_no: int, block: Block) -> None:
        """Check whether this block is the point, then apply it."""
        if self.done:
            return
        point = self.point
        if point.kind is PointKind.LINE:
            hit = line_no == point.number
        elif point.kind is PointKind.BLOCK:
            number = block.values.get("N", "")
            hit = number.isdigit() and int(number) == point.number
        else:
            change = self.scanner.tool_change(block)
            hit = change is not None and point.number in (change[0], int(change[1][1:]))
        if hit:
            self.outcome = self._outcome(line_no, block)
            self.done = point.kind is not PointKind.TOOL or point.before_line is None
        if point.before_line is not None and line_no >= point.before_line:
            self.done = True
        self.scanner.apply(line_no, block)

    def _outcome(self, line_no: int, block: Block) -> RestartPlan | RestartRefused:
        reason = self.scanner.refusal(line_no, block)
        if reason:
            where = self.point.describe()
            if where != f"line {line_no}":  # a block or a tool: the line it is on, too
                where += f" (line {line_no})"
            return RestartRefused(f"cannot restart from {where}: {reason}", line=line_no)
        number = block.values.get("N", "")
        modal = self.scanner.snapshot()
        tool_change_here = self.scanner.tool_change(block) is not None
        return RestartPlan(
            start_line=line_no,
            header=build_header(modal, self.scanner.kind, safe_start=self.safe_start,
                                start_line=line_no,
                                block_number=int(number) if number.isdigit() else None,
                                tool_change_here=tool_change_here),
            modal=modal,
            machine_kind=self.scanner.kind,
            block_number=int(number) if number.isdigit() else None,
            point=self.point,
        )


def build_header(modal: ModalState, kind: MachineKind, *, safe_start: Sequence[str],
                 start_line: int, block_number: int | None = None,
                 tool_change_here: bool = False) -> list[str]:
    """The blocks that put a control in `modal`'s state, in a safe order.

    Order: the safe start; units (every number after is read in them); plane; work
    offset; absolute/incremental; the tool (a mill changes it with M6, then applies G43 H
    for it, once tool and work offset are in place; a lathe indexes the turret); the
    spindle (after the tool, so no tool change or index with it turning, and before any
    feed move; on a lathe the G50 clamp first, so G96 never runs past it); coolant; feed
    mode, then feed (F is read in the mode: per minute or per revolution); the motion
    mode; then comments. No move is added: the first block after the header is the
    program's own, made from where the tool stands.

    Args:
        modal: The state to rebuild.
        kind: The machine kind it was read for.
        safe_start: The opening blocks.
        start_line: The line the program resumes at, for the comment.
        block_number: Its N number, for the comment.
        tool_change_here: The resumed block changes the tool itself: the header leaves
            the tool to it (and, on a mill, the length offset cancelled and the spindle
            stopped, as a tool change leaves them).
    """
    header = list(safe_start)
    header += [code for code in (modal.units, modal.plane, modal.work_offset) if code]
    mill = kind is MachineKind.MILL
    if mill and modal.distance:
        header.append(modal.distance)
    spindle = modal.spindle or "M5"
    if mill and tool_change_here:
        if not any("49" in read_block(b).g for b in safe_start):  # else cancelled twice
            header.append("G49")
        spindle = "M5"
    elif mill:
        if modal.tool_word:
            header.append(f"{modal.tool_word} M6")
        if modal.length_offset:
            header.append(modal.length_offset)
    elif modal.tool_word and not tool_change_here:
        header.append(modal.tool_word)
    if not mill and modal.speed_clamp:
        header.append(modal.speed_clamp)
    mode = None if mill else modal.spindle_mode
    header.append(" ".join(w for w in (mode, modal.spindle_speed, spindle) if w))
    # One M code a block: older controls refuse two.
    header += list(modal.coolant) if modal.coolant else ["M9"]
    feed = " ".join(w for w in (modal.feed_mode, modal.feed) if w)
    if feed:
        header.append(feed)
    # Only a plain G0/G1 is written alone: a cycle or thread code alone would run it.
    motion = modal.motion if modal.motion in ("G0", "G1") else None
    if motion:
        header.append(motion)
    at = f"LINE {start_line}" + (f" N{block_number}" if block_number is not None else "")
    moves = f"IN {motion} " if motion else ""
    header += [f"(RESTART AT {at})",
               f"(NO MOVE ADDED - THE NEXT BLOCK MOVES {moves}FROM WHERE THE TOOL STANDS)"]
    return header
