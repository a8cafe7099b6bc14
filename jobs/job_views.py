"""A job as the API, the CLI and the dashboard show it: its summary, the state it shows,
its progress and a page of its targets; which jobs show as queued (`none_begun`, also for
the state filter of jobs.service and the metrics); and the contract's result of each
target (2.6.7).

Read only: what a job is and does is written by jobs.service and the runners.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from sqlalchemy import ColumnElement, Select, case, exists, func, select
from sqlalchemy.orm import Session, selectinload

from jobs.backup_models import Backup
from jobs.db import IN_CHUNK
from jobs.errors import ErrorCode, result
from jobs.models import Job, JobKind, JobState, Payload, Run, RunState, Target, TargetState
from jobs.run.settle import counts

TARGET_PAGE_DEFAULT = 1000  # targets in one page of a job's view: small jobs come whole
TARGET_PAGE_MAX = 10_000


def target_result(target: Target, job_id: str) -> dict[str, Any]:
    """The contract's `{"errorCode","errorMsg"}` for a target, "still running" if not final."""
    return _result_of(target.state, target.error_code, target.error_msg, job_id)


def _result_of(state: TargetState, error_code: int | None, error_msg: str | None,
               job_id: str) -> dict[str, Any]:
    if not state.final:
        body = result(ErrorCode.STILL_RUNNING)
        body["errorMsg"] = f"Still running: job {job_id}."
        return body
    if state is TargetState.SKIPPED or error_code in (None, 0):
        return result(ErrorCode.SUCCESS)
    return {"errorCode": error_code, "errorMsg": error_msg or ""}


def results_json(*, session: Session, job_id: str) -> bytes:
    """Per-target results in request order, as the JSON array the batch endpoints answer.

    Three columns a row and the text made here: a 100,000-target job's results as ORM
    objects, then encoded by the web framework, took the API past 500 MB.
    """
    rows = session.execute(select(Target.state, Target.error_code, Target.error_msg)
                           .where(Target.job_id == job_id).order_by(Target.position)
                           .execution_options(yield_per=IN_CHUNK))
    return ("[" + ",".join(json.dumps(_result_of(*row, job_id), ensure_ascii=False,
                                      separators=(",", ":"))
                           for row in rows) + "]").encode()


@dataclass(frozen=True)
class TargetPage:
    """Which of a job's targets to show: up to `limit` after position `after`, in order."""

    limit: int = TARGET_PAGE_DEFAULT
    after: int | None = None  # the position the previous page ended with
    state: TargetState | None = None
    machine_id: str | None = None


def view(*, session: Session, job: Job, page: TargetPage | None = None) -> dict[str, Any]:
    """A job as the API shows it: its summary, and one page of its targets if asked.

    The summary (counts, total) is always whole; the targets come a page at a time, so
    that reading a job costs the same whatever its size. `nextAfter` is the `after` of
    the next page, or None on the last one.
    """
    c = counts(session=session, job_id=job.id)
    body: dict[str, Any] = {
        "id": job.id, "kind": job.kind.value, "state": _state(session, job, c).value,
        "fileName": job.file_name, "options": job.options, "createdBy": job.created_by,
        "createdAt": job.created_at, "finishedAt": job.finished_at, "retryOf": job.retry_of,
        "total": sum(c.values()), "counts": c, **_progress(session, job),
    }
    if job.kind is JobKind.DNC_RUN:
        body["stoppedBy"] = _stopped_by(session, job)
    if job.kind is JobKind.BACKUP and not job.options.get("streamed"):
        # The job ends with its targets; its ZIP is assembled after them, and named here
        # once registered (None until then).
        body["backupId"] = session.scalar(select(Backup.id).where(Backup.job_id == job.id))
    if page is not None:
        found = list(session.scalars(_page_query(job.id, page)))
        more = len(found) > page.limit
        shown = found[:page.limit]
        body["targets"] = [_target_view(t, job.id) for t in shown]
        body["nextAfter"] = shown[-1].position if more and shown else None
    return body


def none_begun(job_id: Any) -> ColumnElement[bool]:
    """No target of the job has begun: each is pending with no attempt counted, its task not
    yet taken or waiting for its machine (a drip-feed run queued behind another)."""
    return ~exists().where(Target.job_id == job_id, (Target.state != TargetState.PENDING)
                           | (Target.attempts > 0))


def _state(session: Session, job: Job, c: dict[str, int]) -> JobState:
    """The job's state as shown: one recorded running (queued to the workers) of which no
    target has begun is `queued` still, as `list_jobs` filters it."""
    if job.state is JobState.RUNNING and c["pending"] == sum(c.values()) \
            and session.scalar(select(none_begun(job.id))):
        return JobState.QUEUED
    return job.state


def _stopped_by(session: Session, job: Job) -> str | None:
    """Who stopped a drip-feed run's job: its state stays `cancelled`, the word every client
    of the API knows as an end, and this says why; None when no run ended by a stop."""
    return session.scalar(select(Run.stopped_by).where(
        Run.job_id == job.id, Run.stopped_by.is_not(None),
        Run.state.in_((RunState.STOPPED, RunState.CANCELLED))).order_by(Run.position).limit(1))


def _progress(session: Session, job: Job) -> dict[str, Any]:
    """What a progress bar needs beyond the counts: the bytes of a send job's targets still
    to deliver and delivered (a finished target counts whole, a running one as far as it
    got), and when the next retry is due."""
    body: dict[str, Any] = {"nextAttemptAt": session.scalar(
        select(func.min(Target.next_attempt_at)).where(
            Target.job_id == job.id, Target.state == TargetState.PENDING))}
    if job.kind is JobKind.SEND:
        body["bytes"] = _bytes(session, job)
    if job.kind is JobKind.REQUEST and job.payload_id:  # what the machine sent, for the record
        data = session.scalar(select(Payload.data).where(Payload.id == job.payload_id)) or b""
        body["received"] = data[:RECEIVED_SHOWN_BYTES].decode("latin-1")
        body["receivedBytes"] = len(data)
    return body


RECEIVED_SHOWN_BYTES = 4096  # of what a machine sent, shown with its request job


_GONE = (TargetState.FAILED, TargetState.CANCELLED)  # their bytes are not to be delivered
_WHOLE = (TargetState.SUCCEEDED, TargetState.SKIPPED)


def _bytes(session: Session, job: Job) -> dict[str, int]:
    """A send job's bytes delivered and to deliver, counted without reading every target:
    the targets that send the job's payload by state, those with one of their own in SQL."""
    size = session.scalar(select(Payload.size).where(Payload.id == job.payload_id)) or 0
    total = done = 0
    by_state = (select(Target.state, func.count(), func.coalesce(func.sum(Target.bytes_done), 0))
                .where(Target.job_id == job.id, Target.payload_id.is_(None))
                .group_by(Target.state))
    for state, n, moved in session.execute(by_state):
        if state not in _GONE:
            total += n * size
            done += n * size if state in _WHOLE else \
                min(int(moved), n * size) if state is TargetState.RUNNING else 0
    own = Payload.size
    sent = case((Target.state.in_(_WHOLE), own),
                (Target.state == TargetState.RUNNING,
                 case((Target.bytes_done < own, Target.bytes_done), else_=own)), else_=0)
    own_total, own_done = session.execute(
        select(func.coalesce(func.sum(own), 0), func.coalesce(func.sum(sent), 0))
        .select_from(Target).join(Payload, Payload.id == Target.payload_id)
        .where(Target.job_id == job.id, Target.payload_id.is_not(None),
               Target.state.not_in(_GONE))).one()
    return {"done": done + int(own_done), "total": total + int(own_total)}


def _page_query(job_id: str, page: TargetPage) -> Select[Any]:
    query = (select(Target).where(Target.job_id == job_id).order_by(Target.position)
             .limit(page.limit + 1).options(selectinload(Target.history)))
    if page.after is not None:
        query = query.where(Target.position > page.after)
    if page.state is not None:
        query = query.where(Target.state == page.state)
    if page.machine_id is not None:
        query = query.where(Target.machine_id == page.machine_id)
    return query


def _target_view(t: Target, job_id: str) -> dict[str, Any]:
    return {
        "position": t.position, "machineID": t.machine_id, **t.params, "state": t.state.value,
        **target_result(t, job_id), "statusMsg": t.status_msg, "attempts": t.attempts,
        "startedAt": t.started_at, "finishedAt": t.finished_at, "bytesDone": t.bytes_done,
        "bytesTotal": t.bytes_total, "nextAttemptAt": t.next_attempt_at,
        "replacedCopy": t.replaced_payload_id is not None,
        "history": [{"number": a.number, "worker": a.worker, "startedAt": a.started_at,
                     "finishedAt": a.finished_at, "errorCode": a.error_code,
                     "errorMsg": a.error_msg} for a in t.history],
    }
