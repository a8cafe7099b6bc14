"""The contract's batch endpoints: 2.6.7 batchSendFile, 2.6.9 batchDeleteFile, 2.6.13 backupFiles.

The two batch endpoints make a job each (see /api/jobs) and answer the bare array of
per-target results in request order, once every target finished or when `batch_wait_s`
ran out, whichever comes first; the job id is in `X-Dncq-Job`. backupFiles makes a backup
job too, which the workers fetch, and streams its ZIP as they go (jobs.backup.download).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, Body, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, StreamingResponse

from jobs import job_views, rollout, service
from jobs.api import waiting
from jobs.api.deps import (
    PrincipalDep,
    SessionDep,
    SettingsDep,
    check_machines,
    note_target,
    requires,
)
from jobs.api.errors import ClosingStream, cut_short
from jobs.api.routes.cnc import FileContent, Force, content_bytes
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Role
from jobs.backup import archive_names, download, streamed
from jobs.db import session_scope
from jobs.errors import ContractError
from jobs.fleet.paths import MissingParameter
from jobs.job_options import JobOptions
from jobs.models import JobKind
from jobs.run import settle
from jobs.settings import Settings

log = logging.getLogger(__name__)
router = APIRouter(prefix="/api/cnc", tags=["cnc (gateway contract 2.6)"],
                   route_class=CheckedRoute)

JOB_HEADER = "X-Dncq-Job"
Results = list[dict[str, Any]]


class BatchSendBody(FileContent):
    """2.6.7 body: the file once, and where it goes."""

    targets: list[Any]  # one that is no object fails at its own position (TargetIn.parse)


async def wait_for_results(settings: Settings, job_id: str, timeout_s: float) -> Response:
    """Per-target results once the job is finished or `timeout_s` passed (the JSON array
    made by `job_views.results_json`: `Results` is what the routes document)."""
    await waiting.until(settings, job_id, timeout_s, settle.is_finished)

    def read() -> bytes:
        with session_scope(settings.resolved_database_url) as session:
            return job_views.results_json(session=session, job_id=job_id)

    return Response(await run_in_threadpool(read), media_type="application/json",
                    headers={JOB_HEADER: job_id})


@router.post("/batchSendFile", summary="2.6.7 Send one file to many machines",
             response_model=Results,
             dependencies=[requires(Role.OPERATOR, action="cnc.batchSendFile")])
async def batch_send_file(request: Request, session: SessionDep, settings: SettingsDep,
                          principal: PrincipalDep,
                          body: Annotated[BatchSendBody, Body()]) -> Response:
    targets = [service.TargetIn.parse(t) for t in body.targets]
    # A target outside an operator's machines refuses the whole request (docs/api.md, Roles).
    check_machines(principal, [t.machineID for t in targets if not t.problem])

    def submit() -> str:
        explicit = body.content is None or body.encoding is not None
        payload_id: str | None
        per_target: dict[int, str | ContractError]
        try:
            data = content_bytes(body, "utf-8") if explicit else None
        except MissingParameter:
            raise  # no file at all: the request cannot be parsed (400)
        except ContractError as exc:  # a file that cannot be read fails every target, in place
            payload_id, per_target = None, dict.fromkeys(range(len(targets)), exc)
        else:
            payload_id, per_target = rollout.payloads(session=session, targets=targets,
                                                      content=body.content, data=data)
        job = rollout.submit(session=session, settings=settings, kind=JobKind.SEND,
                             targets=targets, options=JobOptions(),
                             payload_id=payload_id, target_payloads=per_target)
        return job.id

    job_id = await run_in_threadpool(submit)
    note_target(request, job_id)
    return await wait_for_results(settings, job_id, settings.batch_wait_s)


@router.post(
    "/backupFiles",
    summary="2.6.13 Back up files and folders of many machines into one streamed ZIP",
    response_class=StreamingResponse,
    responses={200: {"content": {"application/octet-stream": {}}}},
    dependencies=[requires(Role.VIEWER, action="cnc.backupFiles")],
)
def backup_files(request: Request, session: SessionDep, settings: SettingsDep,
                 body: Annotated[list[Any], Body()]) -> Response:
    plans = streamed.check(session=session, settings=settings, raw_targets=body)
    job = rollout.submit(
        session=session, settings=settings, kind=JobKind.BACKUP,
        targets=[service.TargetIn(**checked.target.model_dump())
                 for plan in plans for checked in plan.targets],
        options=JobOptions(streamed=True), created_by="api:backupFiles")
    note_target(request, job.id)
    now = datetime.now()
    name = archive_names.backup_name(now) + ".zip"
    zipped = download.stream(settings=settings, job_id=job.id, plans=plans, now=now)
    # Nothing is answered before the ZIP's first piece (download.SENT_BYTES): a target
    # that fails before it is answered with its own error, as the contract answers every
    # failing target. Only one that fails after it can cut the download short.
    try:
        first = next(zipped)
    except ContractError as exc:  # answered as JSON; the log says it too (no worker...)
        log.warning("backupFiles job %s answered with %s before its first byte: %s",
                    job.id, int(exc.code), exc.status_msg)
        return JSONResponse(exc.body(), headers={JOB_HEADER: job.id})
    # Closed when the answer ends: a client that went away leaves its job cancelled then.
    return ClosingStream(
        cut_short(_chained(first, zipped), f"backupFiles download {name}"),
        media_type="application/octet-stream",
        headers={"Content-Disposition": f'attachment; filename="{name}"', JOB_HEADER: job.id})


def _chained(first: bytes, rest: Iterator[bytes]) -> Iterator[bytes]:
    """`first`, then `rest`, which is closed with this generator (itertools.chain would not)."""
    yield first
    yield from rest


@router.post("/batchDeleteFile", summary="2.6.9 Delete files on many machines",
             response_model=Results,
             dependencies=[requires(Role.OPERATOR, action="cnc.batchDeleteFile")])
async def batch_delete_file(request: Request, session: SessionDep, settings: SettingsDep,
                            principal: PrincipalDep,
                            body: Annotated[list[Any], Body()],
                            force: Force = False) -> Response:
    targets = [service.TargetIn.parse(t) for t in body]
    check_machines(principal, [t.machineID for t in targets if not t.problem])

    def submit() -> str:  # force=true in the query, as deleteFile takes it
        return rollout.submit(session=session, settings=settings, kind=JobKind.DELETE,
                              targets=targets, options=JobOptions(force=force)).id

    job_id = await run_in_threadpool(submit)
    note_target(request, job_id)
    return await wait_for_results(settings, job_id, settings.batch_wait_s)
