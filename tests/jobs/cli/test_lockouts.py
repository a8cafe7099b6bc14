"""`dncq lockouts list` and `dncq lockouts end`: an address locked out for wrong API keys
listed and ended through the API from another address, or from the locked host itself in
dncq's database (`--local`), which every API process then takes again."""

from __future__ import annotations

import getpass
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import select

from jobs import db
from jobs.api.app import create_app
from jobs.api.key_lockout import LockedAddresses
from jobs.auth.models import AuditEvent
from jobs.cli.client import LOCKED_OUT_EXIT
from jobs.settings import Settings, get_settings
from tests.conftest import API_KEY
from tests.jobs.cli.runner import dncq, table_rows
from tests.jobs.conftest import cli_elsewhere
from tests.live_server import HTTP_TIMEOUT_S, LiveServer

MAX_FAILURES = 2  # wrong keys that lock an address out, at the dncq these tests serve
GUESSER = "10.0.0.7"  # forwarded by loopback, which uvicorn trusts as a proxy


@pytest.fixture
def served(settings: Settings, add_machines: Callable[..., Any],
           monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[LiveServer]:
    """A dncq that locks an address out after MAX_FAILURES wrong keys and asks its database
    about a locked address at every key, served on loopback; the CLI pointed at it."""
    add_machines({"id": "sim", "name": "Sim", "model": "Mock"})
    app = create_app(settings.model_copy(update={"signin_max_failures": MAX_FAILURES}))
    app.state.locked_addresses = LockedAddresses(recheck_s=0.0)
    with cli_elsewhere(app, monkeypatch, tmp_path) as server:
        yield server


def _asked(server: LiveServer, key: str, address: str | None = None) -> int:
    headers = {"X-Api-Key": key, **({"X-Forwarded-For": address} if address else {})}
    with httpx.Client(base_url=server.url, timeout=HTTP_TIMEOUT_S) as c:
        return c.get("/api/machines", headers=headers).status_code


def _lock_out(server: LiveServer, address: str | None = None) -> None:
    statuses = [_asked(server, f"guess-{n}", address) for n in range(MAX_FAILURES)]
    assert statuses[-1] == 429


def test_lockouts_list_shows_the_locked_address_until_when(served) -> None:
    _lock_out(served, GUESSER)

    result = dncq("lockouts", "list", width=120)

    assert result.exit_code == 0, result.output
    [row] = table_rows(result.output)
    assert row["address"] == GUESSER and row["counted"] == "api keys"
    assert row["state"].startswith("locked until 20")


def test_lockouts_end_from_another_address_takes_the_address_keys_again(served) -> None:
    _lock_out(served, GUESSER)
    assert _asked(served, API_KEY, GUESSER) == 429

    result = dncq("lockouts", "end", GUESSER)

    assert result.exit_code == 0, result.output
    assert result.output == f"Ended the lock-out of {GUESSER} (api keys): it is taken again.\n"
    assert _asked(served, API_KEY, GUESSER) == 200


def test_lockouts_end_from_the_locked_host_is_refused_there_and_done_with_local(
        served, settings, monkeypatch) -> None:
    _lock_out(served)  # the CLI's own address, loopback

    refused = dncq("lockouts", "end", "127.0.0.1")
    monkeypatch.setenv("DNCQ_DATA_DIR", str(settings.data_dir))  # on dncq's host
    get_settings.cache_clear()
    ended = dncq("lockouts", "end", "127.0.0.1", "--local")

    assert refused.exit_code == LOCKED_OUT_EXIT
    assert ended.exit_code == 0, ended.output
    assert ended.output.startswith("Ended the lock-out of 127.0.0.1 (api keys) in the database "
                                   "sqlite:///")
    assert "every API process takes its keys again within 10 s" in ended.output
    assert _asked(served, API_KEY) == 200
    with db.session_scope(settings.resolved_database_url) as session:
        [event] = session.scalars(select(AuditEvent).where(AuditEvent.action == "lockouts.end"))
        assert (event.who, event.target, event.path) == (
            f"local:{getpass.getuser()}", "127.0.0.1", "dncq lockouts end --local")


def test_lockouts_end_local_of_an_address_not_counted_says_so(
        served, settings, monkeypatch) -> None:
    monkeypatch.setenv("DNCQ_DATA_DIR", str(settings.data_dir))
    get_settings.cache_clear()

    result = dncq("lockouts", "end", "10.0.0.9", "--local")

    assert result.exit_code == 1
    assert result.output == ("error: no wrong API keys nor failed sign-ins are counted for "
                             "10.0.0.9\n")
