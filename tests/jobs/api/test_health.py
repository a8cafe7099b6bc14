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
from tests.servers import RedisServer


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
