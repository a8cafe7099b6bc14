"""The Moonraker transport passes the conformance suite against a real Moonraker on loopback.

Moonraker is installed from PyPI into a virtual environment of its own (see `venvs`)
and runs without Klipper: its file manager works while it waits for Klipper's socket.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import pytest

from tests.servers import free_port, stop_process, unavailable, wait_for_http, wait_for_port
from tests.worker.transports.contract import *  # noqa: F403
from tests.worker.transports.contract import get, put
from tests.worker.transports.tcp_proxy import CuttableProxy, make_proxy  # noqa: F401
from tests.worker.transports.venvs import venv_with
from worker.transports.base import BadPath, NotFound, TimedOut
from worker.transports.moonraker import MoonrakerOptions, MoonrakerTransport

REQUIREMENT = "moonraker>=0.11,<0.12"

# Trusted loopback clients need no key; moonlight off: no announcement feeds fetched.
CONFIG = """\
[server]
host: 127.0.0.1
port: {port}
klippy_uds_address: {data}/comms/klippy.sock

[authorization]
trusted_clients:
    127.0.0.0/8

[announcements]
enable_moonlight: False
"""


@pytest.fixture(scope="session")
def moonraker_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path]]:
    """A real Moonraker on a loopback port; yields its URL and its gcodes folder."""
    python = venv_with("moonraker", REQUIREMENT)
    data = tmp_path_factory.mktemp("moonraker")
    for sub in ("config", "comms", "gcodes", "logs", "tmp"):
        (data / sub).mkdir()
    port = free_port()
    (data / "config" / "moonraker.conf").write_text(CONFIG.format(port=port, data=data))
    log = open(data / "serve.log", "wb")  # noqa: SIM115 - closed after the server stops
    # Its uploads arrive in TMPDIR: the test's own folder, not the host's /tmp.
    proc = subprocess.Popen([str(python), "-m", "moonraker", "-d", str(data), "-n"],
                            stdout=log, stderr=subprocess.STDOUT,
                            env={**os.environ, "TMPDIR": str(data / "tmp")})
    try:
        url = f"http://127.0.0.1:{port}"
        try:
            wait_for_port(port, timeout_s=60)
            # The file API answers only once every component is up.
            wait_for_http(lambda: httpx.get(f"{url}/server/files/directory",
                                            params={"path": "gcodes"}, timeout=5),
                          timeout_s=60)
        except (TimeoutError, httpx.HTTPError) as exc:
            unavailable(f"Moonraker did not start ({exc}); see {data / 'serve.log'}")
        yield url, data / "gcodes"
    finally:
        stop_process(proc)
        log.close()


@pytest.fixture
def transport(moonraker_server: tuple[str, Path]) -> Iterator[MoonrakerTransport]:
    url, gcodes = moonraker_server
    for child in gcodes.iterdir():  # an empty storage for each test
        shutil.rmtree(child) if child.is_dir() else child.unlink()
    moon = MoonrakerTransport(MoonrakerOptions(url=url))  # type: ignore[arg-type]
    yield moon
    moon.close()


def test_reading_a_folder_is_not_found(transport: MoonrakerTransport) -> None:
    transport.make_dir("DIR")
    with pytest.raises(NotFound):
        b"".join(transport.read("DIR"))


def test_deleting_a_folder_as_a_file_is_not_found(transport: MoonrakerTransport) -> None:
    transport.make_dir("DIR")
    with pytest.raises(NotFound):
        transport.delete("DIR")
    assert transport.stat("DIR").is_dir


def test_a_path_leaving_the_root_is_bad_path(transport: MoonrakerTransport) -> None:
    with pytest.raises(BadPath):
        transport.list_dir("../config")


def test_moonrakers_thumbnail_folders_are_not_listed(transport: MoonrakerTransport) -> None:
    transport.make_dir("T")
    transport.write("T/P.nc", iter([b"G1 X1\n"]))
    transport.delete("T/P.nc")
    assert transport.list_dir("T") == []
    transport.remove_dir("T")


def test_moonraker_tells_the_free_space_of_its_gcodes_folder(
        transport: MoonrakerTransport, moonraker_server: tuple[str, Path]) -> None:
    told = transport.free_bytes()

    assert told is not None
    assert abs(told - shutil.disk_usage(moonraker_server[1]).free) < 256 * 1024**2


@pytest.mark.parametrize(("name", "kept"), [
    ("C.ufp", "C.gcode"),  # Moonraker unpacks a .ufp upload into a .gcode file
    (" A.nc", "A.nc"),  # it strips the spaces around an upload's name
    ("B.nc ", "B.nc"),
    ('Q"1.nc', "Q%221.nc"),  # it keeps the form's escape of a quote
])
def test_a_name_moonraker_would_store_as_another_file_is_refused_and_that_file_kept(
        transport: MoonrakerTransport, moonraker_server: tuple[str, Path],
        name: str, kept: str) -> None:
    put(transport, kept, b"the file already there")

    with pytest.raises(BadPath):
        put(transport, name, b"new")

    assert get(transport, kept) == b"the file already there"
    assert sorted(p.name for p in moonraker_server[1].iterdir() if p.is_file()) == [kept]


def test_an_upload_moonraker_reads_slowly_is_cut_off_at_the_deadline(
        transport: MoonrakerTransport, moonraker_server: tuple[str, Path],
        make_proxy: Callable[[int], CuttableProxy]) -> None:  # noqa: F811
    url, gcodes = moonraker_server
    proxy = make_proxy(int(url.rsplit(":", 1)[1]))
    slow = MoonrakerTransport(MoonrakerOptions(url=f"http://127.0.0.1:{proxy.port}",  # type: ignore[arg-type]
                                               timeout_s=10, transfer_timeout_s=1))
    proxy.throttle(256 * 1024)  # never silent for timeout_s, but 80 s for the upload
    started = time.monotonic()
    try:
        with pytest.raises(TimedOut, match="not complete within 1 s"):
            put(slow, "SLOW.gcode", b"G1 X1 Y1\n" * 2_400_000)  # 21.6 MB
    finally:
        slow.close()
    assert time.monotonic() - started < 15
    assert list(gcodes.iterdir()) == []  # nothing under the name
