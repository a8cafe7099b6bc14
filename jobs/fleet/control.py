"""A machine's control beyond its files, behind its model's rules: program ranges locked,
free space, its kept link's heartbeat, drip-feed, and the link its operator sends requests on.

`MachineControl` holds the machine's transport and the catalogue row that governs it, and
refuses what either cannot do before touching the machine; `jobs.fleet.rules.MachineFiles`
adds the machine's files on top.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import cast

from jobs.errors import ContractError, ErrorCode, from_transport
from jobs.fleet.catalogue import ModelRow
from jobs.fleet.failures import mapped
from jobs.fleet.paths import bad
from worker.transports.base import (
    Transport,
    TransportError,
    Unsupported,
)
from worker.transports.drip import DripFeeder, DripResult, LineFn, LinkLost, StopFn
from worker.transports.optional import (
    FreeSpaceTeller,
    LinkReport,
    LinkReporter,
    RequestLink,
)

LOCKABLE_RANGES = ((8000, 8999), (9000, 9999), (8000, 9999))  # 2.6.10: the only ranges


class MachineControl:
    """One machine's control through its transport, with the rules of the catalogue row that
    governs it."""

    def __init__(self, transport: Transport, row: ModelRow) -> None:
        self.transport = transport
        self.row = row
        self.caps = transport.capabilities

    def lock_range(self, *, is_lock: bool, start: int, end: int) -> None:
        """Lock or unlock editing of the programs start..end (Fanuc and Mitsubishi)."""
        if not self.row.lock_range:
            raise ContractError(ErrorCode.UNSUPPORTED, f"{self.row.name} cannot lock programs")
        if (start, end) not in LOCKABLE_RANGES:
            raise bad("only the ranges 8000-8999, 9000-9999 and 8000-9999 can be locked")
        self._require(self.caps.lock_range, "lock program ranges")
        with mapped():
            self.transport.lock_range(start, end, is_lock)

    def free_bytes(self) -> int | None:
        """Bytes free on the machine's storage, where its transport can tell; else None."""
        if not isinstance(self.transport, FreeSpaceTeller):
            return None
        with mapped():
            return self.transport.free_bytes()

    def link_report(self) -> LinkReport | None:
        """How the machine's kept link answers its heartbeat; None for a transport without
        one (worker.transports.optional.LinkReporter)."""
        if not isinstance(self.transport, LinkReporter):
            return None
        return self.transport.link_report()

    def drip_feed(self, name: str, lines: Iterable[bytes], *, total_lines: int | None,
                  on_line: LineFn, should_stop: StopFn) -> DripResult:
        """Run a program on the machine while it is streamed (worker.transports.drip).

        `LinkLost` comes through as it is (its last line is the run's record); every other
        failure as the contract's error, transient only when its class is: a run is tried
        again before its first line for a control not ready or out of reach, never for one
        that broke the protocol (a bad frame), which would break it again.
        """
        self._require(self.caps.drip_feed, "drip-feed programs")
        feeder = cast(DripFeeder, self.transport)
        try:
            return feeder.drip_feed(name, lines, total_lines=total_lines, on_line=on_line,
                                    should_stop=should_stop)
        except LinkLost:
            raise
        except TransportError as exc:
            raise from_transport(exc) from exc

    def request_link(self) -> RequestLink:
        """The machine's link as one its operator sends requests on and reads answers in
        (worker.transports.optional.RequestLink): its errors are the transport's, masked of
        secrets, not the contract's. The Unsupported ContractError when the transport has
        no `requests` capability."""
        self._require(self.caps.requests, "take requests from its machine")
        return cast(RequestLink, self.transport)

    def _require(self, capable: bool, what: str) -> None:
        if not capable:
            raise from_transport(Unsupported(f"this machine's transport cannot {what}"))
