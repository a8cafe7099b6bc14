"""What a job may be asked to do beyond its targets: the rollout options, and durations."""

from __future__ import annotations

import math
import re
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, WithJsonSchema, field_validator

_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([smhd]?)\s*$")
_UNIT_S = {"": 1, "s": 1, "m": 60, "h": 3600, "d": 86400}


MAX_DELIVER_WITHIN_S = 31 * 86400  # a month: longer than any stop a fleet plans for


def parse_duration_s(text: str | float | int | None) -> float | None:
    """Seconds in 90, "90", "15m", "8h" or "2d": more than 0, at most a month."""
    if text is None:
        return None
    if isinstance(text, int | float) and not isinstance(text, bool):
        seconds = float(text)
    else:
        m = _DURATION.match(text) if isinstance(text, str) else None
        if not m:
            raise ValueError(f"not a duration: {text!r} (use e.g. 90s, 15m, 8h, 2d)")
        seconds = float(m.group(1)) * _UNIT_S[m.group(2)]
    if not (math.isfinite(seconds) and 0 < seconds <= MAX_DELIVER_WITHIN_S):
        raise ValueError(f"duration out of range: {text!r} (more than 0, at most 31d)")
    return seconds


class RolloutOptions(BaseModel):
    """What a user may ask of a job's rollout (the job API's options)."""

    model_config = ConfigDict(extra="forbid")

    replace: bool = False  # delete an existing file first, keeping a copy to restore
    skip_identical: bool = False  # a target that already has these bytes is skipped
    verify: bool = False  # read the file back after sending and compare
    force: bool = False  # also replace or delete the program the machine is running
    # Seconds, or a duration such as "8h" (read into seconds).
    deliver_within: Annotated[float | None, WithJsonSchema(
        {"anyOf": [{"type": "number"}, {"type": "string"}, {"type": "null"}]})] = Field(
        default=None, examples=["8h"], description="seconds, or 90s/15m/8h/2d; at most 31d")
    abort_after_failures: int | None = Field(default=None, ge=1)
    max_attempts: int | None = Field(default=None, ge=1, le=100)

    @field_validator("deliver_within", mode="before")
    @classmethod
    def _duration(cls, value: Any) -> float | None:
        return parse_duration_s(value)


class JobOptions(RolloutOptions):
    """Options of a job: the user's, and those dncq sets itself."""

    make_dirs: bool = False  # create missing folders on the way (restores)
    streamed: bool = False  # a backupFiles download: fetched by the workers, no ZIP stored
    restore_from: str | None = None  # a restore: the backup whose files the targets send
    unstored: str | None = None  # a stored backup whose ZIP could not be written: why
    dropped_file_removed: bool = False  # a request from a drop folder: its file is gone
