"""Fixtures shared by the job tests: the CLI's environment, the CLI against a live API and
worker, a Redis of a test's own, and a webhook server that records what it receives."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from starlette.types import ASGIApp

from jobs import db
from jobs.api.app import create_app
from jobs.settings import get_settings
from tests.conftest import API_KEY
from tests.jobs.recording_server import Received, RecordingServer
from tests.live_server import LiveServer, serving
from tests.servers import RedisServer, redis_server


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A migrated database of each kind dncq runs on, one test each."""
    if request.param == "sqlite":
        url = f"sqlite:///{tmp_path / 'dncq.db'}"
        db.upgrade(url)
        return url
    return str(request.getfixturevalue("postgres_url"))


@pytest.fixture
def env(settings, monkeypatch, tmp_path) -> Iterator[Path]:
    """The CLI pointed at the test's data folder and key; runs in `tmp_path`."""
    monkeypatch.setenv("DNCQ_DATA_DIR", str(settings.data_dir))
    monkeypatch.setenv("DNCQ_API_KEY", API_KEY)
    monkeypatch.delenv("DNCQ_AUTH", raising=False)
    monkeypatch.chdir(tmp_path)
    get_settings.cache_clear()
    yield tmp_path
    get_settings.cache_clear()


@contextlib.contextmanager
def cli_elsewhere(app: ASGIApp, monkeypatch: pytest.MonkeyPatch,
                  tmp_path: Path) -> Iterator[LiveServer]:
    """`app` served on loopback, and the CLI run in an empty folder of its own
    (`tmp_path/elsewhere`) that knows only the API's URL and key (DNCQ_URL, DNCQ_API_KEY),
    not the data folder."""
    folder = tmp_path / "elsewhere"
    folder.mkdir()
    for name in ("DNCQ_DATA_DIR", "DNCQ_DATABASE_URL", "DNCQ_AUTH", "DNCQ_CONFIG_FILE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("DNCQ_API_KEY", API_KEY)
    monkeypatch.chdir(folder)
    with serving(app) as server:
        monkeypatch.setenv("DNCQ_URL", server.url)
        get_settings.cache_clear()
        yield server
    get_settings.cache_clear()


@pytest.fixture
def elsewhere(settings, monkeypatch, tmp_path) -> Iterator[Path]:
    """The test's dncq served on loopback, and the CLI run in an empty folder (`cli_elsewhere`)."""
    with cli_elsewhere(create_app(settings), monkeypatch, tmp_path):
        yield tmp_path / "elsewhere"


@pytest.fixture
def live_with_worker(queue_settings, celery_worker, add_machines, monkeypatch, tmp_path
                     ) -> Iterator[LiveServer]:
    """Three mock machines (two tagged lathes), the API on loopback with a worker behind it,
    the CLI pointed at it."""
    add_machines(*[{"id": f"m{i}", "name": f"M{i}", "model": "Mock",
                    "tags": ["lathes"] if i < 2 else []} for i in range(3)])
    monkeypatch.setenv("DNCQ_DATA_DIR", str(queue_settings.data_dir))
    monkeypatch.setenv("DNCQ_API_KEY", API_KEY)
    monkeypatch.chdir(tmp_path)
    with serving(create_app(queue_settings)) as server:
        monkeypatch.setenv("DNCQ_URL", server.url)
        get_settings.cache_clear()
        yield server
    get_settings.cache_clear()


@pytest.fixture
def own_broker(tmp_path: Path) -> Iterator[RedisServer]:
    """A Redis of this test's own, stopped after it: no other test's connections in its
    count (`tests.jobs.parts_asked`)."""
    (tmp_path / "redis").mkdir()
    with redis_server(tmp_path / "redis") as server:
        yield server


@pytest.fixture
def webhook_server() -> Iterator[Callable[..., RecordingServer]]:
    """Factory: start a recording HTTP server on loopback; every one is shut down after."""
    started: list[ThreadingHTTPServer] = []

    def start(*, status: int = 204) -> RecordingServer:
        recording = RecordingServer(port=0, status=status)

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - the name http.server calls
                length = int(self.headers.get("Content-Length", 0))
                recording.requests.append(Received("POST", self.path, dict(self.headers),
                                                   self.rfile.read(length)))
                self.send_response(recording.status)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, format: str, *args: object) -> None:
                pass  # keep the test output clean

        server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        server.daemon_threads = True
        recording.port = int(server.server_address[1])
        threading.Thread(target=server.serve_forever, daemon=True).start()
        started.append(server)
        return recording

    yield start
    for server in started:
        server.shutdown()
        server.server_close()
