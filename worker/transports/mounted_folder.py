"""A folder on the worker host, confined to itself: the `path` flavour of the share transport,
and the storage of a mock machine."""

from __future__ import annotations

import contextlib
import ctypes
import errno
import functools
import os
import posixpath
import shutil
import stat as stat_mode
import sys
from typing import Any, BinaryIO

from worker.transports.base import Entry


class MountedFolder:
    """A folder on the worker host's file system, usually a mounted share.

    Links are followed only while they stay inside the folder: a link out of it is neither
    listed nor reached (20010), so the machine's root is the limit whatever the share holds.
    Only folders and regular files exist here; a pipe or a device is never listed or opened
    (opening a pipe would wait for a writer, holding the machine).
    """

    def __init__(self, top: str, *, file_mode: int = 0o666, resolved: bool = False) -> None:
        """Args:
        top: the folder; nothing outside it is reached.
        file_mode: permissions of the files it creates (less the umask).
        resolved: `top` is already its own real path (a mock machine's storage, resolved
            once per process), so it is not resolved again for every target.
        """
        self.top = top
        self._real_top = top if resolved else os.path.realpath(top)
        self.file_mode = file_mode

    def free_bytes(self) -> int | None:
        """Free bytes of the file system the folder is on."""
        try:
            return shutil.disk_usage(self.top).free
        except OSError:
            return None

    def bounded(self) -> contextlib.AbstractContextManager[None]:
        """No bound: a call on the worker's own file system is not cut short here."""
        return contextlib.nullcontext()

    def _inside(self, full: str) -> bool:
        if self._no_links_below_top(full):
            return True
        real = os.path.realpath(full)
        return real == self._real_top or real.startswith(self._real_top + os.sep)

    def _no_links_below_top(self, full: str) -> bool:
        """True when `full` is plainly below a top that is its own real path and no name
        on the way down is a link: then it is its own real path too.

        One lstat per name below the top, where resolving the whole path looks up every
        name from the file system's root (a mock machine's storage lies ten deep).
        """
        top = self._real_top
        if self.top != top or not full.startswith(top + os.sep):
            return False
        names = full[len(top) + 1:].split(os.sep)
        if any(name in ("", ".", "..") for name in names):
            return False
        step = top
        for name in names:
            step = f"{step}{os.sep}{name}"
            try:
                if stat_mode.S_ISLNK(os.lstat(step).st_mode):
                    return False
            except FileNotFoundError:
                return True  # nothing below a missing name can be a link
            except NotADirectoryError:
                return True  # a file on the way: nothing below it exists
        return True

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
                is_dir = stat_mode.S_ISDIR(st.st_mode)
                if not (is_dir or stat_mode.S_ISREG(st.st_mode)):
                    continue
                if child.is_symlink() and not self._inside(child.path):
                    continue
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
        # O_EXCL never follows a link at the name; the folders above were checked by _full.
        fd = os.open(self._full(path), os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC,
                     self.file_mode)
        return os.fdopen(fd, "wb")  # closed by the writer

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
