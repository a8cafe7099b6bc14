"""`/api/health`: liveness for anyone; with the API key, version and whether the parts answer."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from sqlalchemy import text

from jobs import __version__
from jobs.api.deps import KeyGivenDep, SettingsDep
from jobs.api.text import CheckedRoute
from jobs.db import session_scope
from jobs.dnc import run_views
from jobs.run import queue

router = APIRouter(tags=["health"], route_class=CheckedRoute)


@router.get("/api/health", summary="Liveness; with the API key, version and whether the "
            "database, broker and workers answer")
def health(settings: SettingsDep, key_given: KeyGivenDep, workers: bool = True) -> dict[str, Any]:
    if not key_given:  # a load balancer's probe: that the API answers, nothing about the site
        return {"status": "ok"}
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
                            "runs": runs}
    if workers and settings.broker_url and broker == "ok":
        try:
            body["workers"] = queue.workers_answering(settings)
        except Exception as exc:
            body["workers"] = f"error: {type(exc).__name__}"
    body["status"] = "ok" if database == "ok" and broker == "ok" else "degraded"
    return body
