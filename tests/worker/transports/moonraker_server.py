"""A real Moonraker for the tests, installed from PyPI into a virtual environment of its own.

It runs without Klipper: its file manager works while it waits for Klipper's socket.
"""

from __future__ import annotations

import os
import re
import sqlite3
import subprocess
from pathlib import Path

import httpx

from tests.servers import free_port, stop_process, unavailable, wait_for_http, wait_for_port
from tests.worker.transports.venvs import venv_with

REQUIREMENT = "moonraker>=0.11,<0.12"

# Moonlight off: no announcement feeds fetched.
CONFIG = """\
[server]
host: 127.0.0.1
port: {port}
max_upload_size: {max_upload_mib}
klippy_uds_address: {data}/comms/klippy.sock

[announcements]
enable_moonlight: False
"""

# Loopback clients need no key; without this section's list every client needs one.
TRUSTED_LOOPBACK = """
[authorization]
trusted_clients:
    127.0.0.0/8
"""


class MoonrakerServer:
    """One Moonraker on a loopback port, its data folder (config, database, `gcodes`, and
    `tmp`, where its uploads arrive) in `data`; stopped and started again on the same port."""

    def __init__(self, data: Path, *, trusted_loopback: bool, max_upload_mib: int = 1024,
                 logs_requests: bool = False) -> None:
        self.data = data
        self.logs_requests = logs_requests  # every request in serve.log (its -v): `requests`
        for sub in ("config", "comms", "gcodes", "logs", "tmp"):
            (data / sub).mkdir(exist_ok=True)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        config = CONFIG.format(port=self.port, data=data, max_upload_mib=max_upload_mib)
        (data / "config" / "moonraker.conf").write_text(
            config + (TRUSTED_LOOPBACK if trusted_loopback else ""))
        self._python = venv_with("moonraker", REQUIREMENT)
        self._proc: subprocess.Popen[bytes] | None = None

    @property
    def gcodes(self) -> Path:
        return self.data / "gcodes"

    @property
    def api_key(self) -> str:
        """The key Moonraker made on its first start, read from its database."""
        database = self.data / "database" / "moonraker-sql.db"
        with sqlite3.connect(f"file:{database}?mode=ro", uri=True) as db:  # never makes one
            row = db.execute("SELECT password FROM authorized_users "
                             "WHERE username = '_API_KEY_USER_'").fetchone()
        return str(row[0])

    def start(self) -> None:
        log = open(self.data / "serve.log", "ab")  # noqa: SIM115 - the child holds it
        with log:
            # Its uploads arrive in TMPDIR: the test's own folder, not the host's /tmp.
            self._proc = subprocess.Popen(
                [str(self._python), "-m", "moonraker", "-d", str(self.data), "-n",
                 *(["-v"] if self.logs_requests else [])],
                stdout=log, stderr=subprocess.STDOUT,
                env={**os.environ, "TMPDIR": str(self.data / "tmp")})
        try:
            wait_for_port(self.port, timeout_s=60)
            # The file API answers only once every component is up (401 without a key).
            wait_for_http(lambda: httpx.get(f"{self.url}/server/files/directory",
                                            params={"path": "gcodes"}, timeout=5,
                                            headers=self._key_header()),
                          timeout_s=60)
        except (TimeoutError, httpx.HTTPError) as exc:
            self.stop()
            unavailable(f"Moonraker did not start ({exc}); see {self.data / 'serve.log'}")

    def _key_header(self) -> dict[str, str]:
        try:
            return {"X-Api-Key": self.api_key}
        except (sqlite3.Error, TypeError):  # no database yet, or no key in it yet
            return {}

    def stop(self) -> None:
        if self._proc is not None:
            stop_process(self._proc)
            self._proc = None

    def restart(self) -> None:
        self.stop()
        self.start()

    def requests(self, method: str, path: str) -> int:
        """How many `method path` requests it answered (with `logs_requests`)."""
        log = (self.data / "serve.log").read_text(errors="replace")
        return len(re.findall(rf" {method} {re.escape(path)}[? ]", log))
