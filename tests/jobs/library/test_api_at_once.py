"""Two clients changing one library program through the HTTP API at the same moment (a
delete, a new version, a control's rename meanwhile): each is answered as the other left
the library, and no version is lost under a deleted program or numbered twice (on
PostgreSQL and on SQLite)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from sqlalchemy import delete
from sqlalchemy.orm import Session

from jobs import db
from jobs.api.app import create_app
from jobs.fleet import registry
from jobs.library import blobs
from jobs.library import service as library
from jobs.library.models import LibraryProgram, LibraryVersion
from jobs.settings import Settings
from tests.conftest import API_KEY
from tests.jobs.helpers import at_once, while_another_writes
from tests.live_server import serving

PROGRAM = "/api/library/programs/VIPROS/0010"


@pytest.fixture
def api(settings: Settings, database_url: str) -> Iterator[tuple[Settings, str]]:
    """The API served on loopback over each database, the library holding VIPROS/0010 and
    0020 (the PostgreSQL database is the module's: the library is emptied first); yields
    the settings and the server's URL."""
    settings = settings.model_copy(update={"database_url": database_url})
    with db.session_scope(database_url) as session:
        session.execute(delete(LibraryVersion))
        session.execute(delete(LibraryProgram))
    for name in ("0010", "0020"):
        _add(settings, name, f"%\nO{name}\nM30\n%\n".encode())
    with serving(create_app(settings)) as server:
        yield settings, server.url


def _add(settings: Settings, name: str, data: bytes, session: Session | None = None) -> None:
    blob = blobs.put(settings, [data])
    if session is not None:
        library.add(session=session, folder="VIPROS", name=name, blob=blob, approve=True)
        return
    with db.session_scope(settings.resolved_database_url) as own:
        library.add(session=own, folder="VIPROS", name=name, blob=blob, approve=True)


def _request(url: str, method: str, path: str, **kwargs: Any) -> httpx.Response:
    with httpx.Client(base_url=url, headers={"X-Api-Key": API_KEY}, timeout=60) as client:
        return client.request(method, path, **kwargs)


def _programs(settings: Settings) -> dict[str, list[int]]:
    """The library's live programs of VIPROS, each with its version numbers."""
    with db.session_scope(settings.resolved_database_url) as session:
        return {p.name: [v.number for v in p.versions]
                for p in library.list_programs(session=session, folder="VIPROS")}


def _deleted_by_another(session: Session) -> None:
    library.delete(session=session, folder="VIPROS", name="0010")


def test_a_program_deleted_by_two_clients_at_once_is_answered_deleted_once(api) -> None:
    settings, url = api

    other = while_another_writes(settings.resolved_database_url, _deleted_by_another,
                                 lambda: _request(url, "DELETE", PROGRAM))

    answer = other["result"]
    assert answer.status_code == 404 and answer.json()["errorCode"] == 158
    assert _programs(settings) == {"0020": [1]}


def test_a_delete_that_meets_a_rename_is_not_found_and_the_new_name_stays(api) -> None:
    settings, url = api

    def renamed_by_a_control(session: Session) -> None:  # as a request's rename writes it
        program = library.find(session=session, folder="VIPROS", name="0010", for_update=True)
        chosen = library.approved(program)
        assert chosen is not None
        library.hold_name(session=session, folder="VIPROS", name="0030")
        library.add(session=session, folder="VIPROS", name="0030", approve=True,
                    blob=blobs.BlobInfo(chosen.sha256, chosen.size))
        library.delete(session=session, folder="VIPROS", name="0010")

    other = while_another_writes(settings.resolved_database_url, renamed_by_a_control,
                                 lambda: _request(url, "DELETE", PROGRAM))

    assert other["result"].status_code == 404
    assert _programs(settings) == {"0020": [1], "0030": [1]}


def test_a_version_added_while_another_deletes_the_program_brings_it_back(api) -> None:
    settings, url = api

    other = while_another_writes(
        settings.resolved_database_url, _deleted_by_another,
        lambda: _request(url, "POST", "/api/library/programs",
                         params={"folder": "VIPROS", "name": "0010", "approve": "true"},
                         content=b"%\nO0010\nG1 X5 F100\nM30\n%\n"))

    answer = other["result"]
    assert answer.status_code == 201, answer.text
    assert (answer.json()["version"]["version"], answer.json()["restored"]) == (2, True)
    assert _programs(settings) == {"0010": [1, 2], "0020": [1]}  # not lost under a delete


def test_a_delete_that_meets_a_new_version_takes_the_program_with_it(api) -> None:
    settings, url = api

    other = while_another_writes(
        settings.resolved_database_url,
        lambda session: _add(settings, "0010", b"%\nO0010\nG1 X9 F100\nM30\n%\n", session),
        lambda: _request(url, "DELETE", PROGRAM))

    assert other["result"].status_code == 200
    assert _programs(settings) == {"0020": [1]}
    with db.session_scope(settings.resolved_database_url) as session:
        kept = library.history(session=session, folder="VIPROS", name="0010")
        assert [v.number for v in kept] == [2, 1]  # its history kept, as for any delete


CLIENTS = 5  # more than add's tries: each waits its turn, none is told to try again


def test_new_versions_added_by_several_clients_at_once_are_numbered_without_gap_or_repeat(
        api) -> None:
    settings, url = api

    def uploads() -> list[httpx.Response]:
        return at_once(*(lambda n=n: _request(
            url, "POST", "/api/library/programs", params={"folder": "VIPROS", "name": "0010"},
            content=f"%\nO0010\nG1 X{n} F100\nM30\n%\n".encode()) for n in range(CLIENTS)))

    other = while_another_writes(
        settings.resolved_database_url,
        lambda session: _add(settings, "0010", b"%\nO0010\nG1 X99 F100\nM30\n%\n", session),
        uploads)

    answers = other["result"]
    assert [a.status_code for a in answers] == [201] * CLIENTS, [a.text for a in answers]
    numbers = sorted(a.json()["version"]["version"] for a in answers)
    assert numbers == list(range(3, 3 + CLIENTS))
    assert _programs(settings)["0010"] == list(range(1, 3 + CLIENTS))


def test_two_octoprint_uploads_with_no_overwrite_at_once_keep_the_first_and_refuse_the_other(
        api) -> None:
    """OctoPrint's `noOverwrite` refuses a file that is there: also one another upload of
    the same name is adding at that moment, which is not to become its version 1."""
    settings, url = api
    with db.session_scope(settings.resolved_database_url) as session:
        registry.upsert(session=session, machine_in=registry.MachineIn(
            id="1016", name="Sim-G", model="Mock"), data_dir=settings.data_dir)

    def uploaded_by_another(session: Session) -> None:  # what its upload writes
        library.add(session=session, folder="CAM", name="PART.gcode", approve=True,
                    blob=blobs.put(settings, [b"G1 X1\n"]))

    other = while_another_writes(
        settings.resolved_database_url, uploaded_by_another,
        lambda: _request(url, "POST", "/machines/1016/api/files/local",
                         files={"file": ("PART.gcode", b"G1 X2\n")},
                         data={"path": "CAM", "noOverwrite": "true"}))

    answer = other["result"]
    assert answer.status_code == 409, answer.text
    assert answer.json()["errorCode"] == 142 and "noOverwrite" in answer.json()["statusMsg"]
    with db.session_scope(settings.resolved_database_url) as session:
        assert [v.number for v in library.history(
            session=session, folder="CAM", name="PART.gcode")] == [1]
