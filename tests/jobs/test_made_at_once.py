"""Rows that two make at the same moment: a program kept once for every job that sends it,
a machine's first check, a library folder given to a machine, a user or a key of one name.
In each case one request finds the row missing while the other has written it and not
committed yet; both must succeed, or the second be told the name exists (on PostgreSQL and
on SQLite)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from jobs import db, service
from jobs.auth import service as auth
from jobs.auth.roles import Role
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import checks, registry
from jobs.library import service as library
from jobs.library.models import LibraryAssignment
from jobs.models import MachineCheck, Payload, utcnow
from tests.jobs.helpers import while_another_writes

PROGRAM = b"%\nO0077\nG0 X0\nM30\n%\n"


def test_the_same_program_stored_twice_is_kept_once(database_url: str) -> None:
    with db.session_scope(database_url) as session:
        first = service.store_payload(session=session, data=PROGRAM)
    with db.session_scope(database_url) as session:
        assert service.store_payload(session=session, data=PROGRAM) == first
        assert session.scalar(select(func.count()).select_from(Payload)
                              .where(Payload.id == first)) == 1


def test_two_requests_storing_the_same_program_at_once_both_succeed(database_url: str) -> None:
    data = PROGRAM + b"\n"

    def store() -> str:
        with db.session_scope(database_url) as session:
            return service.store_payload(session=session, data=data)

    mine: list[str] = []
    other = while_another_writes(database_url, lambda session: mine.append(
        service.store_payload(session=session, data=data)), store)
    assert other == {"result": mine[0]}
    with db.session_scope(database_url) as session:
        assert session.scalar(select(Payload.size).where(Payload.id == mine[0])) == len(data)


def _check(machine_id: str, reachable: bool) -> dict[str, Any]:
    return {"id": machine_id, "reachable": reachable, "latency_ms": 3.0}


def test_a_machine_checked_for_the_first_time_by_two_at_once_keeps_the_later_check(
        database_url: str) -> None:
    def check_first(session: Session) -> None:  # as another record() writes it
        session.add(MachineCheck(machine_id="m1", checked_at=utcnow(), reachable=False,
                                 found=_check("m1", False)))
        session.flush()

    other = while_another_writes(database_url, check_first, lambda: checks.record(
        database_url, [_check("m1", True), _check("m2", True)]))
    assert other == {"result": None}
    with db.session_scope(database_url) as session:
        kept = {c.machine_id: (c.reachable, c.found["latency_ms"])
                for c in session.scalars(select(MachineCheck))}
    assert kept == {"m1": (True, 3.0), "m2": (True, 3.0)}


def test_a_folder_given_to_a_machine_by_two_admins_at_once_is_given_once(
        database_url: str, tmp_path: Path) -> None:
    with db.session_scope(database_url) as session:
        for machine_id in ("m1", "m2"):
            registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(
                {"id": machine_id, "name": machine_id, "model": "Mock"}), data_dir=tmp_path)

    def give() -> list[str]:
        with db.session_scope(database_url) as session:
            return [row.machine_id for row in library.assign(
                session=session, folder="parts", machine_ids=["m1", "m2", "m1"])]

    other = while_another_writes(
        database_url, lambda session: library.assign(session=session, folder="parts",
                                            machine_ids=["m1"]), give)
    assert other == {"result": ["m1", "m2"]}
    with db.session_scope(database_url) as session:
        given = sorted(session.scalars(select(LibraryAssignment.machine_id)
                                       .where(LibraryAssignment.folder == "parts")))
    assert given == ["m1", "m2"]


@pytest.mark.parametrize("what", ["user", "key"])
def test_two_admins_adding_one_name_at_once_are_told_it_exists(database_url: str,
                                                              what: str) -> None:
    def add(session: Session) -> Any:
        if what == "user":
            return auth.create_user(session=session, name="alice",
                                    password="correct horse battery", role=Role.OPERATOR)
        return auth.create_key(session=session, name="line-1", role=Role.OPERATOR)

    def add_alone() -> Any:
        with db.session_scope(database_url) as session:
            return add(session)

    other = while_another_writes(database_url, add, add_alone)
    assert set(other) == {"error"}
    error = other["error"]
    assert isinstance(error, ContractError) and error.code is ErrorCode.PATH_EXISTS
    assert "exists" in str(error)
