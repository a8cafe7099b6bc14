"""`/api/health`: liveness for anyone; with the API key, version, whether the parts answer and
the limits of a request, or (`?only=limits`) the limits alone, asking no part."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query
from sqlalchemy import text

from jobs import __version__
from jobs.api.deps import KeyGivenDep, SettingsDep
from jobs.api.text import CheckedRoute
from jobs.db import session_scope
from jobs.dnc import run_views
from jobs.run import queue
from jobs.settings import Settings

router = APIRouter(tags=["health"], route_class=CheckedRoute)

Only = Annotated[Literal["limits"] | None, Query(description=(
    "limits: the version and the limits alone, with neither the database nor the broker "
    "asked (what a client checks a file against before it sends it)"))]


@router.get("/api/health", summary="Liveness; with the API key, version, whether the "
            "database, broker and workers answer, and the limits of a request")
def health(settings: SettingsDep, key_given: KeyGivenDep, workers: bool = True,
           only: Only = None) -> dict[str, Any]:
    if not key_given:  # a load balancer's probe: that the API answers, nothing about the site
        return {"status": "ok"}
    if only == "limits":  # no "status": this asked no part, so it says nothing of their health
        return {"version": __version__, "limits": limits(settings)}
    # Report, never raise: this is what monitoring polls.
    try:
        with session_scope(settings.resolved_database_url) as session:
            session.execute(text("SELECT 1"))
            runs = run_views.link_report(session=session)
        database = "ok"
    except Exception as exc:
        database, runs = f"error: {type(exc).__name__}", None
    broker = queue.broker_status(settings)
    body: dict[str, Any] = {"version": __version__, "database": database, "broker": broker,
                            "runs": runs, "limits": limits(settings)}
    if workers and settings.broker_url and broker == "ok":
        try:
            body["workers"] = queue.workers_answering(settings)
        except Exception as exc:
            body["workers"] = f"error: {type(exc).__name__}"
    body["status"] = "ok" if database == "ok" and broker == "ok" else "degraded"
    return body


def limits(settings: Settings) -> dict[str, int]:
    """The sizes dncq refuses a request over, in bytes: a client checks a file against them
    before it sends it (a body over its limit is refused from its length, yet still sent)."""
    return {
        "maxJsonBodyBytes": settings.max_json_body_bytes,  # any body but a stream's (20013)
        "maxStreamBodyBytes": settings.max_stream_body_bytes,  # sendFileStream, uploads (20013)
        "maxSendFileBytes": settings.max_send_file_bytes,  # sendFile's file, decoded (20012)
        "maxReceiveFileBytes": settings.max_receive_file_bytes,  # receiveFile's file (20012)
    }
