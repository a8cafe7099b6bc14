"""Two admins saving one machine at the same moment: the later PUT replaces the machine
whole, as its answer shows it, and is never mixed with the other's (on PostgreSQL and on
SQLite)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from sqlalchemy.orm import Session

from jobs import db
from jobs.api.app import create_app
from jobs.fleet import registry
from jobs.settings import Settings
from tests.conftest import API_KEY
from tests.jobs.helpers import while_another_writes
from tests.live_server import serving

LATHE = {"id": "m1", "name": "Lathe", "model": "Mock", "tags": []}


@pytest.fixture
def api(settings: Settings, database_url: str) -> Iterator[tuple[Settings, str]]:
    """The API served on loopback over each database with machine m1; yields the settings
    and the server's URL."""
    settings = settings.model_copy(update={"database_url": database_url})
    with db.session_scope(database_url) as session:
        _save(session, settings, LATHE)
    with serving(create_app(settings)) as server:
        yield settings, server.url


def _save(session: Session, settings: Settings, machine: dict[str, Any]) -> None:
    registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(machine),
                    data_dir=settings.data_dir)


def _shown(url: str) -> dict[str, Any]:
    with httpx.Client(base_url=url, headers={"X-Api-Key": API_KEY}) as client:
        return client.get("/api/machines/m1").json()  # type: ignore[no-any-return]


def test_a_machine_put_while_another_admin_saves_it_is_stored_as_this_put_says(api) -> None:
    settings, url = api
    theirs = {**LATHE, "name": "Night lathe", "tags": ["night"], "max_concurrent": 2}
    mine = {**LATHE, "name": "Lathe 1"}  # the rest as it was read: the other's is replaced

    def put() -> httpx.Response:
        with httpx.Client(base_url=url, headers={"X-Api-Key": API_KEY}, timeout=60) as client:
            return client.put("/api/machines/m1", json=mine)

    other = while_another_writes(
        settings.resolved_database_url, lambda session: _save(session, settings, theirs), put)

    answer = other["result"]
    assert answer.status_code == 200, answer.text
    stored = _shown(url)
    assert (stored["name"], stored["tags"], stored["max_concurrent"]) == ("Lathe 1", [], 1)
    assert {k: stored[k] for k in answer.json()} == answer.json()  # as it was answered
