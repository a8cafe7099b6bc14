"""A mock machine's options, where its folder may be, and what `options.json` may change."""

from __future__ import annotations

import contextlib
import os
import re
import stat
from pathlib import Path

from pydantic import Field, field_validator

from worker.transports.base import BadPath, PermissionDenied, TransportOptions


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
    trace: bool = False
    """Append each operation's start and end (Unix time) to `trace` in the machine's folder:
    how many operations a fleet ran at once can be read from the machines' side."""
    current_program: str | None = None
    """The running program, as the controller names it (a name or a path)."""
    folder: str | None = None
    """The machine's folder in `<data_dir>/mock/` (two machines may share one); default: the id.

    One name, as a machine id is written: the options come from the HTTP API too, and a
    mock machine must become neither a way to write anywhere on the host nor a way into
    another machine's storage (`<data_dir>/mock/<name>/files`).
    """

    @field_validator("folder")
    @classmethod
    def _one_name_in_the_mock_area(cls, value: str | None) -> str | None:
        if value is not None and not _FOLDER_NAME.fullmatch(value):
            raise ValueError(f"folder {value!r} must be one name in data/mock/ (letters, "
                             "digits, '.', '_' and '-', starting with a letter or digit)")
        return value


_FOLDER_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
RUN_TIME_OPTIONS = frozenset(MockOptions.model_fields) - {"folder"}
"""What `options.json` may change: everything but where the machine lives."""


def machine_folder(area: Path, name: str) -> Path:
    """The folder of the mock machine `name` in the mock area `area`.

    Raises:
        PermissionDenied: the folder is a link that leaves the area or points into a
            machine's storage: its real place must be a folder directly in the area.
    """
    if not _FOLDER_NAME.fullmatch(name):
        raise BadPath(f"{name!r} is not a mock machine's folder name")
    folder = area / name
    with contextlib.suppress(FileNotFoundError):
        if stat.S_ISDIR(os.lstat(folder).st_mode):
            # A folder, not a link, directly in the area: its real place is there. The
            # usual case, answered by one lstat (a machine is opened for every target).
            return folder
    area.mkdir(mode=0o700, parents=True, exist_ok=True)
    real_area = os.path.realpath(area)
    if os.path.dirname(os.path.realpath(folder)) != real_area:
        raise PermissionDenied(f"the mock machine's folder {name!r} is a link out of "
                               "data/mock/ or into another machine's storage")
    return folder
