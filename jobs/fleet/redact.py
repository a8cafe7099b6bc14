"""A machine's transport with its secrets masked out of every error that leaves it.

A far side may echo what it was sent (`530 Login incorrect for <password>`); the message
then reaches `statusMsg`, job records, backup errors and logs. The registry wraps every
transport it opens in `Redacting`, so no transport has to remember.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Iterator
from dataclasses import replace
from typing import Any, ClassVar, TypeVar
from urllib.parse import quote, quote_plus

from worker.transports.base import (
    Capabilities,
    Entry,
    ProgressFn,
    Transport,
    TransportError,
    Unsupported,
)
from worker.transports.drip import DripFeeder, DripResult, LineFn, LinkLost, StopFn
from worker.transports.optional import (
    FreeSpaceTeller,
    LinkReport,
    LinkReporter,
    PartsOfFiles,
    RequestLink,
)

MASK = "**********"
MIN_SECRET_CHARS = 4  # masking "a" or "" would shred every message and hide nothing

T = TypeVar("T")


class Redactor:
    """Masks a set of secret values in text and in exceptions."""

    def __init__(self, secrets: Iterable[str]) -> None:
        # As written, and as a URL or a repr() would quote it; longest first, so that a
        # secret that contains another is masked whole.
        forms = {form for s in secrets if len(s) >= MIN_SECRET_CHARS
                 for form in (s, quote(s, safe=""), quote_plus(s), repr(s)[1:-1])}
        self.secrets = sorted(forms, key=len, reverse=True)
        # In any case: a server may echo it changed (pyftpdlib capitalizes a refusal).
        self._found = re.compile("|".join(map(re.escape, self.secrets)), re.IGNORECASE) \
            if self.secrets else None

    def text(self, text: str) -> str:
        """`text` with every secret replaced by the mask, in whatever case it shows."""
        return self._found.sub(MASK, text) if self._found else text

    def leaks(self, exc: BaseException) -> bool:
        """Whether `exc` or an exception it was raised from shows a secret."""
        seen: set[int] = set()
        current: BaseException | None = exc
        while current is not None and id(current) not in seen:
            seen.add(id(current))
            shown = " ".join([str(current), repr(current), *map(str, current.args)])
            if self._found and self._found.search(shown):
                return True
            current = current.__cause__ or current.__context__
        return False

    def exception(self, exc: BaseException) -> BaseException:
        """`exc` itself when it shows no secret, else a copy with them masked.

        The copy keeps the class when it is one of the error tree's (retry decisions read
        it); any other class becomes a `TransportError` naming it. The chain is masked too.
        """
        if not self.secrets or not self.leaks(exc):
            return exc
        message = self.text(str(exc))
        copy: BaseException
        if isinstance(exc, TransportError):
            try:
                copy = type(exc)(message)
            except TypeError:  # a subclass with its own signature
                copy = TransportError(message)
        else:
            copy = TransportError(f"{type(exc).__name__}: {message}")
        copy.__traceback__ = exc.__traceback__
        inner = exc.__cause__ or exc.__context__
        copy.__cause__ = self.exception(inner) if inner is not None else None
        copy.__suppress_context__ = True
        return copy

    def call(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """`fn(*args, **kwargs)`, its exceptions masked."""
        try:
            return fn(*args, **kwargs)
        except Exception as exc:
            masked = self.exception(exc)
            if masked is exc:
                raise
            raise masked from masked.__cause__  # noqa: B904 - the chain is masked, not lost

    def chunks(self, chunks: Iterator[bytes]) -> Iterator[bytes]:
        """The chunks of a read; an error in the middle masked like the others."""
        while True:
            try:
                chunk = next(chunks)
            except StopIteration:
                return
            except Exception as exc:
                masked = self.exception(exc)
                if masked is exc:
                    raise
                raise masked from masked.__cause__  # noqa: B904 - as in call()
            yield chunk


class Redacting:
    """A transport whose errors never show its machine's secrets."""

    capabilities: ClassVar[Capabilities] = Capabilities()  # replaced per instance
    own_storage: ClassVar[bool] = True
    server_row: ClassVar[str | None] = None

    def __init__(self, transport: Transport, redactor: Redactor) -> None:
        self.inner = transport
        self.redactor = redactor
        cls = type(transport)
        # The wrapped transport's class facts, read by the rules above it.
        self.capabilities = cls.capabilities  # type: ignore[misc]
        self.own_storage = cls.own_storage  # type: ignore[misc]
        self.server_row = cls.server_row  # type: ignore[misc]

    def list_dir(self, path: str) -> list[Entry]:
        return self.redactor.call(self.inner.list_dir, path)

    def stat(self, path: str) -> Entry:
        return self.redactor.call(self.inner.stat, path)

    def read(self, path: str, *, progress: ProgressFn | None = None) -> Iterator[bytes]:
        chunks = self.redactor.call(self.inner.read, path, progress=progress)
        return self.redactor.chunks(iter(chunks))

    def write(self, path: str, chunks: Iterable[bytes], *,
              progress: ProgressFn | None = None) -> int:
        return self.redactor.call(self.inner.write, path, chunks, progress=progress)

    def delete(self, path: str) -> None:
        self.redactor.call(self.inner.delete, path)

    def make_dir(self, path: str) -> None:
        self.redactor.call(self.inner.make_dir, path)

    def remove_dir(self, path: str) -> None:
        self.redactor.call(self.inner.remove_dir, path)

    def lock_range(self, start: int, end: int, locked: bool) -> None:
        self.redactor.call(self.inner.lock_range, start, end, locked)

    def select_program(self, path: str) -> None:
        self.redactor.call(self.inner.select_program, path)

    def current_program(self) -> str | None:
        return self.redactor.call(self.inner.current_program)

    def drip_feed(self, name: str, lines: Iterable[bytes], *, total_lines: int | None,
                  on_line: LineFn, should_stop: StopFn) -> DripResult:
        if not isinstance(self.inner, DripFeeder):
            raise Unsupported(f"{type(self.inner).__name__} cannot drip-feed")
        try:
            return self.inner.drip_feed(name, lines, total_lines=total_lines,
                                        on_line=on_line, should_stop=should_stop)
        except LinkLost as exc:  # its own signature: masked by hand, its lines kept
            raise LinkLost(self.redactor.text(str(exc)), last_line=exc.last_line,
                           lines_sent=exc.lines_sent) from None
        except Exception as exc:
            masked = self.redactor.exception(exc)
            if masked is exc:
                raise
            raise masked from masked.__cause__  # noqa: B904 - as in Redactor.call

    def connect(self) -> None:
        self.redactor.call(self._requests().connect)

    def receive_program(self, *, timeout_s: float) -> bytes | None:
        return self.redactor.call(self._requests().receive_program, timeout_s=timeout_s)

    def wait_ready_to_read(self, *, timeout_s: float) -> bool:
        return self.redactor.call(self._requests().wait_ready_to_read, timeout_s=timeout_s)

    def send_to_read(self, name: str, data: bytes) -> None:
        self.redactor.call(self._requests().send_to_read, name, data)

    def _requests(self) -> RequestLink:
        if not self.capabilities.requests or not isinstance(self.inner, RequestLink):
            raise Unsupported(f"{type(self.inner).__name__} takes no requests from its "
                              "machine")
        return self.inner

    def free_bytes(self) -> int | None:
        if not isinstance(self.inner, FreeSpaceTeller):
            return None
        return self.redactor.call(self.inner.free_bytes)

    def remove_parts_of(self, path: str) -> None:
        if isinstance(self.inner, PartsOfFiles):
            self.redactor.call(self.inner.remove_parts_of, path)

    def link_report(self) -> LinkReport | None:
        if not isinstance(self.inner, LinkReporter):
            return None  # a transport without a kept link
        report = self.inner.link_report()
        if report is None or report.error is None:
            return report
        return replace(report, error=self.redactor.text(report.error))

    def close(self) -> None:
        self.redactor.call(self.inner.close)
