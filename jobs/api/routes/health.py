"""`/api/health`: version and whether the parts dncq needs answer."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from sqlalchemy import text

from jobs import __version__
from jobs.api.deps import SessionDep, SettingsDep
from jobs.api.text import CheckedRoute
from jobs.run import queue

router = APIRouter(tags=["health"], route_class=CheckedRoute)


@router.get("/api/health", summary="Version, and whether the database, broker and workers answer")
def health(session: SessionDep, settings: SettingsDep, workers: bool = True) -> dict[str, Any]:
    # Report, never raise: this is what monitoring polls.
    try:
        session.execute(text("SELECT 1"))
        database = "ok"
    except Exception as exc:
        database = f"error: {type(exc).__name__}"
    broker = queue.broker_status(settings)
    body: dict[str, Any] = {"version": __version__, "database": database, "broker": broker}
    if workers and settings.broker_url and broker == "ok":
        body["workers"] = queue.workers_answering(settings)
    body["status"] = "ok" if database == "ok" and broker == "ok" else "degraded"
    return body
