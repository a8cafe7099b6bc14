"""Attempts that finish in one shared transaction each keep their own result.

A worker's runners hand their results to one transaction (jobs.run.group_commit): the
attempts are recorded together (by COPY on PostgreSQL) and the targets that ended alike
are settled by one statement. A success, a failure, a retry and a success with its own
status message finished together must still read back target by target.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select

from jobs import db, service
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import registry
from jobs.models import Attempt, JobKind, Target, TargetState
from jobs.run import targets
from jobs.run.work import Report
from jobs.settings import Settings
from tests.jobs.helpers import on_each_database

MACHINES = ["m1", "m2", "m3", "m4", "m5"]
LONG = ["l1", "l2", "l3", "l4", "l5"]


@pytest.fixture(params=["postgresql", "sqlite"])
def settings(request: pytest.FixtureRequest, tmp_path: Path, settings: Settings) -> Settings:
    return on_each_database(request, tmp_path, settings)


def started_job(settings: Settings, machines: list[str] = MACHINES
                ) -> tuple[str, dict[str, Any]]:
    """A delete job on five machines, each target claimed; the job id and each `Started`.

    `machines`: others for a test after one that leaves their slots held (the PostgreSQL
    server is the module's)."""
    url = settings.resolved_database_url
    with db.session_scope(url) as session:
        for m in machines:
            registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(
                {"id": m, "name": m.upper(), "model": "Mock"}), data_dir=settings.data_dir)
        job = service.create(session=session, kind=JobKind.DELETE,
                             targets=[service.TargetIn(machineID=m, fileName="O1.NC")
                                      for m in machines])
        job_id = job.id
    return job_id, {m: targets.begin(settings=settings, job_id=job_id, machine_id=m)
                    for m in machines}


def test_attempts_finished_in_one_transaction_keep_their_own_results(
        settings: Settings) -> None:
    job_id, started = started_job(settings)
    outcomes: dict[str, dict[str, Any]] = {
        "m1": {},
        "m2": {},
        "m3": {"error": ContractError(ErrorCode.PATH_NOT_FOUND, "O1.NC")},
        "m4": {"error": ContractError(ErrorCode.MACHINE_OFFLINE, "no answer")},
        "m5": {"status_msg": "kept as O1.NC.bak"},
    }
    reports = [Report(settings, started[m].work, started[m].holder,
                      outcomes[m].get("error"), TargetState.SUCCEEDED,
                      outcomes[m].get("status_msg"), None)
               for m in MACHINES]
    with db.session_scope(settings.resolved_database_url) as session:
        finished = targets._serve(session, reports)  # what one shared transaction does

    assert [f.retry_in_s is not None for f in finished] == [False, False, False, True, False]
    with db.session_scope(settings.resolved_database_url) as session:
        rows = {t.machine_id: t for t in session.scalars(
            select(Target).where(Target.job_id == job_id))}
        attempts = {a.target_id: a for a in session.scalars(select(Attempt))}
        got = {m: (rows[m].state, rows[m].error_code, rows[m].status_msg) for m in MACHINES}
        assert got == {
            "m1": (TargetState.SUCCEEDED, 0, None),
            "m2": (TargetState.SUCCEEDED, 0, None),
            "m3": (TargetState.FAILED, int(ErrorCode.PATH_NOT_FOUND), "O1.NC"),
            "m4": (TargetState.PENDING, int(ErrorCode.MACHINE_OFFLINE), got["m4"][2]),
            "m5": (TargetState.SUCCEEDED, 0, "kept as O1.NC.bak"),
        }
        assert "retrying in" in (got["m4"][2] or "")
        assert rows["m4"].next_attempt_at is not None and rows["m4"].finished_at is None
        assert all(rows[m].finished_at is not None for m in ("m1", "m2", "m3", "m5"))
        assert all(rows[m].lease_until is None for m in MACHINES)
        # One attempt each, with its own outcome and times.
        assert {m: attempts[rows[m].id].error_code for m in MACHINES} == {
            "m1": 0, "m2": 0, "m3": int(ErrorCode.PATH_NOT_FOUND),
            "m4": int(ErrorCode.MACHINE_OFFLINE), "m5": 0}
        assert all(attempts[rows[m].id].number == 1 for m in MACHINES)
        for m in MACHINES:
            ended = attempts[rows[m].id].finished_at
            assert ended is not None and attempts[rows[m].id].started_at <= ended


def test_a_target_settled_elsewhere_meanwhile_is_not_overwritten(settings: Settings) -> None:
    """A target the reaper took back (no longer running) keeps what it was given; the
    others of the same statement are settled."""
    job_id, started = started_job(settings)
    url = settings.resolved_database_url
    with db.session_scope(url) as session:
        taken = session.scalar(select(Target).where(Target.job_id == job_id,
                                                    Target.machine_id == "m2"))
        assert taken is not None
        taken.state, taken.lease_until = TargetState.PENDING, None
    reports = [Report(settings, started[m].work, started[m].holder, None,
                      TargetState.SUCCEEDED, None, None) for m in ("m1", "m2", "m3")]
    with db.session_scope(url) as session:
        targets._serve(session, reports)
    with db.session_scope(url) as session:
        states = dict(session.execute(select(Target.machine_id, Target.state)
                                      .where(Target.job_id == job_id)).all())
    assert states == {"m1": TargetState.SUCCEEDED, "m2": TargetState.PENDING,
                      "m3": TargetState.SUCCEEDED, "m4": TargetState.RUNNING,
                      "m5": TargetState.RUNNING}


def test_a_message_longer_than_its_column_is_stored_cut_with_the_other_results(
        settings: Settings) -> None:
    """An FTP server's reply naming a long path, 5,000 characters, is kept to the 1000 a
    target's statusMsg and an attempt's errorMsg hold: PostgreSQL refused it, and with it
    the shared transaction, and the target stayed running until its worker was taken for
    lost, again at every attempt."""
    job_id, started = started_job(settings, LONG)
    said = ("550 " + "/NC_PROG" * 700)[:5000]
    outcomes: dict[str, dict[str, Any]] = {
        "l1": {},
        "l2": {"error": ContractError(ErrorCode.PATH_NOT_FOUND, said)},
        "l3": {"error": ContractError(ErrorCode.CONNECTION_FAILED, said)},
        "l4": {"status_msg": said},
        "l5": {},
    }
    reports = [Report(settings, started[m].work, started[m].holder,
                      outcomes[m].get("error"), TargetState.SUCCEEDED,
                      outcomes[m].get("status_msg"), None)
               for m in LONG]
    with db.session_scope(settings.resolved_database_url) as session:
        targets._serve(session, reports)

    with db.session_scope(settings.resolved_database_url) as session:
        rows = {t.machine_id: t for t in session.scalars(
            select(Target).where(Target.job_id == job_id))}
        attempts = {a.target_id: a.error_msg for a in session.scalars(select(Attempt))}
    assert {m: rows[m].state for m in LONG} == {
        "l1": TargetState.SUCCEEDED, "l2": TargetState.FAILED, "l3": TargetState.PENDING,
        "l4": TargetState.SUCCEEDED, "l5": TargetState.SUCCEEDED}
    assert rows["l2"].status_msg == said[:999] + "…"
    assert rows["l3"].status_msg == f"attempt 1 failed ({said})"[:999] + "…"
    assert rows["l4"].status_msg == said[:999] + "…"
    assert attempts[rows["l2"].id] == attempts[rows["l3"].id] == said[:999] + "…"
    assert rows["l1"].status_msg is None and attempts[rows["l1"].id] is None
