"""The simulated control's program store: a flat folder of programs under the model's naming."""

from __future__ import annotations

import os
import re
import threading
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from worker.transports.base import BadPath, Exists, NotFound

MAX_NAME_BYTES = 255  # UTF-8 bytes of a program name
_FANUC_NAME = re.compile(r"O[0-9]{4,8}")  # O-numbers: O0001, O12345678
_PLAIN_FORBIDDEN = re.compile(r"[\x00-\x1f\x7f/\\]")
_PART = ".part-"  # programs being received: never listed, removed when a receive fails


@dataclass(frozen=True)
class Program:
    """One stored program."""

    name: str
    size: int  # bytes
    mtime_s: int  # POSIX seconds


class ProgramStore:
    """Programs as files in `root`, named as the model's control names them.

    A model whose name starts with "Fanuc" takes O-numbers only (`O0001`); any other takes
    plain names (no slash, no control characters, not starting with a dot).
    """

    def __init__(self, root: Path, *, model: str = "Generic") -> None:
        self.root = root
        self.model = model
        self._fanuc = model.lower().startswith("fanuc")
        self._lock = threading.Lock()  # receives check-then-rename under it: never overwrite
        root.mkdir(parents=True, exist_ok=True)
        for stale in root.glob(f"{_PART}*"):
            stale.unlink()  # left by a simulator that was killed mid-receive

    def check_name(self, name: str) -> None:
        """Raise BadPath unless the control can store a program under `name`."""
        if not name or len(name.encode()) > MAX_NAME_BYTES:
            raise BadPath(f"program name must be 1 to {MAX_NAME_BYTES} bytes: {name!r}")
        if self._fanuc and not _FANUC_NAME.fullmatch(name):
            raise BadPath(f"{self.model} programs are named O0001 to O99999999: {name!r}")
        if _PLAIN_FORBIDDEN.search(name) or name.startswith("."):
            raise BadPath(f"not a program name: {name!r}")

    def programs(self) -> list[Program]:
        """Every stored program, sorted by name."""
        found = []
        for path in self.root.iterdir():
            if path.name.startswith(".") or not path.is_file():
                continue
            st = path.stat()
            found.append(Program(path.name, st.st_size, int(st.st_mtime)))
        return sorted(found, key=lambda p: p.name)

    def find(self, name: str) -> Program:
        """The program called `name` (NotFound if it is not stored)."""
        self.check_name(name)
        path = self.root / name
        if not path.is_file():
            raise NotFound(name)
        st = path.stat()
        return Program(name, st.st_size, int(st.st_mtime))

    def open(self, name: str) -> BinaryIO:
        """The stored program for reading (NotFound if it is not stored)."""
        self.find(name)
        return (self.root / name).open("rb")

    @contextmanager
    def receive(self, name: str, *, replace: bool = False) -> Iterator[BinaryIO]:
        """A file to write a program into; stored under `name` only if the block ends
        without an error. Exists if the name is taken, before and after the receive,
        unless `replace` (a program the operator read in replaces its namesake)."""
        self.check_name(name)
        if not replace and (self.root / name).exists():
            raise Exists(name)
        part = self.root / f"{_PART}{uuid.uuid4().hex}"
        try:
            with part.open("wb") as out:
                yield out
            with self._lock:
                if replace:
                    os.replace(part, self.root / name)
                elif (self.root / name).exists():
                    raise Exists(name)
                else:
                    os.rename(part, self.root / name)
        finally:
            part.unlink(missing_ok=True)

    def delete(self, name: str) -> None:
        """Remove the program (NotFound if it is not stored)."""
        self.find(name)
        try:
            (self.root / name).unlink()
        except FileNotFoundError as exc:
            raise NotFound(name) from exc
