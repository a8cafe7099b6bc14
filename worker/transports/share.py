"""A shared folder: mounted on the worker host (`path`), or SMB2/3 straight from the worker.

The flavours (worker.transports.mounted_folder, worker.transports.smb_folder) do the
native operations; this module checks paths and maps their errors. Both write to
`.dncq-part-<digest of the name>-<uuid>` first and rename it into place with a rename that
refuses to replace, so a file appears under its name only when complete.
"""

from __future__ import annotations

import contextlib
import errno
import os
import posixpath
import sys
import traceback
import uuid
from collections.abc import Iterable, Iterator
from typing import BinaryIO, ClassVar, Protocol

from worker.transports.base import (
    CHUNK_BYTES,
    PART_PREFIX,
    BadPath,
    Busy,
    Capabilities,
    ConnectFailed,
    Dropped,
    Entry,
    Exists,
    NoMachineControl,
    NotEmpty,
    NotFound,
    Offline,
    PermissionDenied,
    ProgressFn,
    TimedOut,
    Transient,
    TransportError,
    parts_of,
)
from worker.transports.left_parts import LeftParts
from worker.transports.mounted_folder import MountedFolder
from worker.transports.share_options import ShareOptions
from worker.transports.smb_folder import SmbFolder

# A part unchanged this long has no writer at it: a write's pieces follow each other
# without pause, each within `timeout_s`. (Samba gives an open file the time of its first
# write, but refuses to delete a file another connection has open: a writer's part stays.)
STILL_WRITING_S = 600.0

# The temporary files this process's writes left, by share: the file's next write removes
# them.
_LEFT = LeftParts()

# The folder's failures as the transport's errors, by errno (local disks, network mounts,
# and smbclient's SMBOSError, which sets errno for the NT statuses it knows).
_BY_ERRNO: dict[int, type[TransportError]] = {
    errno.ENOENT: NotFound,
    errno.ENOTDIR: NotFound,
    errno.EISDIR: NotFound,  # a folder where a file was asked for
    errno.EEXIST: Exists,
    errno.ENOTEMPTY: NotEmpty,
    errno.EACCES: PermissionDenied,
    errno.EPERM: PermissionDenied,
    errno.EROFS: PermissionDenied,
    errno.ENOSPC: PermissionDenied,  # a full disk refuses the file, as an FTP server's 552
    errno.EDQUOT: PermissionDenied,
    errno.EFBIG: PermissionDenied,
    errno.ELOOP: NotFound,  # a link that never ends names no file
    errno.ENAMETOOLONG: BadPath,
    errno.EINVAL: BadPath,
    errno.EILSEQ: BadPath,  # a name the mount's character set cannot hold
    errno.ETIMEDOUT: TimedOut,
    errno.ECONNREFUSED: ConnectFailed,
    errno.EHOSTUNREACH: ConnectFailed,
    errno.ENETUNREACH: ConnectFailed,
    errno.EHOSTDOWN: Offline,
    errno.ECONNRESET: Dropped,
    errno.ECONNABORTED: Dropped,
    errno.EPIPE: Dropped,
    errno.ENOTCONN: Dropped,
    errno.ESTALE: Dropped,  # a network mount lost its server
    errno.EIO: Dropped,  # what a network mount reports when the link breaks mid-transfer
    errno.EBUSY: Busy,
}

# NT statuses (MS-ERREF 2.3) that smbclient leaves without an errno, or maps too coarsely.
_BY_NT_STATUS: dict[int, type[TransportError]] = {
    0xC0000022: PermissionDenied,  # ACCESS_DENIED
    0xC0000061: PermissionDenied,  # PRIVILEGE_NOT_HELD
    0xC000006A: PermissionDenied,  # WRONG_PASSWORD
    0xC000006D: PermissionDenied,  # LOGON_FAILURE
    0xC0000071: PermissionDenied,  # PASSWORD_EXPIRED
    0xC0000121: PermissionDenied,  # CANNOT_DELETE
    0xC0000043: Busy,  # SHARING_VIOLATION: another client has the file open
    0xC0000056: NotFound,  # DELETE_PENDING
    0xC00000CC: NotFound,  # BAD_NETWORK_NAME: no such share
    0xC0000033: BadPath,  # OBJECT_NAME_INVALID
    0xC0000039: BadPath,  # OBJECT_PATH_INVALID
    0xC000003B: BadPath,  # OBJECT_PATH_SYNTAX_BAD
    0xC00000B5: TimedOut,  # IO_TIMEOUT
    0xC0000203: Dropped,  # USER_SESSION_DELETED
    0xC00000C9: Dropped,  # NETWORK_NAME_DELETED
    0xC000009A: Busy,  # INSUFFICIENT_RESOURCES
    0xC0000205: Busy,  # INSUFF_SERVER_RESOURCES
    0xC0000466: Offline,  # SERVER_UNAVAILABLE
}


class _Folder(Protocol):
    """What a flavour does natively; it raises its own errors, the transport maps them."""

    def list(self, path: str) -> list[Entry]: ...
    def stat(self, path: str) -> Entry: ...
    def open_read(self, path: str) -> tuple[BinaryIO, int]: ...
    def create(self, path: str) -> BinaryIO: ...
    def rename_noreplace(self, src: str, dst: str) -> None: ...
    def remove(self, path: str) -> None: ...
    def mkdir(self, path: str) -> None: ...
    def rmdir(self, path: str) -> None: ...
    def free_bytes(self) -> int | None: ...
    def close(self) -> None: ...
    def bounded(self) -> contextlib.AbstractContextManager[None]: ...


class ShareTransport(NoMachineControl):
    """A shared folder, mounted on the worker host or reached over SMB2/3."""

    capabilities: ClassVar[Capabilities] = Capabilities(folders=True, make_dirs=True)
    own_storage: ClassVar[bool] = False
    server_row: ClassVar[str | None] = "Shared folder"

    def __init__(self, options: ShareOptions) -> None:
        self.options = options
        self._folder: _Folder = (
            MountedFolder(options.path) if options.path is not None else SmbFolder(options)
        )

    @contextlib.contextmanager
    def _mapped(self, path: str) -> Iterator[None]:
        """Turn the flavour's native errors into the transport's, once, here; the block is
        bounded by the flavour's timeout."""
        try:
            with self._folder.bounded():
                yield
        except TransportError:
            raise
        except Exception as exc:
            error = _error_class(exc)
            if error is None:
                raise
            if error is NotFound and isinstance(self._folder, MountedFolder):
                if not os.path.isdir(self._folder.top):
                    raise ConnectFailed(f"share not mounted at {self._folder.top}") from exc
            raise error(f"{path or '(top)'}: {exc}") from exc

    def free_bytes(self) -> int | None:
        with self._folder.bounded():
            return self._folder.free_bytes()

    def list_dir(self, path: str) -> list[Entry]:
        with self._mapped(path):
            entries = self._folder.list(_checked(path, top_ok=True))
        return sorted((e for e in entries if not e.name.startswith(PART_PREFIX)),
                      key=lambda e: e.name)

    def stat(self, path: str) -> Entry:
        _refuse_part(path)
        with self._mapped(path):
            return self._folder.stat(_checked(path, top_ok=True))

    def read(self, path: str, *, progress: ProgressFn | None = None) -> Iterator[bytes]:
        _refuse_part(path)
        with self._mapped(path):
            f, total = self._folder.open_read(_checked(path))
        return self._chunks(path, f, total, progress)

    def _chunks(
        self, path: str, f: BinaryIO, total: int, progress: ProgressFn | None
    ) -> Iterator[bytes]:
        try:
            done = 0
            while True:
                with self._mapped(path):
                    chunk = f.read(CHUNK_BYTES)
                if not chunk:
                    return
                done += len(chunk)
                yield chunk
                if progress:
                    progress(done, total)
        finally:
            # every byte is in, or the read failed anyway
            with contextlib.suppress(Exception), self._folder.bounded():
                f.close()

    def write(
        self, path: str, chunks: Iterable[bytes], *, progress: ProgressFn | None = None
    ) -> int:
        target = _checked(path)
        folder, name = posixpath.split(target)
        part = posixpath.join(folder, f"{parts_of(name)}{uuid.uuid4().hex}")
        with self._mapped(path):
            if self._exists(target):
                raise Exists(path)  # fail before moving any bytes
            f = self._folder.create(part)
        try:
            done = 0
            try:
                for chunk in chunks:
                    with self._mapped(path):
                        f.write(chunk)
                    done += len(chunk)
                    if progress:
                        progress(done, None)
            except BaseException:
                with contextlib.suppress(Exception), self._folder.bounded():
                    f.close()
                raise
            with self._mapped(path):
                f.close()  # sends the last bytes
                self._folder.rename_noreplace(part, target)  # never overwrite
        except BaseException as exc:
            why_left = self._remove_part(part)
            if why_left is None:
                raise
            _LEFT.add(self._server_key(), target, part)
            left = f"the temporary file {part!r} was left behind ({why_left})"
            if isinstance(exc, TransportError):  # its message is the target's statusMsg
                raise type(exc)(f"{exc}; {left}") from exc
            exc.add_note(left)
            raise
        self._remove_parts_left(target)
        return done

    def _remove_part(self, part: str) -> str | None:
        """Remove a failed write's temporary file: None once it is gone, else why it is not.

        The write's connection may be dead: a failure of the link is tried again on a new one.
        """
        why = "not tried"
        for _ in range(2):
            try:
                self._remove(part)
                return None
            except Transient as exc:
                why = str(exc)
                self.close()  # the next try connects afresh
            except TransportError as exc:
                return str(exc)
        return why

    def _remove_parts_left(self, target: str) -> None:
        """After a write placed `target`: remove the temporary files earlier writes of it in
        this process left, and, once every `STILL_WRITING_S`, those in its folder nobody
        wrote to for that long (left by a write of another process, or a killed one). Best
        effort: the file is in place whatever comes of it."""
        key, folder = self._server_key(), posixpath.dirname(target)
        left, sweep = _LEFT.take(key, target, folder, sweep_every_s=STILL_WRITING_S)
        try:
            if sweep:
                left |= self._stale_parts(target)
            for part in sorted(left):
                with contextlib.suppress(Busy):  # over SMB: open, a writer is at it after all
                    self._remove(part)
                left.discard(part)
        except Exception:  # whatever it is, the file placed stays placed
            for part in left:  # tried again at the file's next write
                _LEFT.add(key, target, part)

    def _stale_parts(self, target: str) -> set[str]:
        """The temporary files in `target`'s folder unchanged for `STILL_WRITING_S`, by the
        share's clock: the time it gives `target`, just written."""
        folder, name = posixpath.split(target)
        with self._mapped(folder):
            entries = self._folder.list(folder)
        written = next((e.mtime for e in entries if e.name == name), None)
        if written is None:
            return set()
        return {posixpath.join(folder, e.name) for e in entries
                if e.name.startswith(PART_PREFIX) and e.mtime is not None
                and written - e.mtime > STILL_WRITING_S}

    def remove_parts_of(self, path: str) -> None:
        """Remove the temporary files earlier writes of `path`, of any process, left in its
        folder, now that `path` is in place: none of them can be placed any more (a write
        renames without replacing), and over SMB one a writer still has open is refused by
        the server. Best effort: `path` stays placed whatever comes of it."""
        folder, name = posixpath.split(_checked(path))
        with contextlib.suppress(Exception):
            with self._mapped(folder):
                entries = self._folder.list(folder)
            for entry in entries:
                if entry.name.startswith(parts_of(name)):
                    with contextlib.suppress(Busy):
                        self._remove(posixpath.join(folder, entry.name))

    def _remove(self, part: str) -> None:
        """Delete a temporary file, if it is still there."""
        with contextlib.suppress(NotFound), self._mapped(part):
            self._folder.remove(part)

    def _server_key(self) -> tuple[object, ...]:
        """The share this transport writes to, as every transport of the process names it."""
        o = self.options
        return (o.path, o.server, o.port, o.share, o.subfolder.strip("/"), o.user)

    def _exists(self, path: str) -> bool:
        try:
            self._folder.stat(path)
        except OSError as exc:
            if exc.errno == errno.ENOENT:
                return False
            raise
        return True

    def delete(self, path: str) -> None:
        with self._mapped(path):
            target = _checked(path)
            if self._folder.stat(target).is_dir:
                raise NotFound(f"{path} is a folder")
            self._folder.remove(target)

    def make_dir(self, path: str) -> None:
        with self._mapped(path):
            self._folder.mkdir(_checked(path))

    def remove_dir(self, path: str) -> None:
        with self._mapped(path):
            self._folder.rmdir(_checked(path))

    def close(self) -> None:
        # closing a dead connection is not an error
        with contextlib.suppress(Exception), self._folder.bounded():
            self._folder.close()


def _checked(path: str, *, top_ok: bool = False) -> str:
    """The POSIX path relative to the share's top, refused if it could leave it."""
    parts = path.split("/") if path else []
    if path.startswith("/") or any(p in ("", ".", "..") or "\0" in p for p in parts):
        raise BadPath(f"not a relative path inside the share: {path!r}")
    if not parts and not top_ok:
        raise BadPath("the share's top is not a file")
    return path


def _error_class(exc: BaseException) -> type[TransportError] | None:
    """The transport error for a native one, or None when it is unexpected."""
    smb = sys.modules.get("smbprotocol.exceptions")  # loaded only once SMB is in use
    if smb is not None and isinstance(exc, smb.SMBException):
        status = getattr(exc, "ntstatus", None) or getattr(exc, "status", None)
        if status in _BY_NT_STATUS:
            return _BY_NT_STATUS[status]
        if isinstance(exc, smb.SMBConnectionClosed):
            return Dropped
        if isinstance(exc, smb.SMBAuthenticationError):
            return PermissionDenied
    if isinstance(exc, OSError) and exc.errno in _BY_ERRNO:
        return _BY_ERRNO[exc.errno]
    if isinstance(exc, OSError) and exc.errno == errno.EBADF and _raised_in_smb(exc):
        return Dropped  # a send on the socket smbprotocol's reader closed as the server went
    if isinstance(exc, TimeoutError):
        return TimedOut
    if smb is not None and isinstance(exc, smb.SMBException):
        return TransportError  # a failure of the server we have no finer class for
    return None


def _raised_in_smb(exc: BaseException) -> bool:
    """Whether `exc` was raised inside smbprotocol (its socket), not on a mounted folder."""
    frames = traceback.extract_tb(exc.__traceback__)
    return bool(frames) and "smbprotocol" in frames[-1].filename


def _refuse_part(path: str) -> None:
    """A half-written file is not there, for anyone who asks for it by name."""
    if posixpath.basename(path).startswith(PART_PREFIX):
        raise NotFound(path)
