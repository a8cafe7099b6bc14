"""A simulated machine: its storage is a folder of its own, its faults are options.

The storage is `files/` in the machine's folder; what every process that opens the
machine shares beside it (options changed at run time, locked ranges, counters, the
trace) is `mock_state.MachineState`.
"""

from __future__ import annotations

import contextlib
import errno
import os
import posixpath
import random
import re
import time
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, ClassVar

from worker.transports import parts
from worker.transports.base import (
    CHUNK_BYTES,
    PART_PREFIX,
    BadPath,
    Capabilities,
    Dropped,
    Entry,
    Exists,
    NotEmpty,
    NotFound,
    Offline,
    PermissionDenied,
    ProgressFn,
    TransportError,
)
from worker.transports.mock_options import MockOptions, machine_folder
from worker.transports.mock_state import MachineState
from worker.transports.mounted_folder import MountedFolder

__all__ = ["MockOptions", "MockTransport", "machine_folder"]

# A program a lock can protect: O8999 as a Fanuc stores it, 8999 as a Mitsubishi does.
_PROGRAM_NUMBER = re.compile(r"[Oo]?([0-9]{1,8})")

# The local disk's failures as the transport's errors; any other OSError stays unexpected.
_BY_ERRNO: dict[int, type[TransportError]] = {
    errno.ENOENT: NotFound,
    errno.ENOTDIR: NotFound,
    errno.EEXIST: Exists,
    errno.ENOTEMPTY: NotEmpty,
    errno.EACCES: PermissionDenied,
    errno.EPERM: PermissionDenied,
    errno.EROFS: PermissionDenied,
    errno.ENAMETOOLONG: BadPath,  # a name under 255 characters can be over 255 bytes
    errno.EISDIR: NotFound,  # a folder where a file was asked for
    errno.ELOOP: NotFound,  # a link that never ends names no file
}


class MockTransport:
    """A machine storage simulated in a local folder."""

    capabilities: ClassVar[Capabilities] = Capabilities(
        lock_range=True, select_program=True, current_program=True
    )
    own_storage: ClassVar[bool] = True
    server_row: ClassVar[str | None] = None

    def __init__(self, options: MockOptions, *, folder: Path, roots: Iterable[str] = ()) -> None:
        """Args:
        options: the machine's options from the fleet file.
        folder: where this machine's storage and state live.
        roots: storage folders that exist on the simulated controller from the start
            (its model's roots, such as `CNC_MEM` or `TNC/nc_prog`).
        """
        self.base_options = options
        self.folder = folder
        self.files = folder / "files"
        self._root = _ready_root(self.files, tuple(roots))
        # Links stay inside the storage, only files and folders exist, nothing blocks.
        self._disk = MountedFolder(self._root, file_mode=0o600, resolved=True)
        self._state = MachineState(folder, options)

    def options(self) -> MockOptions:
        """Fleet options with the run-time changes applied (re-read only when they change)."""
        return self._state.options()

    def set_options(self, **changes: Any) -> None:
        """Change options at run time, for every process using this machine."""
        self._state.set_options(**changes)

    def peak_active(self) -> int:
        """The highest number of operations this machine ever had at once."""
        return self._state.peak_active()

    def reset_peak(self) -> None:
        """Forget the recorded peak (benchmarks and tests between runs)."""
        self._state.reset_peak()

    @contextlib.contextmanager
    def _operation(self) -> Iterator[MockOptions]:
        """Account one primitive operation: concurrency, latency and simulated faults."""
        opts = self.options()
        if opts.offline:
            raise Offline("machine is offline (simulated)")
        with self._state.counters() as counters:
            counters[2] += 1
            # The same faults every run: the draw depends on the seed and the count only.
            fail = bool(opts.fail_rate) and \
                random.Random(f"{opts.seed}:{counters[2]}").random() < opts.fail_rate
            if not fail:
                counters[0] += 1
                counters[1] = max(counters[1], counters[0])
        if fail:
            raise Dropped("connection dropped (simulated)")
        started = time.time()
        try:
            if opts.latency_ms:
                time.sleep(opts.latency_ms / 1000)
            yield opts
        except OSError as exc:
            error = _BY_ERRNO.get(exc.errno or 0)
            if error is None:
                raise
            raise error(exc.strerror or str(exc)) from exc
        finally:
            with self._state.counters() as counters:
                counters[0] = max(0, counters[0] - 1)
            if opts.trace:
                self._state.trace(started, time.time())

    # -- paths -------------------------------------------------------------

    def _checked(self, path: str) -> str:
        """`path` normalised; BadPath when it climbs out (links are the disk's to refuse)."""
        local = os.path.normpath(os.path.join(self._root, path)) if path else self._root
        if local != self._root and not local.startswith(self._root + os.sep):
            raise BadPath(f"path leaves the machine's storage: {path!r}")
        return os.path.relpath(local, self._root) if local != self._root else ""

    # -- primitives --------------------------------------------------------

    def free_bytes(self) -> int | None:
        """Free bytes of the disk the simulated storage is on."""
        return self._disk.free_bytes()

    def list_dir(self, path: str) -> list[Entry]:
        with self._operation():
            checked = self._checked(path)
            if not self._disk.stat(checked).is_dir:
                raise NotFound(path)
            entries = [e for e in self._disk.list(checked) if not e.name.startswith(PART_PREFIX)]
            return sorted(entries, key=lambda e: e.name)

    def stat(self, path: str) -> Entry:
        with self._operation():
            checked = self._checked(path)
            if posixpath.basename(checked).startswith(PART_PREFIX):
                raise NotFound(path)
            return self._disk.stat(checked)

    def read(self, path: str, *, progress: ProgressFn | None = None) -> Iterator[bytes]:
        checked = self._checked(path)
        with self._operation() as opts:
            try:
                f, total = self._disk.open_read(checked)
            except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
                raise NotFound(path) from None
            with f:
                done = 0
                while chunk := f.read(CHUNK_BYTES):
                    if opts.bytes_per_s:
                        time.sleep(len(chunk) / opts.bytes_per_s)
                    done += len(chunk)
                    yield chunk
                    if progress:
                        progress(done, total)
                    if len(chunk) < CHUNK_BYTES and done >= total:
                        break  # the whole file: no read just to see its end

    def write(
        self, path: str, chunks: Iterable[bytes], *, progress: ProgressFn | None = None
    ) -> int:
        checked = self._checked(path)
        with self._operation() as opts:
            self._refuse_if_locked(checked)
            folder = posixpath.dirname(checked)
            part = posixpath.join(folder,
                                  parts.part_name(PART_PREFIX, uuid.uuid4().hex))
            try:
                f = self._disk.create(part)
            except (FileNotFoundError, NotADirectoryError):
                raise NotFound(folder) from None
            _remove_parts_of_dead_writers(Path(self._root, folder))
            done = 0
            try:
                with f:
                    for chunk in chunks:
                        if opts.bytes_per_s:
                            time.sleep(len(chunk) / opts.bytes_per_s)
                        f.write(chunk)
                        done += len(chunk)
                        if progress:
                            progress(done, None)
                    # No fsync: this simulates a remote storage; the link below is what keeps
                    # a half-written file from ever appearing under its name.
                try:
                    self._disk.rename_noreplace(part, checked)  # never overwrites
                except FileExistsError as exc:
                    raise Exists(path) from exc
            finally:
                with contextlib.suppress(FileNotFoundError):
                    self._disk.remove(part)
            return done

    def delete(self, path: str) -> None:
        with self._operation():
            checked = self._checked(path)
            if not checked or self._disk.stat(checked).is_dir:
                raise NotFound(path)
            self._refuse_if_locked(checked)
            self._disk.remove(checked)

    def make_dir(self, path: str) -> None:
        with self._operation():
            checked = self._checked(path)
            if not checked:
                raise Exists(path)
            self._disk.mkdir(checked)

    def remove_dir(self, path: str) -> None:
        with self._operation():
            checked = self._checked(path)
            if not checked or not self._disk.stat(checked).is_dir:
                raise NotFound(path)
            self._disk.rmdir(checked)

    def lock_range(self, start: int, end: int, locked: bool) -> None:
        with self._operation():
            self._state.lock_range(start, end, locked)

    def locked_ranges(self) -> list[tuple[int, int]]:
        """Program ranges currently locked against editing."""
        return self._state.locked_ranges()

    def _refuse_if_locked(self, path: str) -> None:
        """PermissionDenied when `path` is a program in a locked range: a control with its
        programs protected refuses to store, replace or delete them from outside its panel."""
        if not (m := _PROGRAM_NUMBER.fullmatch(posixpath.basename(path))):
            return
        number = int(m.group(1))
        for start, end in self.locked_ranges():
            if start <= number <= end:
                raise PermissionDenied(f"{path} is protected: programs {start}-{end} "
                                       "are locked")

    def select_program(self, path: str) -> None:
        with self._operation():
            self.set_options(current_program=path)

    def current_program(self) -> str | None:
        with self._operation() as opts:
            return opts.current_program

    def close(self) -> None:
        self._state.close()


_REAL: dict[Path, str] = {}  # storage folder -> its real path, once per process


def _ready_root(files: Path, roots: tuple[str, ...]) -> str:
    """The storage folder's real path, with the model's roots present."""
    real = _REAL.get(files)
    if real is None or not os.path.isdir(real):
        files.mkdir(parents=True, exist_ok=True)
        real = _REAL[files] = os.path.realpath(files)
    for root in roots:
        local = os.path.join(real, root)
        if not os.path.isdir(local):
            if not os.path.realpath(local).startswith(real + os.sep):
                raise BadPath(f"root leaves the machine's storage: {root!r}")
            os.makedirs(local, exist_ok=True)
    return real


PART_SWEEP_S = 10.0
_SWEPT: dict[Path, float] = {}  # folder -> when this process last removed dead parts


def _remove_parts_of_dead_writers(folder: Path) -> None:
    """Delete half-written files whose writer on this host was killed mid-write.

    A folder is looked at again only after `PART_SWEEP_S`: the parts are hidden from
    every listing meanwhile, and a scan per write would cost more than the write.
    """
    now = time.monotonic()
    if now - _SWEPT.get(folder, -PART_SWEEP_S) < PART_SWEEP_S:
        return
    _SWEPT[folder] = now
    parts.remove_parts_of_dead_writers(folder, PART_PREFIX)

