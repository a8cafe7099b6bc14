"""FTP failures as transport errors: the one place that knows ftplib's exceptions and the
servers' reply codes and texts."""

from __future__ import annotations

import contextlib
import ftplib
import re
import ssl
from collections.abc import Iterator

from worker.transports.base import (
    BadPath,
    Busy,
    ConnectFailed,
    Dropped,
    Exists,
    NotEmpty,
    NotFound,
    PermissionDenied,
    TimedOut,
    TransportError,
    Unsupported,
)

# A 550 reply says little by its code; its text tells NotFound from Exists from NotEmpty.
_BY_WORDS: tuple[tuple[re.Pattern[str], type[TransportError]], ...] = (
    (re.compile(r"not empty", re.I), NotEmpty),
    (re.compile(r"no such|not found|not exist|n't exist|cannot find|can't find|"
                r"not retrievable|not a directory|no files found", re.I), NotFound),
    (re.compile(r"exist", re.I), Exists),
    (re.compile(r"denied|not allowed|permission|forbidden|read-only", re.I), PermissionDenied),
)
# pyftpdlib's refusal for the account's rights, said before it looks whether the path is
# there: a permission, which the operations that find out look into as any bare refusal.
_NO_RIGHTS = re.compile(r"not enough privileges", re.I)
# What a 550 without telling words means, by operation; make_dir, remove_dir, delete and
# read find out.
_DEFAULT_550: dict[str, type[TransportError]] = {"rename": PermissionDenied}
_FIND_OUT_550 = ("make_dir", "remove_dir", "delete", "read")
# Replies refusing the connection's protection (RFC 4217; vsftpd's 522 for TLS failures),
# and the words of those that come under other codes at login (vsftpd's 530, ProFTPD's 550).
_TLS_REFUSALS = ("522", "533", "534", "431")
_TLS_WORDS = re.compile(r"\b(ssl|tls)\b|encrypt", re.I)


class Unexplained(PermissionDenied):
    """A refusal whose reply does not say why (vsftpd's bare 550s, pyftpdlib's `Not enough
    privileges.`): the transport finds out.

    Left as it is, it is what it says: the server refused.
    """


@contextlib.contextmanager
def translated(op: str, path: str) -> Iterator[None]:
    """Map what ftplib and the socket raise inside the block onto the error tree."""
    try:
        yield
    except TransportError:
        raise
    except Exception as exc:
        error = _translate(exc, op, path)
        if error is None:
            raise
        raise error from exc


def _translate(exc: Exception, op: str, path: str) -> TransportError | None:
    """The error-tree exception for a low-level one; None for what is not a link problem."""
    where = f"{op} {path!r}"
    if isinstance(exc, ftplib.error_perm | ftplib.error_temp):
        reply = str(exc).strip()
        code = reply[:3]
        by_words = next((cls for pattern, cls in _BY_WORDS if pattern.search(reply)), None)
        text = f"{where}: {reply}"
        # A refused TLS setting is not a permission; words only at login: no file names then.
        if code in _TLS_REFUSALS or (op == "connect" and _TLS_WORDS.search(reply)):
            what = "the connection's TLS setting" if op == "connect" else "the TLS data connection"
            return ConnectFailed(f"{where}: the server refused {what}: {reply}")
        if code in ("530", "532"):
            return PermissionDenied(text)
        if code in ("500", "502", "504"):
            return Unsupported(text)
        if code == "550" or (code in ("450", "501") and by_words is not None):
            if by_words is not None:
                return by_words(text)
            if op in _FIND_OUT_550 or _NO_RIGHTS.search(reply):
                return Unexplained(text)
            return _DEFAULT_550.get(op, NotFound)(text)
        if code in ("501", "553"):
            return BadPath(text)
        if code in ("425", "426"):
            return Dropped(text)
        if code.startswith("4"):
            return Busy(text)  # 421 too many users, 450 file busy, 451/452 local trouble
        return PermissionDenied(text)  # 552 quota and any other refusal
    if isinstance(exc, ftplib.error_reply | ftplib.error_proto):
        return Dropped(f"{where}: unexpected reply {exc}")
    if isinstance(exc, UnicodeError):
        return BadPath(f"{where}: a name the server's encoding cannot take ({exc})")
    if isinstance(exc, TimeoutError):
        return TimedOut(f"{where}: no answer in time")
    if isinstance(exc, ssl.SSLError) and not isinstance(
            exc, ssl.SSLEOFError | ssl.SSLZeroReturnError):  # a handshake refused, not a drop
        what = "connection" if op == "connect" else "data connection"
        return ConnectFailed(f"{where}: TLS on the {what} failed ({exc})")
    if op == "connect" and isinstance(exc, OSError):
        return ConnectFailed(f"{where}: {exc}")
    if isinstance(exc, EOFError | OSError):  # resets, broken pipes, TLS failures
        return Dropped(f"{where}: connection lost ({exc or type(exc).__name__})")
    return None
