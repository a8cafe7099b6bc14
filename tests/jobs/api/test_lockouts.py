"""An administrator lists the addresses locked out for wrong API keys and ends one's
lock-out: its keys are taken again at once by the API process asked, and by every other one
once it asks the database again; the end is written to the audit trail."""

from __future__ import annotations

import time
from collections.abc import Iterator
from datetime import datetime

import httpx
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import delete, select

from jobs import db
from jobs.api.app import create_app
from jobs.api.key_lockout import LockedAddresses
from jobs.auth import service
from jobs.auth.models import AuditEvent, WrongKeyCount
from jobs.auth.roles import Role
from jobs.models import utcnow
from jobs.settings import Settings
from tests.conftest import API_KEY

GUESSER = "10.0.0.7"
ADMIN_HOST = "10.0.0.2"
MAX_FAILURES = 5  # DNCQ_SIGNIN_MAX_FAILURES' default
GUESS = "guess-4f2a9c1e"


def _as(app: FastAPI, address: str) -> TestClient:
    """A client of the API process `app` whose requests come from `address`."""
    return TestClient(app, client=(address, 50000), raise_server_exceptions=False)


@pytest.fixture
def on_database(settings: Settings, database_url: str) -> Settings:
    """The test's dncq on each database, no wrong key counted nor audit event written yet
    (the PostgreSQL database is the module's)."""
    with db.session_scope(database_url) as session:
        session.execute(delete(WrongKeyCount))
        session.execute(delete(AuditEvent))
    return settings.model_copy(update={"database_url": database_url})


@pytest.fixture
def api(on_database: Settings) -> Iterator[FastAPI]:
    yield create_app(on_database)


def _wrong(client: TestClient, times: int) -> list[int]:
    return [client.get("/api/machines", headers={"X-Api-Key": f"{GUESS}-{n}"}).status_code
            for n in range(times)]


def _right(client: TestClient) -> int:
    return client.get("/api/machines", headers={"X-Api-Key": API_KEY}).status_code


def _admin(client: TestClient, method: str, path: str) -> httpx.Response:
    return client.request(method, path, headers={"X-Api-Key": API_KEY})


def test_an_admin_lists_the_locked_address_and_the_one_with_wrong_keys_counted(api) -> None:
    with _as(api, GUESSER) as guesser, _as(api, "10.0.0.8") as typo, \
            _as(api, ADMIN_HOST) as admin:
        _wrong(guesser, MAX_FAILURES)
        _wrong(typo, 2)

        listed = _admin(admin, "GET", "/api/lockouts").json()

    assert [(e["address"], e["counted"], e["failures"]) for e in listed] == [
        (GUESSER, "api keys", MAX_FAILURES), ("10.0.0.8", "api keys", 2)]
    assert datetime.fromisoformat(listed[0]["lockedUntil"]) > utcnow()
    assert listed[0]["failedSince"] is not None  # what locked it out, and since when
    assert listed[1]["lockedUntil"] is None and listed[1]["failedSince"] is not None


def test_an_admin_ends_a_lock_out_and_the_right_key_from_the_address_is_taken_again(
        api) -> None:
    with _as(api, GUESSER) as guesser, _as(api, ADMIN_HOST) as admin:
        _wrong(guesser, MAX_FAILURES)
        assert _right(guesser) == 429

        ended = _admin(admin, "DELETE", f"/api/lockouts/{GUESSER}")

        assert ended.status_code == 200
        assert ended.json()["address"] == GUESSER
        assert [e["counted"] for e in ended.json()["ended"]] == ["api keys"]
        assert _right(guesser) == 200
        assert _admin(admin, "GET", "/api/lockouts").json() == []
        # Its wrong keys count from nothing again.
        assert _wrong(guesser, MAX_FAILURES) == [403] * (MAX_FAILURES - 1) + [429]


def test_the_end_of_a_lock_out_is_written_to_the_audit_trail(api, on_database) -> None:
    with _as(api, GUESSER) as guesser, _as(api, ADMIN_HOST) as admin:
        _wrong(guesser, MAX_FAILURES)
        _admin(admin, "DELETE", f"/api/lockouts/{GUESSER}")

    with db.session_scope(on_database.resolved_database_url) as session:
        events = [(e.action, e.target, e.who, e.address, e.status)
                  for e in session.scalars(select(AuditEvent).order_by(AuditEvent.id))]

    assert events == [("lock out", GUESSER, "-", GUESSER, 429),
                      ("lockouts.end", GUESSER, "admin-key", ADMIN_HOST, 200)]


def test_another_api_process_takes_the_address_again_once_it_asks_the_database(
        api, on_database) -> None:
    other = create_app(on_database)
    with _as(other, GUESSER) as guesser_there:
        other.state.locked_addresses = LockedAddresses(recheck_s=0.0)  # asks at every key
        with _as(api, GUESSER) as guesser, _as(api, ADMIN_HOST) as admin:
            _wrong(guesser, MAX_FAILURES)
            assert _wrong(guesser_there, 1) == [429]  # the other process knows it now
            assert _right(guesser_there) == 429

            _admin(admin, "DELETE", f"/api/lockouts/{GUESSER}")

        assert _right(guesser_there) == 200


def test_an_address_sending_keys_all_the_time_is_taken_again_once_the_other_process_asks(
        api, on_database) -> None:
    # Each refusal from memory had counted as a fresh read: an address sending keys more
    # often than the recheck period was never asked about again, its lock-out ended or not.
    other = create_app(on_database)
    with _as(other, GUESSER) as guesser_there:
        other.state.locked_addresses = LockedAddresses(recheck_s=0.3)
        with _as(api, GUESSER) as guesser, _as(api, ADMIN_HOST) as admin:
            _wrong(guesser, MAX_FAILURES)
            assert _wrong(guesser_there, 1) == [429]
            _admin(admin, "DELETE", f"/api/lockouts/{GUESSER}")

        answers = []
        for _ in range(40):  # a key every 50 ms, for 2 s
            answers.append(_right(guesser_there))
            if answers[-1] == 200:
                break
            time.sleep(0.05)

    assert answers[-1] == 200, answers


def test_ending_an_ipv6_address_ends_the_lock_out_of_its_64(api) -> None:
    with _as(api, "2001:db8:7:1::5") as guesser, _as(api, "2001:db8:7:1::9") as same_host, \
            _as(api, ADMIN_HOST) as admin:
        _wrong(guesser, MAX_FAILURES)
        assert _right(same_host) == 429

        ended = _admin(admin, "DELETE", "/api/lockouts/2001:db8:7:1::5")

        assert ended.json()["address"] == "2001:db8:7:1::/64"
        assert _right(same_host) == 200


def test_a_lock_out_is_ended_by_the_64_as_listed(api) -> None:
    with _as(api, "2001:db8:7:1::5") as guesser, _as(api, ADMIN_HOST) as admin:
        _wrong(guesser, MAX_FAILURES)
        listed = _admin(admin, "GET", "/api/lockouts").json()[0]["address"]

        ended = _admin(admin, "DELETE", "/api/lockouts/" + listed.replace("/", "%2F"))

        assert (listed, ended.status_code) == ("2001:db8:7:1::/64", 200)
        assert _right(guesser) == 200


def test_ending_an_address_without_wrong_keys_is_404_and_changes_nothing(api) -> None:
    with _as(api, GUESSER) as guesser, _as(api, ADMIN_HOST) as admin:
        _wrong(guesser, MAX_FAILURES)

        refused = _admin(admin, "DELETE", "/api/lockouts/10.0.0.9")

        assert refused.status_code == 404
        assert refused.json()["statusMsg"] == ("no wrong API keys nor failed sign-ins are "
                                               "counted for 10.0.0.9")
        assert _right(guesser) == 429


def test_a_programmer_key_may_not_end_a_lock_out(api, on_database) -> None:
    with db.session_scope(on_database.resolved_database_url) as session:
        _, programmer = service.create_key(session=session, name="ci", role=Role.PROGRAMMER)
    with _as(api, GUESSER) as guesser, _as(api, ADMIN_HOST) as admin:
        _wrong(guesser, MAX_FAILURES)

        refused = admin.delete(f"/api/lockouts/{GUESSER}", headers={"X-Api-Key": programmer})

        assert refused.status_code == 403
        assert _right(guesser) == 429
