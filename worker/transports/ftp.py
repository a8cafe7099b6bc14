"""The `ftp` transport: a machine's FTP server, or an FTP file server in front of it.

Standard-library ftplib, plain or explicit FTPS (worker.transports.ftp_link opens the
connections); connections are opened lazily and kept for the next call until `close()`,
which hands them to the process's kept connections (worker.transports.ftp_pool) for the
next job's transport of the same server and account. The server's replies map onto the
error tree in worker.transports.ftp_errors, the one place that knows them.
"""

from __future__ import annotations

import contextlib
import ftplib
import posixpath
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
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
    Unsupported,
    byte_count,
)
from worker.transports.ftp_errors import Unexplained, translated
from worker.transports.ftp_link import FtpOptions, alive, finish, open_link, quiet
from worker.transports.ftp_listing import (
    may_name_a_link,
    mdtm_seconds,
    names_a_link,
    parse_list_line,
    parse_mlsx,
)
from worker.transports.ftp_pool import KEPT, quit_quietly

# A kept connection idle longer than this, or on which the server sent something unasked
# (a 421 before hanging up), is probed with NOOP before use.
_IDLE_CHECK_S = 5.0


class FtpTransport(NoMachineControl):
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
                    total = _count(ftp.size, full)
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
                with translated("read", path):
                    finish(ftp, conn)

    def write(
        self, path: str, chunks: Iterable[bytes], *, progress: ProgressFn | None = None
    ) -> int:
        full = _absolute(path)
        folder, name = posixpath.split(full)
        if not name:
            raise BadPath(f"no file name in {path!r}")
        part = posixpath.join(folder, f"{PART_PREFIX}{uuid.uuid4().hex}")
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
        except BaseException as exc:
            why_left = self._remove_part(part)
            if why_left is None:
                raise
            left = f"the temporary file {part!r} was left behind ({why_left})"
            if isinstance(exc, TransportError):  # its message is the target's statusMsg
                raise type(exc)(f"{exc}; {left}") from exc
            exc.add_note(left)
            raise
        return done

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

    def _list(self, ftp: ftplib.FTP, full: str, path: str) -> list[Entry]:
        """A folder's entries as the server lists them, temporary files too; MLSD or LIST."""
        if self._has_mlsd is not False:
            try:
                lines = self._lines(ftp, f"MLSD {full}", "list_dir", path)
                self._has_mlsd = True
                return self._followed(ftp, full, [(line, parse_mlsx(line)) for line in lines])
            except Unsupported:
                self._has_mlsd = False
        return self._list_legacy(ftp, full, path)

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

    def _holds_anything(self, ftp: ftplib.FTP, full: str, path: str) -> bool:
        """Whether a folder lists any entry, dot files too where the server shows them."""
        if self._list(ftp, full, path):
            return True
        with contextlib.suppress(Permanent):  # `-a` is vsftpd's and ProFTPD's, not everyone's
            lines = self._lines(ftp, f"LIST -a {full}", "list_dir", path)
            return any(e is not None and e.name not in (".", "..")
                       for e in map(parse_list_line, lines))
        return False

    def _lines(self, ftp: ftplib.FTP, command: str, op: str, path: str) -> list[str]:
        """A listing command's data, as lines in the server's encoding."""
        deadline = Deadline(self.options.transfer_timeout_s)
        with translated(op, path):
            conn = ftp.transfercmd(command)
            with conn:
                data = bytearray()
                while block := conn.recv(CHUNK_BYTES):
                    deadline.check(f"{op} {path!r}")
                    data += block
                finish(ftp, conn)
        # surrogateescape: a name the encoding cannot take still lists, and gives BadPath later
        text = bytes(data).decode(self.options.encoding, "surrogateescape")
        return [line for line in text.splitlines() if line.strip()]

    def _list_legacy(self, ftp: ftplib.FTP, full: str, path: str) -> list[Entry]:
        """LIST parsed (Unix or DOS style); NLST and CWD probes if the format is unknown."""
        self._require_dir(ftp, full, path)  # LIST of a missing folder may just be empty
        lines = self._lines(ftp, f"LIST {full}", "list_dir", path)
        parsed = [(line, parse_list_line(line)) for line in lines
                  if not line.startswith("total ")]
        if all(e is not None for _, e in parsed):
            return [e for e in self._followed(ftp, full, parsed) if e.name not in (".", "..")]
        names = {posixpath.basename(n) for n in self._lines(ftp, f"NLST {full}", "list_dir", path)}
        return [Entry(n, self._is_dir(ftp, posixpath.join(full, n))) for n in sorted(names)
                if n not in (".", "..")]

    def _stat(self, ftp: ftplib.FTP, full: str, path: str) -> Entry:
        name = posixpath.basename(full)
        if self._has_mlst is not False:
            try:
                with translated("stat", path):
                    reply = ftp.sendcmd(f"MLST {full}")
                self._has_mlst = True
                facts = reply.splitlines()[1].strip() if "\n" in reply else ""
                line = f"{facts.partition(' ')[0]} {name}"
                entry = parse_mlsx(line)
                if entry is None:
                    raise NotFound(path)
                if entry.is_dir or not may_name_a_link(line):
                    return entry
            except Unsupported:
                self._has_mlst = False
        return self._stat_followed(ftp, full, path)  # no MLST, or a link's own facts in it

    def _stat_followed(self, ftp: ftplib.FTP, full: str, path: str) -> Entry:
        """SIZE, MDTM or CWD's answer: about what a link leads to, not the link."""
        name = posixpath.basename(full)
        try:
            with translated("stat", path):
                size = _count(ftp.size, full)
        except NotFound:
            if self._is_dir(ftp, full):
                return Entry(name, True)
            raise
        mtime = None
        with contextlib.suppress(Permanent), translated("stat", path):
            mtime = mdtm_seconds(ftp.sendcmd(f"MDTM {full}")[4:].strip())
        return Entry(name, False, size, mtime)

    def _followed(self, ftp: ftplib.FTP, full: str,
                  parsed: list[tuple[str, Entry | None]]) -> list[Entry]:
        """The entries a folder's listing lines give, a link's as what it leads to; a link
        that leads nowhere is left out, since there is nothing there to read."""
        entries = []
        for line, entry in parsed:
            if entry is not None and names_a_link(line):
                target = posixpath.join(full, entry.name)
                try:
                    entry = self._stat_followed(ftp, target, target)
                except NotFound:
                    continue
            if entry is not None:
                entries.append(entry)
        return entries

    def _exists(self, ftp: ftplib.FTP, full: str, path: str) -> bool:
        try:
            self._stat(ftp, full, path)
        except NotFound:
            return False
        return True

    def _is_dir(self, ftp: ftplib.FTP, full: str) -> bool:
        try:
            with translated("stat", full):
                ftp.cwd(full)
        except NotFound:
            return False
        return True

    def _require_dir(self, ftp: ftplib.FTP, full: str, path: str) -> None:
        if not self._is_dir(ftp, full):
            raise NotFound(path)

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


def _count(size: Callable[[str], int | None], full: str) -> int | None:
    """SIZE's answer, or None when the server's answer is not a count of bytes."""
    try:
        return byte_count(size(full))
    except ValueError:  # "213 abc"
        return None
