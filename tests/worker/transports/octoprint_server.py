"""A real OctoPrint for the tests, installed from PyPI into a virtual environment of its own."""

from __future__ import annotations

import contextlib
import secrets
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import yaml

from tests.servers import free_port, stop_process, unavailable, wait_for_http, wait_for_port
from tests.worker.transports.venvs import venv_with

REQUIREMENT = "OctoPrint>=1.11,<1.12"

CONFIG = {
    "server": {
        "firstRun": False,
        "onlineCheck": {"enabled": False},
        "pluginBlacklist": {"enabled": False},
        "pythonEolCheck": {"enabled": False},
    },
    "plugins": {  # the bundled plugins that reach the internet or the network
        "_disabled": ["announcements", "softwareupdate", "pluginmanager", "tracking",
                      "errortracking", "discovery", "backup", "file_check", "firmware_check",
                      "pi_support", "health_check"],
    },
}

# OctoPrint takes only the extensions its tree knows (gcode, gco, g); a CNC shop's
# OctoPrint adds its program extensions the same way, through this hook.
EXTENSIONS_PLUGIN = '''
__plugin_name__ = "dncq test extensions"
__plugin_pythoncompat__ = ">=3.7,<4"


def _extension_tree(*args, **kwargs):
    return {"machinecode": {"cnc": ["nc", "bin"]}}


__plugin_hooks__ = {"octoprint.filemanager.extension_tree": _extension_tree}
'''


@dataclass(frozen=True)
class OctoPrintServer:
    url: str
    api_key: str


@contextlib.contextmanager
def running_octoprint(base: Path) -> Iterator[OctoPrintServer]:
    """A real OctoPrint on a loopback port with an admin user and its API key; its
    configuration, users and log in `base`."""
    python = venv_with("octoprint", REQUIREMENT)
    (base / "config.yaml").write_text(yaml.safe_dump(CONFIG))
    (base / "plugins").mkdir()
    (base / "plugins" / "dncq_test_extensions.py").write_text(EXTENSIONS_PLUGIN)
    octoprint = [str(python), "-m", "octoprint", "-b", str(base)]
    made = subprocess.run([*octoprint, "user", "add", "--admin", "--password",
                           secrets.token_hex(16), "dncq"], capture_output=True, timeout=120)
    if made.returncode != 0:
        unavailable(f"octoprint user add failed: {made.stderr.decode(errors='replace')[-500:]}")
    api_key = secrets.token_hex(16)
    users = yaml.safe_load((base / "users.yaml").read_text())
    users["dncq"]["apikey"] = api_key
    (base / "users.yaml").write_text(yaml.safe_dump(users))
    port = free_port()
    log = open(base / "serve.log", "wb")  # noqa: SIM115 - closed after the server stops
    proc = subprocess.Popen([*octoprint, "serve", "--iknowwhatimdoing", "--host", "127.0.0.1",
                             "--port", str(port)], stdout=log, stderr=subprocess.STDOUT)
    try:
        url = f"http://127.0.0.1:{port}"
        try:
            wait_for_port(port, timeout_s=90)
            wait_for_http(lambda: httpx.get(f"{url}/api/version",
                                            headers={"X-Api-Key": api_key}, timeout=5),
                          timeout_s=90)
        except (TimeoutError, httpx.HTTPError) as exc:
            unavailable(f"OctoPrint did not start ({exc}); see {base / 'serve.log'}")
        yield OctoPrintServer(url, api_key)
    finally:
        stop_process(proc)
        log.close()


def empty_octoprint(server: OctoPrintServer) -> None:
    """Delete everything in the local origin (folders recursively)."""
    headers = {"X-Api-Key": server.api_key}
    with httpx.Client(base_url=server.url, headers=headers, timeout=30) as client:
        listing = client.get("/api/files/local", params={"force": "true"}).json()
        for item in listing["files"]:
            client.delete(f"/api/files/local/{item['path']}").raise_for_status()
