"""A send job of a library version: which version, its bytes, and the job saying it sent it."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from fastapi import HTTPException
from sqlalchemy.orm import Session

from jobs import job_views
from jobs.api.errors import CodedHTTPError, library_errors
from jobs.errors import ErrorCode
from jobs.library import blobs, names
from jobs.library import service as library
from jobs.library.models import LibraryVersion
from jobs.library.views import reference
from jobs.models import Job, JobKind
from jobs.settings import Settings

SEND_MAX_BYTES = 256 * 1024 * 1024  # a send job's payload is held in the database whole


class LibraryAsked(Protocol):
    """The fields of a job request that name a library version."""

    kind: JobKind
    library: str | None
    library_version: int | None
    content: str | None
    base64: str | None


def version(*, session: Session, settings: Settings, request: LibraryAsked) -> LibraryVersion:
    """The version a send job of `request.library` rolls out; 404 or 400 when there is none."""
    if request.kind is not JobKind.SEND:
        raise HTTPException(422, detail="only a send job takes a library program")
    if request.content is not None or request.base64 is not None:
        raise HTTPException(422, detail="give library or content/base64, not both")
    assert request.library is not None
    with library_errors():
        folder, name, number = names.split_reference(request.library)
        if number is not None and request.library_version not in (None, number):
            raise names.bad(f"{request.library} and library_version "
                            f"{request.library_version} name two versions")
        chosen = library.for_send(session=session, folder=folder, name=name,
                                  number=number or request.library_version)
    if chosen.size > SEND_MAX_BYTES:
        raise CodedHTTPError(413, ErrorCode.FILE_TOO_LARGE,
                             f"{chosen.program.path} v{chosen.number} is over "
                             f"{SEND_MAX_BYTES} bytes: too large for a send job")
    return chosen


def content(*, settings: Settings, sent: LibraryVersion) -> bytes:
    """The version's bytes, read from its blob."""
    with library_errors():
        return blobs.read_all(settings, sent.sha256)


def recorder(sent: LibraryVersion | None) -> Callable[[Job], None] | None:
    """What records on the job, in its own transaction, which version it sent."""
    if sent is None:
        return None

    def record(job: Job) -> None:
        job.library_version_id = sent.id

    return record


def view(*, session: Session, job: Job, page: job_views.TargetPage | None = None
         ) -> dict[str, Any]:
    """`jobs.job_views.view`, with `library` saying which version a send job sent."""
    body = job_views.view(session=session, job=job, page=page)
    if job.library_version_id is not None:
        sent = session.get(LibraryVersion, job.library_version_id)
        body["library"] = reference(sent) if sent is not None else {
            "versionId": job.library_version_id}
    return body
