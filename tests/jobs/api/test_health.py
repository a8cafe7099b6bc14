"""`/api/health?only=limits`: the limits a client checks a file against before it sends it,
answered without asking the database or the broker, and only with the key."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from jobs import __version__
from jobs.api.app import create_app
from jobs.api.routes.health import limits
from jobs.settings import Settings
from tests.conftest import API_KEY
from tests.jobs.parts_asked import parts_asked
from tests.servers import RedisServer, free_port


@pytest.fixture
def queued(settings: Settings, own_broker: RedisServer) -> Settings:
    """Settings of a dncq whose broker is `own_broker`."""
    return settings.model_copy(update={"broker_url": own_broker.url})


def test_the_limits_alone_are_answered_without_asking_the_database_or_the_broker(
        queued: Settings, own_broker: RedisServer) -> None:
    # The CLI asks them before every upload: the whole report ran a statement, a query of
    # the runs and a connection to the broker (2 s and more when the broker was down).
    with TestClient(create_app(queued)) as c, parts_asked(own_broker) as asked:
        response = c.get("/api/health", params={"only": "limits"},
                         headers={"X-Api-Key": API_KEY})

    assert response.status_code == 200
    assert response.json() == {"version": __version__, "limits": limits(queued)}
    assert (asked.statements, asked.broker_connections) == ([], 0)


def test_the_limits_alone_are_not_shown_without_a_key(queued: Settings) -> None:
    with TestClient(create_app(queued)) as c:
        response = c.get("/api/health", params={"only": "limits"})

    assert response.status_code == 200
    assert response.json() == {"status": "ok"}  # as a load balancer's probe is answered


def test_the_api_starts_and_says_so_while_its_database_cannot_be_reached(
        settings: Settings) -> None:
    # The API reads the addresses locked out for wrong keys as it starts: a database started
    # after it (or down for a moment) must not keep it from serving its health.
    nowhere = settings.model_copy(update={
        "database_url": f"postgresql+psycopg://dncq@127.0.0.1:{free_port()}/dncq"})
    with TestClient(create_app(nowhere)) as c:
        response = c.get("/api/health", headers={"X-Api-Key": API_KEY})

    assert response.status_code == 200
    assert response.json()["status"] == "degraded"
    assert response.json()["database"].startswith("error")
