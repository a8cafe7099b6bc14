"""`/api/health`: version and whether the parts dncq needs answer."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from sqlalchemy import text

from jobs import __version__
from jobs.api.deps import SessionDep

router = APIRouter(tags=["health"])


@router.get("/api/health", summary="Version and the state of the database")
def health(session: SessionDep) -> dict[str, Any]:
    try:
        session.execute(text("SELECT 1"))
        database = "ok"
    except Exception as exc:  # report, never raise: this is what monitoring polls
        database = f"error: {type(exc).__name__}"
    return {"version": __version__, "database": database,
            "status": "ok" if database == "ok" else "degraded"}
