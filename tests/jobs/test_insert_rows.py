"""Rows taken by COPY on PostgreSQL (`db.insert_rows`) read back as an INSERT's do, and
the same rows on SQLite too.

Job targets and backup files go in that way: a column whose value COPY spells differently
(an enum, JSON, an aware time, text with tabs, backslashes or newlines) would change what
every later query sees.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, cast

import pytest
from sqlalchemy import Table, insert, select

from jobs import db
from jobs.models import Job, JobKind, Target, TargetState

TARGETS = cast(Table, Target.__table__)
WHEN = datetime(2026, 12, 5, 3, 4, 5, 678901, tzinfo=UTC)


@pytest.fixture(params=["postgresql", "sqlite"])
def url(request: pytest.FixtureRequest, tmp_path: Any) -> str:
    if request.param == "postgresql":
        return str(request.getfixturevalue("postgres_url"))
    url = f"sqlite:///{tmp_path}/dncq.db"
    db.upgrade(url)
    return url


def rows(job_id: str) -> list[dict[str, Any]]:
    pending = {"job_id": job_id, "position": 0, "machine_id": "m-1",
               "params": {"fileName": "Ø 1\t\\x.nc", "dirAtCNC": "//CNC_MEM/USER/", "n": [1, None]},
               "state": TargetState.PENDING, "attempts": 0, "bytes_done": 0,
               "dispatched_at": WHEN, "interrupted": False}
    failed = {**pending, "position": 1, "machine_id": "nobody", "params": {},
              "state": TargetState.FAILED, "finished_at": WHEN, "error_code": 10003,
              "error_msg": 'line one\nline "two" \\ \\N', "status_msg": None}
    return [pending, failed]


def stored(session: Any, job_id: str) -> list[dict[str, Any]]:
    found = session.execute(select(Target).where(Target.job_id == job_id)
                            .order_by(Target.position)).scalars().all()
    return [{c.key: getattr(t, c.key) for c in TARGETS.columns if c.key not in ("id", "job_id")}
            for t in found]


def test_rows_copied_read_back_as_inserted_ones(url: str) -> None:
    with db.session_scope(url) as session:
        session.add_all([Job(id="by-insert", kind=JobKind.SEND),
                         Job(id="by-copy", kind=JobKind.SEND)])
        session.flush()
        session.execute(insert(Target), rows("by-insert"))
        db.insert_rows(session, TARGETS, rows("by-copy"))

    with db.session_scope(url) as session:
        inserted, copied = stored(session, "by-insert"), stored(session, "by-copy")
    assert copied == inserted
    assert copied[1]["error_msg"] == 'line one\nline "two" \\ \\N'
    assert copied[0]["params"]["fileName"] == "Ø 1\t\\x.nc"
    assert (copied[0]["state"], copied[0]["dispatched_at"]) == (TargetState.PENDING, WHEN)
    assert copied[0]["error_code"] is None  # a key the row lacks: NULL


def test_copied_rows_belong_to_the_transaction(url: str) -> None:
    """A job whose recording fails leaves no target behind."""
    try:
        with db.session_scope(url) as session:
            session.add(Job(id="rolled-back", kind=JobKind.SEND))
            session.flush()
            db.insert_rows(session, TARGETS, rows("rolled-back"))
            raise RuntimeError("the request failed after its targets")
    except RuntimeError:
        pass
    with db.session_scope(url) as session:
        assert session.scalars(select(Target.id).where(Target.job_id == "rolled-back")).all() == []
