"""Two controls changing one library program at the same moment (a delete, a rename):
the second is answered as the first left the library, nothing is kept twice or lost under
another's name (on PostgreSQL and on SQLite)."""

from __future__ import annotations

from typing import Any

import pytest
from sqlalchemy import delete
from sqlalchemy.orm import Session

from jobs import db
from jobs.errors import ContractError, ErrorCode
from jobs.fleet.request_settings import Source
from jobs.library import blobs
from jobs.library import service as library
from jobs.library.models import LibraryProgram, LibraryVersion
from jobs.requests import sources
from jobs.settings import Settings
from tests.jobs.helpers import while_another_writes

LIBRARY = [Source.parse("library:")]


@pytest.fixture
def on_database(settings: Settings, database_url: str) -> Settings:
    """The test's dncq on each database, the library holding VIPROS/0010 and 0020 (the
    PostgreSQL database is the module's: the folder is emptied first)."""
    settings = settings.model_copy(update={"database_url": database_url})
    with db.session_scope(settings.resolved_database_url) as session:
        session.execute(delete(LibraryVersion))
        session.execute(delete(LibraryProgram))
    for name in ("0010", "0020"):
        blob = blobs.put(settings, [f"%\nO{name}\nM30\n%\n".encode()])
        with db.session_scope(settings.resolved_database_url) as session:
            library.add(session=session, folder="VIPROS", name=name, blob=blob, approve=True)
    return settings


def renamed_by_another(settings: Settings, old: str, new: str) -> Any:
    """What another request's rename writes, in the transaction the test holds open."""
    def rename(session: Session) -> None:
        program = library.find(session=session, folder="VIPROS", name=old)
        chosen = library.approved(program)
        assert chosen is not None
        library.add(session=session, folder="VIPROS", name=new, approve=True,
                    blob=blobs.BlobInfo(chosen.sha256, chosen.size))
        library.delete(session=session, folder="VIPROS", name=old)
    return rename


def programs(settings: Settings) -> dict[str, list[int]]:
    """The library's live programs of VIPROS, each with its version numbers."""
    with db.session_scope(settings.resolved_database_url) as session:
        return {p.name: [v.number for v in p.versions]
                for p in library.list_programs(session=session, folder="VIPROS")
                if not p.deleted}


def test_a_program_renamed_by_two_at_once_gets_one_new_name(on_database: Settings) -> None:
    other = while_another_writes(
        on_database.resolved_database_url, renamed_by_another(on_database, "0010", "0030"),
        lambda: sources.rename(on_database, LIBRARY, "VIPROS", "0010", "0040", by="m2"))

    error = other.get("error")
    assert isinstance(error, ContractError) and error.code is ErrorCode.PATH_NOT_FOUND
    assert programs(on_database) == {"0020": [1], "0030": [1]}


def test_two_programs_renamed_onto_one_name_at_once_leave_the_second_as_it_was(
        on_database: Settings) -> None:
    other = while_another_writes(
        on_database.resolved_database_url, renamed_by_another(on_database, "0020", "0030"),
        lambda: sources.rename(on_database, LIBRARY, "VIPROS", "0010", "0030", by="m2"))

    error = other.get("error")
    assert isinstance(error, ContractError) and error.code is ErrorCode.PATH_EXISTS
    assert programs(on_database) == {"0010": [1], "0030": [1]}  # not O0010 as its v2


def test_a_program_deleted_by_two_at_once_is_reported_deleted_once(
        on_database: Settings) -> None:
    def deleted_by_another(session: Session) -> None:
        library.delete(session=session, folder="VIPROS", name="0010")

    other = while_another_writes(
        on_database.resolved_database_url, deleted_by_another,
        lambda: sources.delete(on_database, LIBRARY, "VIPROS", "0010", by="m2"))

    error = other.get("error")
    assert isinstance(error, ContractError) and error.code is ErrorCode.PATH_NOT_FOUND
    assert programs(on_database) == {"0020": [1]}


def test_a_program_renamed_while_another_deletes_it_is_not_found_to_rename(
        on_database: Settings) -> None:
    def deleted_by_another(session: Session) -> None:
        library.delete(session=session, folder="VIPROS", name="0010")

    other = while_another_writes(
        on_database.resolved_database_url, deleted_by_another,
        lambda: sources.rename(on_database, LIBRARY, "VIPROS", "0010", "0030", by="m2"))

    error = other.get("error")
    assert isinstance(error, ContractError) and error.code is ErrorCode.PATH_NOT_FOUND
    assert programs(on_database) == {"0020": [1]}  # no 0030 living on after its delete
