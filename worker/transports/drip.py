"""Drip-feed (DNC machining): a program streamed to a machine while it runs it.

A link that can drip-feed (the seed protocol's `dnc` transport, an RS-232 `serial` line)
implements `DripFeeder` beside the file primitives and says so in its capabilities
(`drip_feed`). The caller hands over the program as lines and learns, while it runs, the
line the machine is executing; the link does the framing, the flow control (the
machine's ready state, XON/XOFF) and the heartbeat.

Lines are counted from 1 in the order the caller gives them; the "running line" is the
last line the machine confirmed it executed (over the seed protocol, its line sync;
over RS-232, the lines flow control let through), never a line merely sent.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from worker.transports.base import Dropped

LineFn = Callable[[int, int], None]
"""Called with (running line, lines sent so far) whenever either moves."""

StopFn = Callable[[], bool]
"""Polled while running: True when the run must stop (the machine is reset)."""


@dataclass(frozen=True)
class DripResult:
    """How a run ended that did not fail."""

    lines_sent: int
    """Lines handed to the machine."""
    last_line: int
    """The last line the machine confirmed it executed."""
    stopped: bool
    """Ended on request: the rest of the program was not sent."""
    stop_said: str = "the machine was reset"
    """What a stop did to the machine, as the run's record says it."""


class LinkLost(Dropped):
    """The link stayed down longer than its grace period: the run is over.

    `last_line` is the last line the machine confirmed before the link went, the point a
    restart from a block starts from.
    """

    def __init__(self, message: str, *, last_line: int, lines_sent: int) -> None:
        super().__init__(message)
        self.last_line = last_line
        self.lines_sent = lines_sent


@runtime_checkable
class DripFeeder(Protocol):
    """A link that can feed a running program (capabilities.drip_feed is True)."""

    def drip_feed(self, name: str, lines: Iterable[bytes], *, total_lines: int | None,
                  on_line: LineFn, should_stop: StopFn) -> DripResult:
        """Run the program `name` from `lines` (each without its line ending, in the
        machine's encoding), read lazily: a program of any size runs in constant memory.

        Returns when the machine has executed the last line (or was stopped); raises
        `LinkLost` when the link stayed down past its grace period, another
        `TransportError` when the run could not start (not in DNC mode: Busy; refused:
        PermissionDenied). A link drop shorter than the grace period is not an error: the
        run goes on with the next line the machine has not got, none lost or repeated.
        """
        ...
