"""A share reached over SMB2/3 from the worker: the `server`/`share` flavour of the share
transport (smbprotocol's `smbclient`, an optional dependency)."""

from __future__ import annotations

import contextlib
import errno
import posixpath
import stat as stat_mode
import threading
from collections.abc import Iterator
from typing import Any, BinaryIO

from worker.transports.base import BadPath, ConnectFailed, Entry, TimedOut, Unsupported
from worker.transports.share_options import SMB_MISSING, ShareOptions


class SmbFolder:
    """A share reached over SMB2/3 with smbprotocol's `smbclient`, on connections of its own."""

    def __init__(self, options: ShareOptions) -> None:
        try:
            import smbclient
        except ImportError as exc:
            raise Unsupported(SMB_MISSING) from exc
        self._smb: Any = smbclient
        self._server = options.server or ""
        self._timeout_s = options.timeout_s
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

    @contextlib.contextmanager
    def bounded(self) -> Iterator[None]:
        """The block, cut off with TimedOut when the server has not answered in `timeout_s`.

        smbclient waits for an answer without end (a stalled server held the worker until
        its keep-alive gave up, 20 minutes on); ending the connection ends the wait.
        """
        cut = threading.Event()

        def give_up() -> None:
            cut.set()
            for key, connection in list(self._cache.items()):
                # Out of the cache too: the next call connects afresh, also when this one
                # fired as the block's last answer came.
                self._cache.pop(key, None)
                connection.disconnect(close=False)  # no goodbye: the server does not answer

        timer = threading.Timer(self._timeout_s, give_up)
        timer.daemon = True
        timer.start()
        try:
            yield
        except Exception as exc:
            if cut.is_set():
                raise TimedOut(f"{self._server}: no answer in {self._timeout_s:g} s "
                               "(timeout_s)") from exc
            raise
        finally:
            timer.cancel()

    def free_bytes(self) -> int | None:
        """What the share's volume has free for this user (SMB2 FileFsFullSizeInformation)."""
        try:
            volume = self._smb.stat_volume(self._top, **self._session)
        except Exception:  # an old server without the query: it does not say
            return None
        return int(volume.caller_available_size)

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
