"""A simulated machine: its storage is a folder of its own, its faults are options.

The folder holds `files/` (the storage) and `state.json`: options changed at run
time, the operations in progress and the highest number ever seen at once. Every
process that opens the same machine shares that state through the folder, under
an advisory file lock.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import random
import time
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, ClassVar

from pydantic import Field

from worker.transports.base import (
    CHUNK_BYTES,
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
    TransportOptions,
)

PART_PREFIX = ".dncq-part-"  # half-written files; never listed, never read

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
}


class MockOptions(TransportOptions):
    """Options of a mock machine (fleet file `options:`)."""

    latency_ms: float = Field(default=0.0, ge=0)
    """Added to every primitive operation."""
    bytes_per_s: int | None = Field(default=None, gt=0)
    """Transfer speed limit; None for as fast as the disk."""
    offline: bool = False
    """Every operation fails as if the machine were switched off."""
    fail_rate: float = Field(default=0.0, ge=0, le=1)
    """Share of operations that drop the connection."""
    seed: int = 0
    """Seed of the fault sequence, so that a test sees the same faults every run."""
    current_program: str | None = None
    """The running program, as the controller names it (a name or a path)."""
    folder: str | None = None
    """Storage folder; default: `<data_dir>/mock/<machine id>`."""


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
        self.files.mkdir(parents=True, exist_ok=True)
        for root in roots:
            self._local(root).mkdir(parents=True, exist_ok=True)

    # -- shared state ------------------------------------------------------

    @contextlib.contextmanager
    def _state(self) -> Iterator[dict[str, Any]]:
        """The shared state, locked for the duration of the block, saved after it."""
        with open(self.folder / "state.lock", "a+") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                path = self.folder / "state.json"
                state = json.loads(path.read_text()) if path.exists() else {}
                yield state
                tmp = path.with_suffix(f".{os.getpid()}.tmp")
                tmp.write_text(json.dumps(state))
                os.replace(tmp, path)
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)

    def options(self) -> MockOptions:
        """Fleet options with the run-time changes applied."""
        path = self.folder / "state.json"
        overrides = json.loads(path.read_text()).get("options", {}) if path.exists() else {}
        return self.base_options.model_copy(update=overrides)

    def set_options(self, **changes: Any) -> None:
        """Change options at run time, for every process using this machine."""
        MockOptions.model_validate({**self.base_options.model_dump(), **changes})
        with self._state() as state:
            state.setdefault("options", {}).update(changes)

    def peak_active(self) -> int:
        """The highest number of operations this machine ever had at once."""
        with self._state() as state:
            return int(state.get("peak_active", 0))

    def reset_peak(self) -> None:
        """Forget the recorded peak (benchmarks and tests between runs)."""
        with self._state() as state:
            state["peak_active"] = state.get("active", 0)

    @contextlib.contextmanager
    def _operation(self) -> Iterator[MockOptions]:
        """Account one primitive operation: concurrency, latency and simulated faults."""
        with self._state() as state:
            opts = self.base_options.model_copy(update=state.get("options", {}))
            if opts.offline:
                raise Offline("machine is offline (simulated)")
            count = state.get("ops", 0) + 1
            state["ops"] = count
            draw = random.Random(f"{opts.seed}:{count}").random()  # same faults every run
            fail = draw < opts.fail_rate
            if not fail:
                state["active"] = state.get("active", 0) + 1
                state["peak_active"] = max(state.get("peak_active", 0), state["active"])
        if fail:
            raise Dropped("connection dropped (simulated)")
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
            with self._state() as state:
                state["active"] = max(0, state.get("active", 0) - 1)

    # -- paths -------------------------------------------------------------

    def _local(self, path: str) -> Path:
        local = (self.files / path).resolve() if path else self.files.resolve()
        if not local.is_relative_to(self.files.resolve()):
            raise BadPath(f"path leaves the machine's storage: {path!r}")
        return local

    # -- primitives --------------------------------------------------------

    def list_dir(self, path: str) -> list[Entry]:
        with self._operation():
            local = self._local(path)
            if not local.is_dir():
                raise NotFound(path)
            entries = []
            for child in sorted(local.iterdir(), key=lambda p: p.name):
                if child.name.startswith(PART_PREFIX):
                    continue
                st = child.stat()
                entries.append(
                    Entry(child.name, child.is_dir(), None if child.is_dir() else st.st_size,
                          st.st_mtime)
                )
            return entries

    def stat(self, path: str) -> Entry:
        with self._operation():
            local = self._local(path)
            if not local.exists() or local.name.startswith(PART_PREFIX):
                raise NotFound(path)
            st = local.stat()
            return Entry(local.name, local.is_dir(), None if local.is_dir() else st.st_size,
                         st.st_mtime)

    def read(self, path: str, *, progress: ProgressFn | None = None) -> Iterator[bytes]:
        local = self._local(path)
        with self._operation() as opts:
            if not local.is_file():
                raise NotFound(path)
            total = local.stat().st_size
            done = 0
            with open(local, "rb") as f:
                while chunk := f.read(CHUNK_BYTES):
                    if opts.bytes_per_s:
                        time.sleep(len(chunk) / opts.bytes_per_s)
                    done += len(chunk)
                    yield chunk
                    if progress:
                        progress(done, total)

    def write(
        self, path: str, chunks: Iterable[bytes], *, progress: ProgressFn | None = None
    ) -> int:
        local = self._local(path)
        with self._operation() as opts:
            if not local.parent.is_dir():
                raise NotFound(str(Path(path).parent))
            if local.exists():
                raise Exists(path)
            part = local.parent / f"{PART_PREFIX}{uuid.uuid4().hex}"
            done = 0
            try:
                with open(part, "wb") as f:
                    for chunk in chunks:
                        if opts.bytes_per_s:
                            time.sleep(len(chunk) / opts.bytes_per_s)
                        f.write(chunk)
                        done += len(chunk)
                        if progress:
                            progress(done, None)
                    f.flush()
                    os.fsync(f.fileno())
                try:
                    os.link(part, local)  # fails if the name appeared meanwhile: never overwrite
                except FileExistsError as exc:
                    raise Exists(path) from exc
            finally:
                part.unlink(missing_ok=True)
            return done

    def delete(self, path: str) -> None:
        with self._operation():
            local = self._local(path)
            if not local.is_file():
                raise NotFound(path)
            local.unlink()

    def make_dir(self, path: str) -> None:
        with self._operation():
            local = self._local(path)
            if local.exists():
                raise Exists(path)
            if not local.parent.is_dir():
                raise NotFound(str(Path(path).parent))
            local.mkdir()

    def remove_dir(self, path: str) -> None:
        with self._operation():
            local = self._local(path)
            if not local.is_dir() or local == self.files.resolve():
                raise NotFound(path)
            if any(local.iterdir()):
                raise NotEmpty(path)
            local.rmdir()

    def lock_range(self, start: int, end: int, locked: bool) -> None:
        with self._operation(), self._state() as state:
            ranges = {tuple(r) for r in state.get("locked_ranges", [])}
            (ranges.add if locked else ranges.discard)((start, end))
            state["locked_ranges"] = sorted(ranges)

    def locked_ranges(self) -> list[tuple[int, int]]:
        """Program ranges currently locked against editing."""
        with self._state() as state:
            return [tuple(r) for r in state.get("locked_ranges", [])]  # type: ignore[misc]

    def select_program(self, path: str) -> None:
        with self._operation():
            self.set_options(current_program=path)

    def current_program(self) -> str | None:
        with self._operation() as opts:
            return opts.current_program

    def close(self) -> None:
        pass
