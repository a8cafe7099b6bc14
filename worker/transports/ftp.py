"""The `ftp` transport: a machine's FTP server, or an FTP file server in front of it.

Standard-library ftplib, plain or explicit FTPS (worker.transports.ftp_link opens the
connections); connections are opened lazily and kept for the next call until `close()`,
which hands them to the process's kept connections (worker.transports.ftp_pool) for the
next job's transport of the same server and account. What is at a name is looked up in
worker.transports.ftp_lookups; the server's replies map onto the error tree in
worker.transports.ftp_errors, the one place that knows them.
"""

from __future__ import annotations

import contextlib
import ftplib
import posixpath
import socket
import threading
import time
import uuid
from collections.abc import Iterable, Iterator
from typing import ClassVar

from worker.transports.base import (
    CHUNK_BYTES,
    PART_PREFIX,
    BadPath,
    Capabilities,
    Deadline,
    Entry,
    Exists,
    NoMachineControl,
    NotEmpty,
    NotFound,
    Permanent,
    PermissionDenied,
    ProgressFn,
    Transient,
    TransportError,
    parts_of,
)
from worker.transports.ftp_errors import Unexplained, translated
from worker.transports.ftp_link import FtpOptions, alive, finish, open_link, quiet
from worker.transports.ftp_lookups import FtpLookups, size_of
from worker.transports.ftp_pool import KEPT, quit_quietly
from worker.transports.left_parts import LeftParts

# A kept connection idle longer than this, or on which the server sent something unasked
# (a 421 before hanging up), is probed with NOOP before use.
_IDLE_CHECK_S = 5.0

# The temporary files this process's writes left, by server and account: the file's next
# write here removes them.
_LEFT = LeftParts()


class FtpTransport(FtpLookups, NoMachineControl):
    """Files on an FTP server; paths are relative to the server's top ("" is "/")."""

    capabilities: ClassVar[Capabilities] = Capabilities(
        folders=True, make_dirs=True, lock_range=False, select_program=False,
        current_program=False,
    )
    own_storage: ClassVar[bool] = False
    server_row: ClassVar[str | None] = "FTP server"

    def __init__(self, options: FtpOptions) -> None:
        self.options = options
        self._idle: list[tuple[ftplib.FTP, float]] = []  # kept connections, last used (monotonic)
        self._lock = threading.Lock()
        self._has_mlsd: bool | None = None  # None until the server has been asked
        self._has_mlst: bool | None = None

    def __repr__(self) -> str:
        return f"FtpTransport({self.options.user}@{self.options.host}:{self.options.port})"

    # -- connections -------------------------------------------------------

    @contextlib.contextmanager
    def _session(self, *, fresh: bool = False) -> Iterator[ftplib.FTP]:
        """A logged-in connection: a kept one if any, else (or if `fresh`) a new one; kept after.

        A connection whose operation failed other than by a clean refusal (a Permanent
        error) is closed instead, since its replies may be out of step.
        """
        ftp = None
        while ftp is None:
            with self._lock:
                kept = self._idle.pop() if self._idle and not fresh else None
            if kept is None and not fresh:
                kept = KEPT.take(self.options.connection_key())  # an earlier job's
            if kept is None:
                ftp = open_link(self.options)
            elif ((time.monotonic() - kept[1] < _IDLE_CHECK_S and quiet(kept[0]))
                  or alive(kept[0])):
                ftp = kept[0]
            else:
                kept[0].close()  # the server hung up while it was idle
        try:
            yield ftp
        except Permanent:
            self._keep(ftp)
            raise
        except BaseException:
            ftp.close()
            raise
        self._keep(ftp)

    def _keep(self, ftp: ftplib.FTP) -> None:
        if ftp.sock is None:  # closed on purpose: its replies were out of step
            return
        with self._lock:
            self._idle.append((ftp, time.monotonic()))

    def close(self) -> None:
        with self._lock:
            idle, self._idle = self._idle, []
        keep_s = self.options.keep_connection_s
        for ftp, used in idle:
            if keep_s > 0:
                KEPT.give(self.options.connection_key(), ftp, used=used, keep_s=keep_s)
            else:
                quit_quietly(ftp)

    # -- primitives --------------------------------------------------------

    def free_bytes(self) -> int | None:
        """The server's `AVBL` answer (the streamlined-FTP extension), where it has one.

        vsftpd, ProFTPD and pyftpdlib have none: they do not say, and that is None.
        """
        try:
            with self._session() as ftp:
                reply = ftp.sendcmd("AVBL")
        except ftplib.Error:
            return None
        number = reply[4:].strip().split(" ", 1)[0] if reply.startswith("213") else ""
        return int(number) if number.isdigit() else None

    def list_dir(self, path: str) -> list[Entry]:
        full = _absolute(path)
        with self._session() as ftp:
            return _visible(self._list(ftp, full, path))

    def stat(self, path: str) -> Entry:
        full = _absolute(path)
        if posixpath.basename(full).startswith(PART_PREFIX):
            raise NotFound(path)
        if full == "/":
            return Entry("", True)
        with self._session() as ftp:
            return self._stat(ftp, full, path)

    def read(self, path: str, *, progress: ProgressFn | None = None) -> Iterator[bytes]:
        full = _absolute(path)
        deadline = Deadline(self.options.transfer_timeout_s)
        with self._session() as ftp:
            total: int | None = None
            if progress is not None:  # SIZE is for progress only: RETR decides the end
                with contextlib.suppress(Permanent), translated("read", path):
                    total = size_of(ftp.size, full)
            try:
                with translated("read", path):
                    conn = ftp.transfercmd(f"RETR {full}")
            except Unexplained as exc:
                raise self._explained(ftp, "read", full, path, exc) from exc
            done = 0
            with conn:
                while True:
                    with translated("read", path):
                        data = conn.recv(CHUNK_BYTES)
                    if not data:
                        break
                    deadline.check(f"read {path!r}")
                    done += len(data)
                    yield data
                    if progress:
                        progress(done, total)
                with translated("end of read", path):  # a refusal there is not of the file
                    finish(ftp, conn)

    def write(
        self, path: str, chunks: Iterable[bytes], *, progress: ProgressFn | None = None
    ) -> int:
        full = _absolute(path)
        folder, name = posixpath.split(full)
        if not name:
            raise BadPath(f"no file name in {path!r}")
        part = posixpath.join(folder, f"{parts_of(name)}{uuid.uuid4().hex}")
        deadline = Deadline(self.options.transfer_timeout_s)
        with self._session() as ftp:
            if self._exists(ftp, full, path):  # before sending: no upload only to be refused
                raise Exists(path)
        try:
            with self._session() as ftp:
                conn = self._store(ftp, part, folder, path)
                done = 0
                with conn:
                    try:
                        for chunk in chunks:  # the source's own errors pass through unmapped
                            with translated("write", path):
                                conn.sendall(chunk)
                            deadline.check(f"write {path!r}")
                            done += len(chunk)
                            if progress:
                                progress(done, None)
                    except BaseException:
                        ftp.close()  # mid-transfer: the control link is out of step, drop it
                        raise
                    with translated("write", path):
                        finish(ftp, conn)
                # Race: FTP has no rename-unless-exists, and RNTO overwrites on most
                # servers; this second check narrows, not closes, the window in which
                # another client could create the name and lose its file to ours.
                if self._exists(ftp, full, path):
                    raise Exists(path)
                with translated("rename", path):
                    ftp.rename(part, full)
                self._remove_parts_left(ftp, full)
        except BaseException as exc:
            why_left = self._remove_part(part)
            if why_left is None:
                raise
            _LEFT.add(self.options.connection_key(), full, part)
            left = f"the temporary file {part!r} was left behind ({why_left})"
            if isinstance(exc, TransportError):  # its message is the target's statusMsg
                raise type(exc)(f"{exc}; {left}") from exc
            exc.add_note(left)
            raise
        return done

    def remove_parts_of(self, path: str) -> None:
        """Remove the temporary files earlier writes of `path`, of any process, left in its
        folder, now that `path` is in place: none of them can be placed any more (a write
        never replaces a file, and looks for the name once more before its rename), so no
        writer is kept from anything. Best effort: `path` stays placed whatever comes of it.
        """
        full = _absolute(path)
        folder, name = posixpath.split(full)
        with contextlib.suppress(Exception), self._session() as ftp:
            for entry in self._list_all(ftp, folder, folder):
                if entry.name.startswith(parts_of(name)):
                    with contextlib.suppress(NotFound):
                        self._delete(ftp, posixpath.join(folder, entry.name), entry.name)

    def delete(self, path: str) -> None:
        full = _absolute(path)
        with self._session() as ftp:
            self._delete(ftp, full, path)

    def make_dir(self, path: str) -> None:
        full = _absolute(path)
        with self._session() as ftp:
            try:
                with translated("make_dir", path):
                    ftp.mkd(full)
            except Unexplained as exc:
                raise self._explained(ftp, "make_dir", full, path, exc) from exc

    def remove_dir(self, path: str) -> None:
        full = _absolute(path)
        if full == "/":
            raise PermissionDenied("the top folder cannot be removed")
        with self._session() as ftp:
            try:
                with translated("remove_dir", path):
                    ftp.rmd(full)
            except Unexplained as exc:
                raise self._explained(ftp, "remove_dir", full, path, exc) from exc

    # -- helpers -----------------------------------------------------------

    def _store(self, ftp: ftplib.FTP, part: str, folder: str, path: str) -> socket.socket:
        """STOR's data connection; a refusal into a folder that is not there is NotFound,
        into one that is there PermissionDenied (the temporary name is ours, and good)."""
        try:
            with translated("write", path):
                return ftp.transfercmd(f"STOR {part}")
        except (BadPath, PermissionDenied) as exc:  # vsftpd: "553 Could not create file."
            if not self._is_dir(ftp, folder):
                raise NotFound(f"write {path!r}: the folder {folder!r} is not there") from exc
            if isinstance(exc, BadPath):
                raise PermissionDenied(f"{exc} (into the folder {folder!r})") from exc
            raise

    def _delete(self, ftp: ftplib.FTP, full: str, path: str) -> None:
        try:
            with translated("delete", path):
                ftp.delete(full)
        except Unexplained as exc:
            raise self._explained(ftp, "delete", full, path, exc) from exc

    def _explained(self, ftp: ftplib.FTP, op: str, full: str, path: str,
                   refusal: Unexplained) -> TransportError:
        """Why MKD, RMD, DELE or RETR was refused when the reply does not say: asked of the
        server.

        Probed by name (CWD, SIZE or MLST), not found in a listing: vsftpd leaves dot
        files out of LIST.
        """
        parent = posixpath.dirname(full)
        if op in ("delete", "read"):  # vsftpd's one reply whether the file is missing or kept
            try:
                entry = self._stat(ftp, full, path)
            except NotFound:
                return NotFound(f"{op} {path!r}: no such file")
            if entry.is_dir:
                return NotFound(f"{op} {path!r}: a folder, not a file")
            kept = "is there but the server will not read it" if op == "read" else "is still there"
            return Unexplained(f"{refusal} (the file {kept})")
        if op == "make_dir":
            if self._exists(ftp, full, path):
                return Exists(f"{op} {path!r}: already there")
            if not self._is_dir(ftp, parent):
                return NotFound(f"{op} {path!r}: the folder {parent!r} is not there")
            return refusal
        if not self._is_dir(ftp, full):
            return NotFound(f"{op} {path!r}: no such folder")
        if self._holds_anything(ftp, full, path):
            return NotEmpty(f"{op} {path!r}: the folder is not empty")
        return Unexplained(f"{refusal} (the folder lists empty)")

    def _remove_part(self, part: str) -> str | None:
        """Remove a failed write's temporary file: None once it is gone, else why it is not.

        The write's connection may be dead (a server that refused the data connection
        may hang up too): a failure of the link is tried again on a new connection.
        """
        why = "not tried"
        for fresh in (False, True):
            try:
                with self._session(fresh=fresh) as ftp, contextlib.suppress(NotFound):
                    self._delete(ftp, part, part)
                return None
            except Transient as exc:
                why = str(exc)
            except TransportError as exc:
                return str(exc)
        return why

    def _remove_parts_left(self, ftp: ftplib.FTP, full: str) -> None:
        """After a write placed `full`: remove the temporary files earlier writes of it in
        this process left, and, once every `_longest_write_s`, those in its folder nobody
        wrote to for that long (left by a write of another process, or a killed one); never
        one being written. Best effort: the file is in place whatever comes of it."""
        key = self.options.connection_key()
        left, sweep = _LEFT.take(key, full, posixpath.dirname(full),
                                 sweep_every_s=self._longest_write_s())
        try:
            if sweep:
                left |= self._stale_parts(ftp, full)
            for part in sorted(left):
                with contextlib.suppress(NotFound):
                    self._delete(ftp, part, part)
                left.discard(part)
        except Exception as exc:  # whatever it is, the file placed stays placed
            for part in left:  # tried again at the file's next write
                _LEFT.add(key, full, part)
            if not isinstance(exc, Permanent):
                ftp.close()  # its replies may be out of step: not kept

    def _longest_write_s(self) -> float:
        """The longest a write goes on: its bytes within `transfer_timeout_s`, then the last
        piece, the server's answer, the second look and the rename, `timeout_s` each."""
        return self.options.transfer_timeout_s + 5 * self.options.timeout_s

    def _stale_parts(self, ftp: ftplib.FTP, full: str) -> set[str]:
        """The temporary files in `full`'s folder unchanged for `_longest_write_s`, by the
        server's clock: the time it gives `full`, just written (a machine's clock is its own).
        Those a server lists (MLSD does, and vsftpd's and ProFTPD's `LIST -a`)."""
        folder, name = posixpath.split(full)
        entries = self._list_all(ftp, folder, folder)
        written = next((e.mtime for e in entries if e.name == name), None)
        if written is None:
            return set()
        unchanged_s = self._longest_write_s() + (0 if self._has_mlsd else 60)  # LIST: minutes
        return {posixpath.join(folder, e.name) for e in entries
                if e.name.startswith(PART_PREFIX) and e.mtime is not None
                and written - e.mtime > unchanged_s}


def _absolute(path: str) -> str:
    """The server path of a transport path; BadPath for what the server cannot take."""
    if any(c in path for c in "\r\n\0"):
        raise BadPath(f"control characters in {path!r}")
    parts = [p for p in path.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise BadPath(f"path leaves the server's top: {path!r}")
    return "/" + "/".join(parts)


def _visible(entries: list[Entry]) -> list[Entry]:
    return sorted((e for e in entries if not e.name.startswith(PART_PREFIX)),
                  key=lambda e: e.name)
