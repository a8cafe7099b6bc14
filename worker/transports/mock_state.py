"""A mock machine's state in its folder, shared under advisory file locks by every process
that opens the machine: options changed at run time, locked ranges, counters, the trace.

The folder holds `options.json` (options changed at run time), `locks.json` (locked
program ranges), `counters` (operations in progress, the most ever seen at once,
operations begun) and, when asked, `trace`; the storage itself is `files/` beside them.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import struct
import threading
import weakref
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from worker.transports.base import Permanent
from worker.transports.mock_options import RUN_TIME_OPTIONS, MockOptions

OPTIONS_FILE = "options.json"  # options changed at run time
LOCKS_FILE = "locks.json"  # program ranges locked against editing
TRACE_FILE = "trace"  # with the `trace` option: "start end" of every operation
_COUNTERS = struct.Struct("<qqq")  # in progress, most ever at once, begun


class MachineState:
    """One mock machine's shared state, kept in its folder."""

    def __init__(self, folder: Path, base_options: MockOptions) -> None:
        """Args:
        folder: the machine's folder.
        base_options: the machine's options from the fleet file, before run-time changes.
        """
        self.folder = folder
        self.base_options = base_options
        self._options, self._options_key = base_options, (0, 0, 0)
        self._counters_fd: int | None = None  # opened on first use, kept until close()
        self._counters_lock = threading.Lock()
        self._close_counters: weakref.finalize[Any, Any] | None = None

    @contextlib.contextmanager
    def counters(self) -> Iterator[list[int]]:
        """[in progress, most ever at once, begun], locked for the block, saved after it."""
        with self._counters_lock:  # an advisory lock keeps other open files out, not threads
            if self._counters_fd is None:
                fd = self._counters_fd = os.open(self.folder / "counters",
                                                 os.O_RDWR | os.O_CREAT, 0o600)
                self._close_counters = weakref.finalize(self, os.close, fd)
            fd = self._counters_fd
            fcntl.flock(fd, fcntl.LOCK_EX)
            try:
                raw = os.pread(fd, _COUNTERS.size, 0)
                values = list(_COUNTERS.unpack(raw)) if len(raw) == _COUNTERS.size else [0, 0, 0]
                yield values
                os.pwrite(fd, _COUNTERS.pack(*values), 0)
            finally:
                fcntl.flock(fd, fcntl.LOCK_UN)

    def _read_json(self, name: str) -> dict[str, Any]:
        path = self.folder / name
        try:
            data = json.loads(path.read_text()) if path.exists() else {}
        except (ValueError, UnicodeError) as exc:
            raise Permanent(f"{name} of this mock machine is not JSON: {exc}") from None
        if not isinstance(data, dict):
            raise Permanent(f"{name} of this mock machine holds no JSON object")
        return data

    def _update_json(self, name: str, change: Callable[[dict[str, Any]], None]) -> None:
        """Change a shared JSON file atomically, one process at a time."""
        with open(self.folder / f"{name}.lock", "a", opener=private) as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            data = self._read_json(name)
            change(data)
            tmp = self.folder / f"{name}.{os.getpid()}.tmp"
            with open(tmp, "w", opener=private) as f:
                f.write(json.dumps(data))
            os.replace(tmp, self.folder / name)

    def options(self) -> MockOptions:
        """Fleet options with the run-time changes applied (re-read only when they change)."""
        try:
            st = (self.folder / OPTIONS_FILE).stat()
        except FileNotFoundError:
            return self.base_options
        key = (st.st_ino, st.st_mtime_ns, st.st_size)
        if self._options_key != key:
            self._options = self._validated(self._read_json(OPTIONS_FILE))
            self._options_key = key
        return self._options

    def _validated(self, changes: dict[str, Any]) -> MockOptions:
        """The fleet options with run-time `changes`, checked as the fleet's options are."""
        unknown = sorted(set(changes) - RUN_TIME_OPTIONS)
        if unknown:
            raise Permanent(f"{OPTIONS_FILE} of this mock machine cannot set "
                            f"{', '.join(unknown)}")
        try:
            return MockOptions.model_validate({**self.base_options.model_dump(), **changes})
        except ValidationError as exc:
            problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}"
                                 for e in exc.errors())
            raise Permanent(f"{OPTIONS_FILE} of this mock machine is not valid: "
                            f"{problems}") from None

    def set_options(self, **changes: Any) -> None:
        """Change options at run time, for every process using this machine."""
        self._validated(changes)
        self._update_json(OPTIONS_FILE, lambda data: data.update(changes))

    def peak_active(self) -> int:
        """The highest number of operations this machine ever had at once."""
        with self.counters() as counters:
            return counters[1]

    def reset_peak(self) -> None:
        """Forget the recorded peak (benchmarks and tests between runs)."""
        with self.counters() as counters:
            counters[1] = counters[0]

    def lock_range(self, start: int, end: int, locked: bool) -> None:
        """Lock programs `start` to `end` against editing, or unlock them."""
        def change(data: dict[str, Any]) -> None:
            ranges = {tuple(r) for r in data.get("locked_ranges", [])}
            (ranges.add if locked else ranges.discard)((start, end))
            data["locked_ranges"] = sorted(ranges)

        self._update_json(LOCKS_FILE, change)

    def locked_ranges(self) -> list[tuple[int, int]]:
        """Program ranges currently locked against editing."""
        ranges = self._read_json(LOCKS_FILE).get("locked_ranges", [])
        return [(int(a), int(b)) for a, b in ranges]

    def trace(self, started: float, ended: float) -> None:
        """Append one operation's start and end (Unix time) to the trace."""
        with open(self.folder / TRACE_FILE, "a", opener=private) as trace:  # one append
            trace.write(f"{started:.6f} {ended:.6f}\n")

    def close(self) -> None:
        """Close the counters' file; the next use opens it again."""
        with self._counters_lock:
            if self._close_counters is not None:
                self._close_counters()
            self._counters_fd = self._close_counters = None


def private(path: str, flags: int) -> int:
    """An opener that creates files 0600: the machine's state lives in dncq's data folder."""
    return os.open(path, flags, 0o600)


def traced(folders: Iterable[Path], *, since: float = 0.0) -> list[tuple[float, float]]:
    """(start, end) of each operation the machines (their folders) traced with the `trace`
    option, those that started at `since` or later."""
    operations = []
    for folder in folders:
        with contextlib.suppress(FileNotFoundError):
            for line in (folder / TRACE_FILE).read_text().splitlines():
                start, end = map(float, line.split())
                if start >= since:
                    operations.append((start, end))
    return operations


def most_at_once(intervals: Iterable[tuple[Any, Any]]) -> int:
    """The most (start, end) intervals that overlap at one moment; one that ends when
    another starts does not overlap it."""
    events = sorted(e for start, end in intervals for e in ((start, 1), (end, -1)))
    most = running = 0
    for _, step in events:  # at a tie the end (-1) sorts first
        running += step
        most = max(most, running)
    return most
