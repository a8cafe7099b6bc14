"""What a transport may do beyond the primitives of `base.Transport`, each optional and asked
by `isinstance(transport, Protocol)` the way capabilities are read, never by its class: a
kept link's heartbeat, a control's requests, its free space, its temporary files."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class LinkReport:
    """The state of a kept link, as its heartbeat finds it."""

    heartbeat: bool
    """The far side answered a heartbeat just now."""
    round_trip_ms: float | None
    """How long that answer took; None when it did not come."""
    error: str | None = None
    """Why the heartbeat went unanswered."""


@runtime_checkable
class LinkReporter(Protocol):
    """Optional, beside the primitives: a transport that keeps a link with a heartbeat (the
    seed protocol's `dnc`) says how that link is. A caller asks `isinstance(t,
    LinkReporter)`, the way it reads capabilities, never the transport's class."""

    def link_report(self) -> LinkReport | None:
        """Send one heartbeat and report it; never raises a TransportError (an unanswered
        heartbeat is the report). None: this link has nothing to report."""
        ...


@runtime_checkable
class RequestLink(Protocol):
    """A link on which the control's operator sends programs to dncq and reads answers in.

    Optional, beside the primitives: a transport that is one says so in its capabilities
    (`requests`). A caller holds no lock across the calls: each takes the link for as long
    as it needs it, so the link's other uses (and its heartbeat) go on between them.
    """

    def connect(self) -> None:
        """Open the link now if it is not, so that what the operator sends next is heard:
        a serial port discards what waited in its input when it is opened.

        Raises:
            TransportError: the link cannot be opened.
        """
        ...

    def receive_program(self, *, timeout_s: float) -> bytes | None:
        """The next program the control sends: its ISO text, framing characters (`%`)
        included, exactly as received minus noise (NUL, DC1, DC3, DEL); None when nothing
        began within `timeout_s`.

        Raises:
            TimedOut: a program began but stopped before its end (CutShort: with what
                came of it).
            Permanent: the program is longer than the link takes (`max_receive_bytes`);
                the rest of it was discarded and the link is ready for the next one.
            TransportError: the link failed.
        """
        ...

    def wait_ready_to_read(self, *, timeout_s: float) -> bool:
        """True once the control is ready to read a program in (its operator switched it
        to receive); False when `timeout_s` passed first.

        Raises:
            PunchedInstead: the control began to send a program meanwhile.
            TransportError: the link failed.
        """
        ...

    def send_to_read(self, name: str, data: bytes) -> None:
        """Send one program to a control that is ready to read it in (`data`: ISO text;
        framed and encoded as the link's options say).

        The control stores it under its own naming, REPLACING a program of that name (the
        operator asked for it). dncq keeps no copy of it.
        """
        ...


@runtime_checkable
class FreeSpaceTeller(Protocol):
    """A transport that can tell the free space of its storage (optional, like the
    capabilities): mock, shared folders, OctoPrint, Moonraker, FTP servers with AVBL."""

    def free_bytes(self) -> int | None:
        """Bytes free where programs are stored; None when the far side does not say."""
        ...


@runtime_checkable
class PartsOfFiles(Protocol):
    """A transport whose temporary files say which file they were for (optional, like the
    capabilities): FTP and shared folders."""

    def remove_parts_of(self, path: str) -> None:
        """Remove the temporary files earlier writes of `path`, of any process, left, now
        that `path` is in place; never raises (the file placed stays placed)."""
        ...
