"""The transport interface: the few primitives every way of reaching a machine's files implements.

A transport moves bytes and knows nothing of controller models: paths are POSIX
paths relative to the top of the storage it reaches ("" is the top, "CNC_MEM/USER"
a folder below it). Model rules (roots, naming, what is allowed) live above it.

Errors, one tree; retry decisions read only the class::

    TransportError
    ├── Transient              try again later
    │   ├── ConnectFailed      refused, unreachable, DNS
    │   ├── TimedOut           no answer in time
    │   │   └── CutShort       a program the control sent stopped before its end
    │   ├── Dropped            connection lost mid-operation
    │   ├── Busy               the machine refuses more work right now
    │   └── Offline            the machine is switched off or marked offline
    └── Permanent              the same request will fail again
        ├── NotFound           no such file or folder (158)
        ├── Exists             a file of that name is already there (142)
        ├── NotEmpty           folder still holds files
        ├── Unsupported        this transport cannot do that
        ├── PermissionDenied   the far side refused the operation
        └── BadPath            a path the far side cannot take
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Annotated, ClassVar, Protocol, runtime_checkable

from pydantic import AfterValidator, BaseModel, ConfigDict, Field

ProgressFn = Callable[[int, int | None], None]
"""Called with (bytes done, bytes in all or None when unknown)."""

CHUNK_BYTES = 256 * 1024
# Half-written files carry this prefix until they are complete: never listed, never read.
# It lies inside jobs.fleet.paths.RESERVED_PREFIX, which no name a user gives may start with.
PART_PREFIX = ".dncq-part-"


def parts_of(name: str) -> str:
    """How the temporary files of writes of the file `name` begin: the prefix, then a digest
    of the name, so that a write that placed a file knows which its earlier ones left."""
    return f"{PART_PREFIX}{hashlib.sha256(name.encode()).hexdigest()[:8]}-"


class TransportError(Exception):
    """Anything that went wrong reaching a machine's files."""


class Transient(TransportError):
    """Worth retrying: the machine or the link may come back."""


class ConnectFailed(Transient):
    """The machine could not be reached."""


class TimedOut(Transient):
    """The machine did not answer in time."""


class CutShort(TimedOut):
    """A program the control sent stopped before its end; `received` is what came of it."""

    def __init__(self, message: str, *, received: bytes) -> None:
        super().__init__(message)
        self.received = received


class Dropped(Transient):
    """The connection was lost in the middle of an operation."""


class Busy(Transient):
    """The machine refuses more work right now."""


class Offline(Transient):
    """The machine is switched off or marked offline."""


class PunchedInstead(TransportError):
    """The control sent a program while dncq waited for it to read one in: it is left on
    the link for the next `receive_program`."""


class Permanent(TransportError):
    """The same request will fail again."""


class NotFound(Permanent):
    """No such file or folder."""


class Exists(Permanent):
    """A file or folder of that name is already there."""


class NotEmpty(Permanent):
    """The folder still holds files or folders."""


class Unsupported(Permanent):
    """This transport or machine cannot do that."""


class PermissionDenied(Permanent):
    """The far side refused the operation."""


class BadPath(Permanent):
    """A path the far side cannot take."""


@dataclass(frozen=True)
class Entry:
    """One file or folder in a listing.

    A size that is no byte count (negative, a fraction, `true`, more than any file system
    holds) is a far side's nonsense: the entry says it does not know, rather than passing
    it on to a Content-Length, a progress bar or a message.
    """

    name: str
    is_dir: bool
    size: int | None = None  # bytes; None when the far side does not say
    mtime: float | None = None  # POSIX seconds; None when the far side does not say

    def __post_init__(self) -> None:
        if self.size is not None and byte_count(self.size) is None:
            object.__setattr__(self, "size", None)  # frozen: the dataclass way to normalise


LARGEST_FILE_BYTES = 2**63 - 1  # the most a file can hold anywhere (POSIX off_t, ZIP64, HTTP)


def byte_count(value: object) -> int | None:
    """`value` when it is a count of bytes a file can have, else None."""
    if isinstance(value, bool) or not isinstance(value, int):  # JSON `true` is no size
        return None
    return value if 0 <= value <= LARGEST_FILE_BYTES else None


class Capabilities(BaseModel):
    """What a transport can do beyond the basic file primitives."""

    model_config = ConfigDict(frozen=True)

    folders: bool = True
    """Folders exist below the top: list them, and walk into them."""
    make_dirs: bool = True
    """Folders can be created and removed."""
    lock_range: bool = False
    """Program numbers can be locked against editing (2.6.10)."""
    select_program: bool = False
    """A program can be selected as the main program (2.6.14)."""
    current_program: bool = False
    """The running program can be asked for (2.6.4)."""
    atomic_write: bool = True
    """A write appears under its name only when complete."""
    drip_feed: bool = False
    """A program can be streamed to the machine while it runs (worker.transports.drip)."""
    requests: bool = False
    """The machine's operator can send programs to dncq over the link and read dncq's
    answers in: machine-initiated requests (`RequestLink`)."""
    held_copies: bool = False
    """What `list_dir`, `stat` and `read` show is what dncq holds for the machine on this
    host, not the machine's memory: reading it leaves the machine's link alone."""


class TransportOptions(BaseModel):
    """Base of every transport's options model; secrets are `SecretStr` fields."""

    # An error's text never quotes what was given: a password typed into the wrong option
    # (or a URL's) would reach the log of a machine whose stored options fail to load.
    model_config = ConfigDict(extra="forbid", hide_input_in_errors=True)

    def missing_package(self) -> str | None:
        """What to install for these options to work here, or None when nothing is missing.

        Asked when a machine is registered, not when it is opened: a machine whose package
        went missing later is refused by its transport (Unsupported), one operation at a time.
        """
        return None


def _host_only(value: str) -> str:
    # A URL here (ftp://user:password@host) would keep the password in an option stored
    # unsealed, shown to every viewer of the machine and quoted in each connection error.
    if any(mark in value for mark in ("://", "@", "/", "\\")):
        raise ValueError("a host name or address only, not a URL: give the user and the "
                         "password as their own options")
    return value


HostName = Annotated[str, Field(min_length=1), AfterValidator(_host_only)]
"""A server's host name or IP address, nothing around it."""


class NetworkOptions(TransportOptions):
    """Options of a transport that reaches its machine over the network."""

    timeout_s: float = Field(default=30.0, gt=0)
    """Longest wait to connect, and for each reply or next bytes: catches a silent far side."""
    transfer_timeout_s: float = Field(default=900.0, gt=0)
    """Longest one request or file transfer may take in all: catches a far side that
    trickles its bytes, which `timeout_s` alone never does."""


class Deadline:
    """The end of one transfer, checked as its bytes come and go."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self._ends = time.monotonic() + seconds

    def passed(self) -> bool:
        return time.monotonic() > self._ends

    @property
    def missed(self) -> str:
        """What to say once it has passed."""
        return f"not complete within {self.seconds:g} s (transfer_timeout_s)"

    def check(self, what: str) -> None:
        """Raise TimedOut once the deadline has passed."""
        if self.passed():
            raise TimedOut(f"{what}: {self.missed}")


@runtime_checkable
class Transport(Protocol):
    """The primitives; the optional ones raise `Unsupported` unless capabilities say so."""

    capabilities: ClassVar[Capabilities]
    own_storage: ClassVar[bool]
    """True when the transport reaches the controller's own storage (its model's row
    governs); False for a file server in front of the machine (the server's row does)."""
    server_row: ClassVar[str | None]
    """Catalogue row of the file-server type when `own_storage` is False."""

    def list_dir(self, path: str) -> list[Entry]:
        """Entries of the folder at `path` (NotFound if it is missing)."""
        ...

    def stat(self, path: str) -> Entry:
        """The entry at `path` (NotFound if it is missing)."""
        ...

    def read(self, path: str, *, progress: ProgressFn | None = None) -> Iterator[bytes]:
        """The file's bytes in chunks; raises NotFound before yielding if it is missing."""
        ...

    def write(
        self, path: str, chunks: Iterable[bytes], *, progress: ProgressFn | None = None
    ) -> int:
        """Store a new file and return its size; Exists if the name is taken.

        Never overwrites, never leaves a partial file under the name.
        """
        ...

    def delete(self, path: str) -> None:
        """Delete the file at `path`."""
        ...

    def make_dir(self, path: str) -> None:
        """Create one folder (its parent must exist)."""
        ...

    def remove_dir(self, path: str) -> None:
        """Remove an empty folder."""
        ...

    def lock_range(self, start: int, end: int, locked: bool) -> None:
        """Lock or unlock editing of programs numbered start..end."""
        ...

    def select_program(self, path: str) -> None:
        """Make the program at `path` the main program."""
        ...

    def current_program(self) -> str | None:
        """Path of the running program, or None when nothing runs."""
        ...

    def close(self) -> None:
        """Release connections."""
        ...


class NoMachineControl:
    """The optional operations, refused: for transports that reach a file server in front of
    a machine, not its controller (FTP, shared folders, gateways, printer hosts)."""

    def lock_range(self, start: int, end: int, locked: bool) -> None:
        raise Unsupported(f"{type(self).__name__} cannot lock program ranges")

    def select_program(self, path: str) -> None:
        raise Unsupported(f"{type(self).__name__} cannot select a program")

    def current_program(self) -> str | None:
        raise Unsupported(f"{type(self).__name__} cannot tell the running program")


def below_root(path: str, root: str) -> str | None:
    """`path` below `root`, the one folder a flat link shows (a control's program memory:
    Fanuc's `//CNC_MEM/` is `CNC_MEM`); None for the top above it; NotFound elsewhere.

    A model whose root is the top ("") takes every path as it is.
    """
    path, root = path.strip("/"), root.strip("/")
    if not root:
        return path
    if path == root:
        return ""
    if path.startswith(root + "/"):
        return path[len(root) + 1:]
    if not path:
        return None
    raise NotFound(f"{path}: this link reaches the control's program memory ({root}) only")


def first_chunk_then(chunks: Iterator[bytes]) -> Iterator[bytes]:
    """Start a generator so that errors raised before the first chunk surface now."""
    try:
        first = next(chunks)
    except StopIteration:
        return iter(())

    def rest() -> Iterator[bytes]:
        yield first
        yield from chunks

    return rest()
