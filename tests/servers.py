"""Real servers on loopback for the tests: Redis and PostgreSQL, started and stopped here.

A server whose program is missing skips its tests with the reason printed; under
CI (`CI=true`) that is a failure instead, so a green CI always ran them.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NoReturn

import httpx
import pytest


def free_port() -> int:
    """A TCP port nobody listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def unavailable(reason: str) -> NoReturn:
    """Skip (or, in CI, fail) because a server cannot be had."""
    if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
        pytest.fail(f"{reason} (CI must run these tests: install it in .ci/run)")
    pytest.skip(reason)


def wait_for_port(port: int, timeout_s: float = 20.0) -> None:
    """Block until something accepts connections on the loopback port."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"nothing listens on 127.0.0.1:{port} after {timeout_s} s")


def wait_for_http(request: Callable[[], httpx.Response], timeout_s: float) -> None:
    """Block until `request()` is answered with 200: a port opens before its app is ready."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            response = request()
            if response.status_code == 200 or time.monotonic() > deadline:
                response.raise_for_status()
                return
        except httpx.TransportError:
            if time.monotonic() > deadline:
                raise
        time.sleep(0.2)


def stop_process(proc: subprocess.Popen[bytes], timeout_s: float = 20.0) -> None:
    """Terminate a server's process, and kill it if it has not stopped in `timeout_s`."""
    proc.terminate()
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class RedisServer:
    """A redis-server process on a loopback port; can be killed and started again.

    With `appendonly`, every write is in its append-only file before Redis answers, so a
    kill loses nothing: started again, it has the queues and unacknowledged messages back.
    """

    def __init__(self, folder: Path, *, appendonly: bool = False) -> None:
        self.folder, self.appendonly = folder, appendonly
        self.port = free_port()
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        binary = shutil.which("redis-server")
        if binary is None:
            unavailable("redis-server is not installed (apt-get install -y redis-server)")
        self.proc = subprocess.Popen(
            [binary, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "",
             "--appendonly", "yes" if self.appendonly else "no", "--appendfsync", "always",
             "--dir", str(self.folder)],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wait_for_port(self.port)
        self._wait_until_loaded()

    def _wait_until_loaded(self, timeout_s: float = 30.0) -> None:
        """Started is serving: the port opens before Redis has read its append-only file
        back, and until then it answers every command with LOADING."""
        import redis

        client = redis.Redis.from_url(self.url)
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                client.ping()
                return
            except redis.exceptions.BusyLoadingError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)
            finally:
                client.close()

    def kill(self) -> None:
        """SIGKILL: whatever the queue held is gone."""
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self.proc = None

    def flush(self) -> None:
        import redis

        redis.Redis.from_url(self.url).flushall()


@contextmanager
def redis_server(folder: Path) -> Iterator[RedisServer]:
    """A running Redis, stopped afterwards."""
    server = RedisServer(folder)
    server.start()
    try:
        yield server
    finally:
        server.kill()


class PostgresServer:
    """A PostgreSQL cluster of its own, run as the `postgres` user; can be stopped and started."""

    def __init__(self, folder: Path, settings: dict[str, str] | None = None) -> None:
        initdb = shutil.which("initdb") or _pg_bin("initdb")
        pg_ctl = shutil.which("pg_ctl") or _pg_bin("pg_ctl")
        if not initdb or not pg_ctl:
            unavailable("PostgreSQL is not installed (apt-get install -y postgresql)")
        self.folder, self._pg_ctl = folder, pg_ctl
        self._settings = settings or {}
        self._as_postgres: list[str] = []
        if os.geteuid() == 0:  # the server refuses to run as root
            self._as_postgres = ["runuser", "-u", "postgres", "--"]
            shutil.chown(folder, "postgres")
        self._data = folder / "pgdata"
        self.port = free_port()
        self._started = False
        subprocess.run([*self._as_postgres, initdb, "-D", str(self._data), "--auth=trust",
                        "-U", "dncq", "--no-sync"], check=True, capture_output=True)

    @property
    def url(self) -> str:
        return f"postgresql+psycopg://dncq@127.0.0.1:{self.port}/postgres"

    def start(self) -> None:
        """Start the server; a first start whose port was taken meanwhile (it was free when
        picked, before initdb's seconds) tries another. A restart keeps its port."""
        tries = 1 if self._started else 3
        for attempt in range(1, tries + 1):
            try:
                self._start()
            except subprocess.CalledProcessError:
                log = (self.folder / "pg.log").read_text(errors="replace")
                if attempt == tries or "could not bind" not in log:
                    raise
                self.port = free_port()
            else:
                self._started = True
                return

    def _start(self) -> None:
        extra = "".join(f" -c {name}={value}" for name, value in self._settings.items())
        subprocess.run(
            [*self._as_postgres, self._pg_ctl, "-D", str(self._data), "-l",
             str(self.folder / "pg.log"), "-w", "-o",
             f"-p {self.port} -k {self.folder} -c listen_addresses=127.0.0.1 "
             f"-c fsync=off -c max_connections=300{extra}", "start"],
            check=True, capture_output=True)

    def stop(self) -> None:
        """An immediate shutdown: every connection is cut, as when the server crashes."""
        subprocess.run([*self._as_postgres, self._pg_ctl, "-D", str(self._data), "-m",
                        "immediate", "stop"], capture_output=True)


@contextmanager
def postgres_server(folder: Path,
                    settings: dict[str, str] | None = None) -> Iterator[PostgresServer]:
    """A running PostgreSQL cluster of its own in `folder` (with server `settings`, as
    `-c name=value`), stopped afterwards."""
    server = PostgresServer(folder, settings)
    server.start()
    try:
        yield server
    finally:
        server.stop()


@contextmanager
def postgres_of_its_own() -> Iterator[PostgresServer]:
    """`postgres_server` in a temporary folder, removed afterwards.

    Not under pytest's temporary root: that is private to its owner, and the server runs
    as the `postgres` user, who must reach its folder.
    """
    folder = Path(tempfile.mkdtemp(prefix="dncq-pg-"))
    try:
        with postgres_server(folder) as server:
            yield server
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _pg_bin(name: str) -> str | None:
    for version in ("17", "16", "15", "14"):
        candidate = Path(f"/usr/lib/postgresql/{version}/bin/{name}")
        if candidate.exists():
            return str(candidate)
    return None
