"""What a runner is given, reports and gets back for its targets: plain data, no database."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Any

from jobs.errors import TRANSIENT_CODES, ContractError, ErrorCode
from jobs.fleet.registry import MachineSpec
from jobs.job_options import JobOptions
from jobs.models import JobKind, TargetState
from jobs.settings import Settings

# Transient failures that may have come after bytes were sent: an offline or busy machine
# refused the attempt first. (20006 is also a connection refused, which sent nothing: the
# code alone cannot tell, so it counts.)
MAY_HAVE_WRITTEN = TRANSIENT_CODES - {ErrorCode.MACHINE_OFFLINE, ErrorCode.MACHINE_BUSY}


@dataclass(frozen=True)
class JobInfo:
    """What a runner needs of the job, read once per task."""

    job_id: str
    kind: JobKind
    options: JobOptions
    payload_id: str | None
    created_at: datetime


@dataclass(frozen=True)
class Work:
    """One claimed target, as plain data for a runner."""

    target_id: int
    job: JobInfo
    machine_id: str
    params: dict[str, Any]
    payload_id: str | None
    attempt: int  # 1 for the first try
    started_at: datetime
    # An earlier attempt was cut off (its worker died, its connection dropped, it timed out)
    # and may have done its work: remembered through the attempts after it.
    previous_interrupted: bool
    more: bool = True  # other targets of the job were pending on the machine when claimed
    previous_error: int | None = None  # the last attempt's errorCode (None: none recorded)
    tries_before: int = 0  # attempts made before the last retry on request
    counted_from: datetime | None = None  # when that retry was asked (None: the job's start)

    @property
    def may_have_written(self) -> bool:
        """Whether an earlier attempt may have got this target's bytes onto the machine.

        Only an attempt that died with its worker or failed on the way (a dropped
        connection, a timeout) can have, and the target remembers one through every attempt
        after it; one that ended with a permanent error (142: the file was already there),
        or found the machine offline or busy before anything was sent, wrote nothing, and a
        retry after such attempts alone that finds the same bytes finds someone else's file.
        """
        return self.previous_interrupted or self.previous_error in MAY_HAVE_WRITTEN

    @property
    def kind(self) -> JobKind:
        return self.job.kind

    @property
    def options(self) -> JobOptions:
        return self.job.options


@dataclass(frozen=True)
class Started:
    """What `begin` found: the machine, and when it got a slot, the holder and first target."""

    spec: MachineSpec | None
    holder: str | None = None
    work: Work | None = None
    job_done: bool = False  # it found the job cancelled and ended it: say so


@dataclass(frozen=True)
class Report:
    """A runner reports an attempt and asks for its next target."""

    settings: Settings
    work: Work
    holder: str
    error: ContractError | None
    state: TargetState
    status_msg: str | None
    replaced_payload_id: str | None


@dataclass(frozen=True)
class Finished:
    """What `finish` left to do: the next target, or a retry or a waiting job to queue."""

    next_work: Work | None
    retry_in_s: float | None = None
    waiting_job_id: str | None = None
    job_done: bool = False  # this attempt was the job's last
