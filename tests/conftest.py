"""Fixtures shared by every test: a data folder, a migrated database, an app, a fleet."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from jobs import db, machines
from jobs.api.app import create_app
from jobs.settings import AuthMode, Settings

API_KEY = "test-key-0123456789"


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    """Settings of a fresh dncq: its own data folder and SQLite database, a known API key."""
    data = tmp_path / "data"
    data.mkdir()
    s = Settings(data_dir=data, api_key=API_KEY, auth=AuthMode.KEY)
    db.upgrade(s.resolved_database_url)
    return s


@pytest.fixture
def add_machines(settings: Settings) -> Callable[..., list[machines.MachineSpec]]:
    """Factory: register machines given as fleet-file entries."""

    def add(*entries: dict[str, Any]) -> list[machines.MachineSpec]:
        with db.session_scope(settings.resolved_database_url) as session:
            return [
                machines.upsert(session=session, machine_in=machines.MachineIn.model_validate(e))[0]
                for e in entries
            ]

    return add


@pytest.fixture
def client(settings: Settings) -> Iterator[TestClient]:
    """The HTTP API of that dncq, with the API key sent on every request."""
    with TestClient(create_app(settings), headers={"X-Api-Key": API_KEY}) as c:
        yield c


@pytest.fixture
def demo_fleet(settings: Settings) -> None:
    """The demo fleet with its sample programs."""
    from jobs import demo

    with db.session_scope(settings.resolved_database_url) as session:
        demo.create(session=session, data_dir=settings.data_dir)
