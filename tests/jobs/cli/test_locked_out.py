"""The CLI from an address locked out for wrong API keys: every command says so in one line,
until when and where its key came from, exits LOCKED_OUT, and asks dncq nothing more."""

from __future__ import annotations

import re
import threading
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import httpx
import pytest
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from jobs.api.app import create_app
from jobs.cli.client import LOCKED_OUT_EXIT
from jobs.local_times import local_text
from jobs.settings import Settings
from tests.conftest import API_KEY
from tests.jobs.cli.runner import dncq
from tests.jobs.conftest import cli_elsewhere
from tests.live_server import HTTP_TIMEOUT_S, LiveServer
from tests.servers import RedisServer

MAX_FAILURES = 2  # wrong keys that lock an address out, at the dncq these tests serve
LOCKOUT_S = 600.0
LOCKED_LINE = re.compile(
    r"error: 20429 Too many wrong API keys: this address \(127\.0\.0\.1\) is locked out for "
    r"wrong API keys until (?P<until>\d{4}-\d\d-\d\d \d\d:\d\d:\d\d \S+): dncq refuses every "
    r"key from it until then, the right one too; an admin ends it sooner with `dncq lockouts "
    r"end 127\.0\.0\.1` from another address, or with --local on dncq's host; the CLI sent "
    r"the key set by DNCQ_API_KEY")


class Answers:
    """An app that notes the status of each answer it sends, by the request's path."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self.statuses: list[tuple[str, int]] = []

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def noted(message: Message) -> None:
            if message["type"] == "http.response.start":
                self.statuses.append((scope["path"], message["status"]))
            await send(message)

        await self.app(scope, receive, noted)

    def refused(self) -> int:
        """How many answers were 429s."""
        return sum(status == 429 for _, status in self.statuses)


@pytest.fixture
def served(settings: Settings, own_broker: RedisServer, add_machines: Callable[..., Any],
           monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[tuple[LiveServer, Answers]]:
    """A dncq that locks an address out after MAX_FAILURES wrong keys, with a mock machine
    `sim` and a broker no worker reads (a job stays queued), served on loopback; the CLI
    pointed at it from an empty folder with the right key."""
    add_machines({"id": "sim", "name": "Sim", "model": "Mock"})
    strict = settings.model_copy(update={
        "broker_url": own_broker.url, "signin_max_failures": MAX_FAILURES,
        "signin_lockout_s": LOCKOUT_S})
    answers = Answers(create_app(strict))
    with cli_elsewhere(answers, monkeypatch, tmp_path) as server:
        yield server, answers


def _lock_out(server: LiveServer) -> None:
    """Send MAX_FAILURES wrong keys from loopback, the address the CLI's requests come from."""
    with httpx.Client(base_url=server.url, timeout=HTTP_TIMEOUT_S) as c:
        statuses = [c.get("/api/machines", headers={"X-Api-Key": f"guess-{n}"}).status_code
                    for n in range(MAX_FAILURES)]
    assert statuses[-1] == 429


def _said_locked(output: str, *, asked_at: datetime) -> None:
    """`output` is the one line of a lock-out, its end in local time LOCKOUT_S after `asked_at`."""
    said = " ".join(output.split())
    found = LOCKED_LINE.fullmatch(said)
    assert found, said
    earliest = local_text(asked_at + timedelta(seconds=LOCKOUT_S - 5), seconds=True)
    latest = local_text(asked_at + timedelta(seconds=LOCKOUT_S + 5), seconds=True)
    assert earliest <= found["until"] <= latest
    assert API_KEY not in output


# A read and a change of each way the CLI asks dncq: a JSON answer, a file, a CSV, a job
# queued with its file, a program uploaded.
COMMANDS = {
    "machines list": ("machines", "list"),
    "get": ("get", "sim", "P1", "-o", "-"),
    "audit --csv": ("audit", "--csv"),
    "cancel": ("cancel", "0123456789abcdef"),
    "send": ("send", "{file}", "--to", "sim", "--no-wait"),
    "library add": ("library", "add", "{file}", "--folder", "VIPROS"),
}


@pytest.mark.parametrize("command", COMMANDS)
def test_a_command_from_a_locked_address_says_so_until_when_and_exits_locked_out(
        served: tuple[LiveServer, Answers], program: Path, command: str) -> None:
    server, answers = served
    _lock_out(server)
    asked_at = datetime.now(UTC)

    result = dncq(*(arg.format(file=program) for arg in COMMANDS[command]))

    assert result.exit_code == LOCKED_OUT_EXIT
    _said_locked(result.output, asked_at=asked_at)
    assert answers.refused() == 2  # the guess that locked it, and the command's one request


def _queued_job(server: LiveServer, request: dict[str, Any]) -> str:
    with httpx.Client(base_url=server.url, timeout=HTTP_TIMEOUT_S,
                      headers={"X-Api-Key": API_KEY}) as c:
        answer = c.post("/api/jobs", json=request)
    assert answer.status_code == 202, answer.text
    return str(answer.json()["id"])


# A backup job's watch goes on to the stored backup once the job has ended, or failed.
JOBS = {
    "delete": {"kind": "delete", "machines": {"ids": ["sim"]}, "fileName": "P1"},
    "backup": {"kind": "backup", "machines": {"ids": ["sim"]}},
}


@pytest.mark.parametrize("kind", JOBS)
def test_watching_a_job_ends_at_the_first_refusal_once_the_address_is_locked_out(
        served: tuple[LiveServer, Answers], kind: str) -> None:
    server, answers = served
    job_id = _queued_job(server, JOBS[kind])  # no worker: it stays queued, the watch goes on

    def lock_out_while_watched() -> None:
        # Once the watch has asked for the job a few times, as it goes on doing.
        while sum(path == f"/api/jobs/{job_id}" for path, _ in answers.statuses) < 3:
            threading.Event().wait(0.05)
        _lock_out(server)

    guesser = threading.Thread(target=lock_out_while_watched, daemon=True)
    guesser.start()
    asked_at = datetime.now(UTC)

    result = dncq("job", job_id, "--watch")

    guesser.join(HTTP_TIMEOUT_S)
    assert result.exit_code == LOCKED_OUT_EXIT
    _said_locked(result.output, asked_at=asked_at)
    assert answers.refused() == 2  # the guess that locked it, and the watch's next ask
    assert answers.statuses[-1] == (f"/api/jobs/{job_id}", 429)  # and nothing asked after
