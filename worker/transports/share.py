"""A shared folder: mounted on the worker host (`path`), or SMB2/3 straight from the worker.

Both flavours write to `.dncq-part-<uuid>` first and rename it into place with a rename
that refuses to replace, so a file appears under its name only when complete.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import functools
import os
import posixpath
import stat as stat_mode
import sys
import uuid
from collections.abc import Iterable, Iterator
from typing import Any, BinaryIO, ClassVar, Protocol

from pydantic import Field, SecretStr, model_validator

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
    TransportError,
    TransportOptions,
    Unsupported,
)

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


class ShareOptions(TransportOptions):
    """Options of a shared folder (fleet file `options:`): `path`, or `server` and `share`."""

    path: str | None = None
    """Mount point of the share on the worker host (absolute)."""
    server: str | None = None
    """SMB server host name or address, for SMB straight from the worker."""
    share: str | None = None
    """SMB share name on `server`."""
    port: int = Field(default=445, gt=0, lt=65536)
    """SMB server TCP port."""
    user: str | None = None
    """SMB user name; None for Kerberos from the worker's ticket."""
    password: SecretStr | None = None
    """SMB password."""
    subfolder: str = ""
    """SMB folder below the share's top that this machine's paths start from."""
    connect_timeout_s: float = Field(default=10.0, gt=0)
    """Time allowed for the SMB connection to be set up."""

    @model_validator(mode="after")
    def _one_flavour(self) -> ShareOptions:
        if (self.path is None) == (self.server is None):
            raise ValueError("give either path (a mounted folder) or server and share (SMB)")
        if self.path is not None:
            if not os.path.isabs(self.path):
                raise ValueError("path must be absolute")
            smb_only = {"server", "share", "port", "user", "password", "subfolder"}
            if given := sorted(smb_only & self.model_fields_set):
                raise ValueError(f"{', '.join(given)} only apply to SMB (server and share)")
        elif not self.share:
            raise ValueError("share is required with server")
        return self


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
    def close(self) -> None: ...


class ShareTransport(NoMachineControl):
    """A shared folder, mounted on the worker host or reached over SMB2/3."""

    capabilities: ClassVar[Capabilities] = Capabilities(folders=True, make_dirs=True)
    own_storage: ClassVar[bool] = False
    server_row: ClassVar[str | None] = "Shared folder"

    def __init__(self, options: ShareOptions) -> None:
        self.options = options
        self._folder: _Folder = (
            _MountedFolder(options.path) if options.path is not None else _SmbFolder(options)
        )

    @contextlib.contextmanager
    def _mapped(self, path: str) -> Iterator[None]:
        """Turn the flavour's native errors into the transport's, once, here."""
        try:
            yield
        except TransportError:
            raise
        except Exception as exc:
            error = _error_class(exc)
            if error is None:
                raise
            if error is NotFound and isinstance(self._folder, _MountedFolder):
                if not os.path.isdir(self._folder.top):
                    raise ConnectFailed(f"share not mounted at {self._folder.top}") from exc
            raise error(f"{path or '(top)'}: {exc}") from exc

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
            with contextlib.suppress(Exception):  # every byte is in, or the read failed anyway
                f.close()

    def write(
        self, path: str, chunks: Iterable[bytes], *, progress: ProgressFn | None = None
    ) -> int:
        target = _checked(path)
        part = posixpath.join(posixpath.dirname(target), f"{PART_PREFIX}{uuid.uuid4().hex}")
        with self._mapped(path):
            if self._exists(target):
                raise Exists(path)  # fail before moving any bytes
            f = self._folder.create(part)
        placed = False
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
                with contextlib.suppress(Exception):
                    f.close()
                raise
            with self._mapped(path):
                f.close()  # sends the last bytes
                self._folder.rename_noreplace(part, target)  # never overwrite
            placed = True
            return done
        finally:
            if not placed:
                with contextlib.suppress(Exception):  # the link may be gone: best effort
                    self._folder.remove(part)

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
        with contextlib.suppress(Exception):  # closing a dead connection is not an error
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
    if isinstance(exc, TimeoutError):
        return TimedOut
    if smb is not None and isinstance(exc, smb.SMBException):
        return TransportError  # a failure of the server we have no finer class for
    return None


class _MountedFolder:
    """A folder on the worker host's file system, usually a mounted share.

    Links are followed only while they stay inside the folder: a link out of it is neither
    listed nor reached (20010), so the machine's root is the limit whatever the share holds.
    Only folders and regular files exist here; a pipe or a device is never listed or opened
    (opening a pipe would wait for a writer, holding the machine).
    """

    def __init__(self, top: str) -> None:
        self.top = top
        self._real_top = os.path.realpath(top)

    def _inside(self, full: str) -> bool:
        real = os.path.realpath(full)
        return real == self._real_top or real.startswith(self._real_top + os.sep)

    def _full(self, path: str) -> str:
        full = os.path.join(self.top, path) if path else self.top
        if not self._inside(full):
            raise PermissionError(errno.EACCES, "a link out of the share", path)
        return full

    def list(self, path: str) -> list[Entry]:
        entries = []
        with os.scandir(self._full(path)) as children:
            for child in children:
                try:
                    st = child.stat()
                except OSError as exc:  # deleted meanwhile, a broken link, a link loop
                    if exc.errno in (errno.ENOENT, errno.ELOOP):
                        continue
                    raise
                if not (stat_mode.S_ISDIR(st.st_mode) or stat_mode.S_ISREG(st.st_mode)):
                    continue
                if child.is_symlink() and not self._inside(child.path):
                    continue
                is_dir = stat_mode.S_ISDIR(st.st_mode)
                entries.append(Entry(child.name, is_dir, None if is_dir else st.st_size,
                                     st.st_mtime))
        return entries

    def stat(self, path: str) -> Entry:
        st = os.stat(self._full(path))
        is_dir = stat_mode.S_ISDIR(st.st_mode)
        if not (is_dir or stat_mode.S_ISREG(st.st_mode)):
            raise FileNotFoundError(errno.ENOENT, "neither a file nor a folder", path)
        return Entry(posixpath.basename(path), is_dir, None if is_dir else st.st_size,
                     st.st_mtime)

    def open_read(self, path: str) -> tuple[BinaryIO, int]:
        # Non-blocking, so that a pipe answers at once instead of waiting for a writer;
        # the flag changes nothing for a regular file.
        fd = os.open(self._full(path), os.O_RDONLY | os.O_NONBLOCK)
        st = os.fstat(fd)
        if not stat_mode.S_ISREG(st.st_mode):
            os.close(fd)
            raise FileNotFoundError(errno.ENOENT, "not a regular file", path)
        return os.fdopen(fd, "rb"), st.st_size  # closed by the reading generator

    def create(self, path: str) -> BinaryIO:
        return open(self._full(path), "xb")  # closed by the writer

    def rename_noreplace(self, src: str, dst: str) -> None:
        src, dst = self._full(src), self._full(dst)
        try:
            os.link(src, dst)  # fails if the name is taken
        except OSError as exc:
            if exc.errno not in _NO_HARD_LINKS:
                raise
            _rename_noreplace(src, dst)  # mounts without hard links (many CIFS, FAT)
        else:
            os.unlink(src)

    def remove(self, path: str) -> None:
        os.unlink(self._full(path))

    def mkdir(self, path: str) -> None:
        os.mkdir(self._full(path))

    def rmdir(self, path: str) -> None:
        os.rmdir(self._full(path))

    def close(self) -> None:
        pass


_NO_HARD_LINKS = {errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EMLINK, errno.ENOSYS}
_RENAME_NOREPLACE = 1  # linux/fs.h
_AT_FDCWD = -100


def _refuse_part(path: str) -> None:
    """A half-written file is not there, for anyone who asks for it by name."""
    if posixpath.basename(path).startswith(PART_PREFIX):
        raise NotFound(path)


@functools.cache
def _renameat2() -> Any:
    """libc's renameat2 (glibc 2.28+), looked up once; None where there is none."""
    return getattr(ctypes.CDLL(None, use_errno=True), "renameat2", None)


def _rename_noreplace(src: str, dst: str) -> None:
    """Rename that fails with EEXIST when `dst` exists (Linux renameat2)."""
    renameat2 = _renameat2()
    if sys.platform == "linux" and renameat2 is not None:
        if renameat2(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst),
                     _RENAME_NOREPLACE) == 0:
            return
        err = ctypes.get_errno()
        if err not in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
            raise OSError(err, os.strerror(err), dst)
    # Last resort where the file system has neither: a check, then a rename that could
    # replace a file that appeared between the two.
    if os.path.lexists(dst):
        raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), dst)
    os.rename(src, dst)


class _SmbFolder:
    """A share reached over SMB2/3 with smbprotocol's `smbclient`, on connections of its own."""

    def __init__(self, options: ShareOptions) -> None:
        try:
            import smbclient
        except ImportError as exc:
            raise Unsupported("SMB needs the smbprotocol package (pip install dncq[smb])") from exc
        self._smb: Any = smbclient
        self._server = options.server or ""
        self._cache: dict[str, Any] = {}  # this transport's connections, closed with it
        self._session: dict[str, Any] = {
            "username": options.user,
            "password": options.password.get_secret_value() if options.password else None,
            "port": options.port,
            "connection_timeout": options.connect_timeout_s,
            "connection_cache": self._cache,
        }
        below = options.subfolder.strip("/").replace("/", "\\")
        self._top = f"\\\\{self._server}\\{options.share}" + (f"\\{below}" if below else "")

    def _full(self, path: str) -> str:
        """The UNC path, after making sure the session is up (reconnects after a drop)."""
        if "\\" in path:
            raise BadPath(f"a backslash is a separator on SMB: {path!r}")
        try:
            self._smb.register_session(self._server, **self._session)
        except ValueError as exc:  # what smbprotocol raises when the TCP connect fails
            raise ConnectFailed(f"{self._server}:{self._session['port']}: {exc}") from exc
        return self._top + ("\\" + path.replace("/", "\\") if path else "")

    def list(self, path: str) -> list[Entry]:
        entries = []
        for child in self._smb.scandir(self._full(path), **self._session):
            info = child.smb_info
            is_dir = child.is_dir(follow_symlinks=False)
            entries.append(Entry(child.name, is_dir, None if is_dir else info.end_of_file,
                                 info.last_write_time.timestamp()))
        return entries

    def stat(self, path: str) -> Entry:
        st = self._smb.stat(self._full(path), **self._session)
        is_dir = stat_mode.S_ISDIR(st.st_mode)
        return Entry(posixpath.basename(path), is_dir, None if is_dir else st.st_size,
                     st.st_mtime)

    def open_read(self, path: str) -> tuple[BinaryIO, int]:
        full = self._full(path)
        size = self._smb.stat(full, **self._session).st_size
        return self._smb.open_file(full, mode="rb", **self._session), size

    def create(self, path: str) -> BinaryIO:
        # "x": the server creates the file only if the name is free (FILE_CREATE).
        f: BinaryIO = self._smb.open_file(self._full(path), mode="xb",
                                          **self._session)
        return f

    def rename_noreplace(self, src: str, dst: str) -> None:
        # smbclient.rename sets ReplaceIfExists = 0: the server refuses a taken name. It opens
        # the target first (for DFS), which Samba refuses on a file without an execute bit.
        try:
            self._smb.rename(self._full(src), self._full(dst), **self._session)
        except OSError as exc:
            if exc.errno != errno.EEXIST and self._smb.path.lexists(self._full(dst),
                                                                   **self._session):
                raise FileExistsError(errno.EEXIST, "name taken", dst) from exc
            raise

    def remove(self, path: str) -> None:
        self._smb.remove(self._full(path), **self._session)

    def mkdir(self, path: str) -> None:
        self._smb.mkdir(self._full(path), **self._session)

    def rmdir(self, path: str) -> None:
        self._smb.rmdir(self._full(path), **self._session)

    def close(self) -> None:
        self._smb.reset_connection_cache(fail_on_error=False, connection_cache=self._cache)
