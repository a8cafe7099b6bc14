"""Wrong API keys counted per client address: after too many, every key from that address,
the right one too, is refused with 429 until the lock-out ends; other addresses go on, a
locked address costs the database nothing, and the lock-out is written once to the trail."""

from __future__ import annotations

import time
from collections.abc import Iterator

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import delete, select

from jobs import db
from jobs.api.app import create_app
from jobs.auth import service
from jobs.auth.models import AuditEvent, WrongKeyCount
from jobs.auth.roles import Role
from jobs.settings import Settings
from tests.conftest import API_KEY
from tests.jobs.parts_asked import parts_asked
from tests.live_server import HTTP_TIMEOUT_S, serving
from tests.servers import RedisServer

GUESSER = "10.0.0.7"
NEIGHBOUR = "10.0.0.8"
MAX_FAILURES = 5  # DNCQ_SIGNIN_MAX_FAILURES' default
GUESS = "guess-4f2a9c1e"  # a wrong key, looked for in everything written


def _as(settings: Settings, address: str) -> TestClient:
    """A client of the API whose requests come from `address`."""
    return TestClient(create_app(settings), client=(address, 50000),
                      raise_server_exceptions=False)


@pytest.fixture
def guesser(settings: Settings, add_machines) -> Iterator[TestClient]:
    add_machines({"id": "sim", "name": "Sim", "model": "Mock"})
    with _as(settings, GUESSER) as c:
        yield c


def _wrong(client: TestClient, times: int) -> list[int]:
    return [client.get("/api/machines", headers={"X-Api-Key": f"{GUESS}-{n}"}).status_code
            for n in range(times)]


def _right(client: TestClient, path: str = "/api/machines") -> httpx.Response:
    return client.get(path, headers={"X-Api-Key": API_KEY})


def test_the_right_key_after_too_many_wrong_ones_from_its_address_is_refused_429(guesser):
    assert _wrong(guesser, MAX_FAILURES) == [403] * (MAX_FAILURES - 1) + [429]

    refused = _right(guesser)

    assert refused.status_code == 429
    body = refused.json()
    assert (body["errorCode"], body["errorMsg"]) == (20429, "Too many wrong API keys.")
    assert body["statusMsg"].startswith(f"too many wrong API keys came from {GUESSER}: every "
                                        "key from it is refused for ")
    assert 0 < int(refused.headers["Retry-After"]) <= 900


def test_a_wrong_key_counts_whichever_way_it_comes(guesser, settings):
    with db.session_scope(settings.resolved_database_url) as session:
        _, named = service.create_key(session=session, name="cell", role=Role.OPERATOR)
    statuses = [
        guesser.get("/api/machines", headers={"X-Api-Key": GUESS}).status_code,
        guesser.get("/api/machines", headers={"Authorization": f"Bearer {GUESS}"}).status_code,
        guesser.get("/api/machines", params={"apikey": GUESS}).status_code,
        guesser.get("/api/machines", headers={"X-Api-Key": f"{GUESS}@sim"}).status_code,
        guesser.get("/api/cnc/readProgramList", params={"machineID": "sim"},
                    headers={"X-Api-Key": GUESS}).status_code,
    ]

    assert statuses == [403, 403, 403, 403, 429]
    assert guesser.get("/api/machines", headers={"X-Api-Key": named}).status_code == 429
    assert guesser.get("/api/machines", headers={"X-Api-Key": f"{API_KEY}@sim"}
                       ).status_code == 429


def test_the_right_key_from_another_address_is_still_taken(guesser, settings):
    _wrong(guesser, MAX_FAILURES)

    with _as(settings, NEIGHBOUR) as neighbour:
        assert _right(neighbour).status_code == 200


def test_a_request_without_a_key_from_a_locked_address_is_still_answered_401(guesser):
    _wrong(guesser, MAX_FAILURES)

    assert guesser.get("/api/machines").status_code == 401


def test_a_right_key_between_wrong_ones_gives_the_guesser_no_more_of_them(guesser):
    assert _wrong(guesser, MAX_FAILURES - 1) == [403] * (MAX_FAILURES - 1)
    assert _right(guesser).status_code == 200

    assert _wrong(guesser, 1) == [429]


def test_the_right_key_is_taken_again_once_the_lock_out_has_passed(settings, add_machines):
    short = settings.model_copy(update={"signin_lockout_s": 1.0})
    with _as(short, GUESSER) as guesser:
        _wrong(guesser, MAX_FAILURES)
        assert _right(guesser).status_code == 429

        time.sleep(1.2)  # the lock-out's end, not a timing assert

        assert _right(guesser).status_code == 200


def test_a_revoked_key_is_refused_401_and_not_counted_as_a_guess(guesser, settings):
    with db.session_scope(settings.resolved_database_url) as session:
        _, revoked = service.create_key(session=session, name="old", role=Role.VIEWER)
        service.revoke_key(session=session, name="old")

    statuses = [guesser.get("/api/machines", headers={"X-Api-Key": revoked}).status_code
                for _ in range(MAX_FAILURES + 1)]

    assert statuses == [401] * (MAX_FAILURES + 1)
    assert _right(guesser).status_code == 200


def test_a_locked_address_is_refused_without_a_database_statement(
        guesser, settings, own_broker: RedisServer):
    with db.session_scope(settings.resolved_database_url) as session:
        _, named = service.create_key(session=session, name="cell", role=Role.OPERATOR)
    _wrong(guesser, MAX_FAILURES)

    with parts_asked(own_broker) as asked:
        statuses = [
            *_wrong(guesser, 20),
            _right(guesser).status_code,
            _right(guesser, "/api/health?only=limits").status_code,
            guesser.get("/api/machines", headers={"X-Api-Key": named}).status_code,
            guesser.post("/api/cnc/sendFile", params={"machineID": "sim", "fileName": "P1"},
                         json={"content": "G0"}, headers={"X-Api-Key": GUESS}).status_code,
        ]

    assert statuses == [429] * 24
    assert asked.statements == []  # no count, no audit entry, not even a read


def test_an_address_another_api_process_locked_is_refused_there_after_one_read(
        guesser, settings, own_broker: RedisServer):
    # Two processes of the API sharing one database: guesses sent to both count together.
    with _as(settings, GUESSER) as other_process:
        assert _wrong(guesser, 3) + _wrong(other_process, 2) == [403] * 4 + [429]

        with parts_asked(own_broker) as asked:
            statuses = _wrong(guesser, 3)

    assert statuses == [429] * 3
    assert [s.split()[0] for s in asked.statements] == ["SELECT"]  # the first one's, no write


def test_a_lock_out_is_written_once_to_the_audit_trail_and_never_a_key(guesser, settings):
    _wrong(guesser, MAX_FAILURES + 3)
    guesser.post("/api/cnc/sendFile", params={"machineID": "sim", "fileName": "P1"},
                 json={"content": "G0"}, headers={"X-Api-Key": GUESS})

    with db.session_scope(settings.resolved_database_url) as session:
        events = list(session.scalars(select(AuditEvent)))
        written = [(e.action, e.target, e.who, e.address, e.status, e.method, e.path,
                    e.detail["failures"]) for e in events]
        every_value = repr([vars(e) for e in events])

    assert written == [("lock out", GUESSER, "-", GUESSER, 429, "GET", "/api/machines",
                        MAX_FAILURES)]
    assert GUESS not in every_value and API_KEY not in every_value


def test_behind_a_trusted_proxy_each_forwarded_address_is_counted_apart(settings, add_machines):
    # A real uvicorn, which takes X-Forwarded-For from its loopback proxy.
    add_machines({"id": "sim", "name": "Sim", "model": "Mock"})
    with serving(create_app(settings)) as server, httpx.Client(
            base_url=server.url, timeout=HTTP_TIMEOUT_S) as http:
        def asked(key: str, address: str) -> int:
            return http.get("/api/machines", headers={
                "X-Api-Key": key, "X-Forwarded-For": address}).status_code

        guessed = [asked(GUESS, GUESSER) for _ in range(MAX_FAILURES)]

        assert guessed[-1] == 429 and asked(API_KEY, GUESSER) == 429
        assert asked(API_KEY, NEIGHBOUR) == 200


def test_guesses_from_one_ipv6_host_add_up_whichever_of_its_addresses_they_come_from(
        settings: Settings, add_machines) -> None:
    """A host is given a whole /64 and may pick a new address in it for every guess."""
    add_machines({"id": "sim", "name": "Sim", "model": "Mock"})
    app = create_app(settings)  # one API process, which learns of the lock-out

    def client_at(address: str) -> TestClient:
        return TestClient(app, client=(address, 50000), raise_server_exceptions=False)

    statuses = []
    for n in range(MAX_FAILURES):
        with client_at(f"2001:db8:7:1::{n + 1:x}") as client:
            statuses += _wrong(client, 1)
    with client_at("2001:db8:7:1:ffff::9") as same_host, \
            client_at("2001:db8:7:2::1") as next_network:
        locked, other = _right(same_host), _right(next_network)

    assert statuses == [403] * (MAX_FAILURES - 1) + [429]
    assert locked.status_code == 429
    assert "came from 2001:db8:7:1::/64:" in locked.json()["statusMsg"]
    assert other.status_code == 200



def test_an_api_process_started_after_the_lock_out_refuses_the_right_key_from_the_address(
        settings: Settings, database_url: str) -> None:
    on_database = settings.model_copy(update={"database_url": database_url})
    with db.session_scope(database_url) as session:  # the PostgreSQL database is the module's
        session.execute(delete(WrongKeyCount))
    with _as(on_database, GUESSER) as guesser:
        assert _wrong(guesser, MAX_FAILURES)[-1] == 429

    with _as(on_database, GUESSER) as restarted, _as(on_database, NEIGHBOUR) as neighbour:
        refused, taken = _right(restarted), _right(neighbour)

    assert refused.status_code == 429
    assert refused.json()["errorCode"] == 20429
    assert taken.status_code == 200
