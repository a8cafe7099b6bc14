"""The Moonraker transport passes the conformance suite against a real Moonraker on loopback."""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from pydantic import SecretStr

from tests.worker.transports.contract import *  # noqa: F403
from tests.worker.transports.contract import get, put
from tests.worker.transports.moonraker_server import MoonrakerServer
from tests.worker.transports.tcp_proxy import CuttableProxy, make_proxy  # noqa: F401
from worker.transports.base import (
    BadPath,
    Exists,
    NotEmpty,
    NotFound,
    PermissionDenied,
    TimedOut,
)
from worker.transports.moonraker import MoonrakerOptions, MoonrakerTransport


@pytest.fixture(scope="session")
def moonraker_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path]]:
    """A real Moonraker on a loopback port that trusts loopback clients; yields its URL and
    its gcodes folder."""
    server = MoonrakerServer(tmp_path_factory.mktemp("moonraker"), trusted_loopback=True)
    server.start()
    try:
        yield server.url, server.gcodes
    finally:
        server.stop()


@pytest.fixture(scope="module")
def keyed_moonraker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MoonrakerServer]:
    """A real Moonraker as installed: its `[authorization]` trusts no client, every request
    needs its API key."""
    server = MoonrakerServer(tmp_path_factory.mktemp("keyed-moonraker"), trusted_loopback=False)
    server.start()
    try:
        yield server
    finally:
        server.stop()


def keyed(server: MoonrakerServer, key: str | None) -> MoonrakerTransport:
    return MoonrakerTransport(MoonrakerOptions(
        url=server.url, api_key=SecretStr(key) if key else None))  # type: ignore[arg-type]


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


@pytest.mark.parametrize("key", [None, "wrong-key-0123456789abcdef"])
def test_a_moonraker_that_needs_its_key_refuses_every_step_without_it(
        keyed_moonraker: MoonrakerServer, key: str | None) -> None:
    (keyed_moonraker.gcodes / "THERE.gcode").write_bytes(b"G1 X1\n")
    moon = keyed(keyed_moonraker, key)
    steps = [lambda: moon.list_dir(""), lambda: moon.stat("THERE.gcode"),
             lambda: get(moon, "THERE.gcode"), lambda: put(moon, "NEW.gcode", b"G1\n"),
             lambda: moon.delete("THERE.gcode"), lambda: moon.make_dir("D"),
             lambda: moon.remove_dir("D"), moon.free_bytes]
    try:
        for step in steps:
            with pytest.raises(PermissionDenied) as refused:
                step()
            assert keyed_moonraker.api_key not in str(refused.value)
    finally:
        moon.close()
    assert (keyed_moonraker.gcodes / "THERE.gcode").read_bytes() == b"G1 X1\n"
    assert not (keyed_moonraker.gcodes / "NEW.gcode").exists()
    assert not (keyed_moonraker.gcodes / "D").exists()


def test_a_moonraker_that_needs_its_key_serves_the_transport_given_it(
        keyed_moonraker: MoonrakerServer) -> None:
    moon = keyed(keyed_moonraker, keyed_moonraker.api_key)
    try:
        put(moon, "KEYED.gcode", b"G1 X2\n")
        assert get(moon, "KEYED.gcode") == b"G1 X2\n"
        moon.delete("KEYED.gcode")
    finally:
        moon.close()


def test_a_moonraker_restarted_between_two_steps_is_reached_again(
        keyed_moonraker: MoonrakerServer) -> None:
    moon = keyed(keyed_moonraker, keyed_moonraker.api_key)
    try:
        put(moon, "BEFORE.gcode", b"G1 X3\n")
        keyed_moonraker.restart()  # the transport's kept connection is gone with it
        assert get(moon, "BEFORE.gcode") == b"G1 X3\n"
        put(moon, "AFTER.gcode", b"G1 X4\n")
        assert {e.name for e in moon.list_dir("")} >= {"BEFORE.gcode", "AFTER.gcode"}
    finally:
        moon.close()


@pytest.mark.parametrize("name", ["A B.gcode", "Teil #1.gcode", "50%.gcode", "why?.gcode",
                                  "a%41+b&c=d.gcode", "Fräse 日本.gcode"])
def test_names_with_spaces_and_url_characters_work_at_every_step(
        transport: MoonrakerTransport, moonraker_server: tuple[str, Path], name: str) -> None:
    folder = name.replace(".gcode", "")
    transport.make_dir(folder)
    path = f"{folder}/{name}"
    put(transport, path, b"G1 X1\n")
    with pytest.raises(Exists):
        put(transport, path, b"G1 X2\n")

    assert [(e.name, e.is_dir) for e in transport.list_dir("")] == [(folder, True)]
    assert transport.stat(path).size == 6
    assert get(transport, path) == b"G1 X1\n"
    assert (moonraker_server[1] / folder / name).read_bytes() == b"G1 X1\n"
    with pytest.raises(NotEmpty):
        transport.remove_dir(folder)
    transport.delete(path)
    transport.remove_dir(folder)
    assert transport.list_dir("") == []


def test_an_upload_over_moonrakers_max_upload_size_is_refused_saying_so(
        tmp_path: Path) -> None:
    server = MoonrakerServer(tmp_path, trusted_loopback=True, max_upload_mib=1)
    server.start()
    moon = MoonrakerTransport(MoonrakerOptions(url=server.url))  # type: ignore[arg-type]
    try:
        put(moon, "SMALL.gcode", b"G1 X1\n" * 100_000)  # 600 kB
        with pytest.raises(BadPath, match="max_upload_size"):
            put(moon, "LARGE.gcode", b"G1 X1\n" * 400_000)  # 2.4 MB
    finally:
        moon.close()
        server.stop()
    assert sorted(p.name for p in server.gcodes.glob("*.gcode")) == ["SMALL.gcode"]


def test_the_upload_limit_is_asked_of_each_moonraker_once_a_minute_by_the_process(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A transport is opened per operation: a second upload within the minute asks
    Moonraker's server/config no more, one after it asks again (a raised limit is seen)."""
    from tests.jobs.helpers import wait_until
    from worker.transports import moonraker

    now_s = [1000.0]
    monkeypatch.setattr(moonraker, "_clock", lambda: now_s[0])
    monkeypatch.setattr(moonraker, "_upload_limits", {})
    server = MoonrakerServer(tmp_path, trusted_loopback=True, logs_requests=True)
    server.start()

    def uploaded(name: str) -> None:  # as a worker does it: a transport of its own
        moon = MoonrakerTransport(MoonrakerOptions(url=server.url))  # type: ignore[arg-type]
        try:
            put(moon, name, b"G1 X1\n")
        finally:
            moon.close()

    def asked_after(uploads: int) -> int:  # read once the last upload is in the log
        wait_until(lambda: server.requests("POST", "/server/files/upload") == uploads)
        return server.requests("GET", "/server/config")

    try:
        uploaded("FIRST.gcode")
        now_s[0] += moonraker.UPLOAD_LIMIT_KEPT_S - 1
        uploaded("WITHIN.gcode")
        asked_within = asked_after(2)
        now_s[0] += 1
        uploaded("AFTER.gcode")
        asked_later = asked_after(3)
    finally:
        server.stop()

    assert (asked_within, asked_later) == (1, 2)
