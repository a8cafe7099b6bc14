"""The gateway transport passes the conformance suite against a second dncq on loopback."""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from pydantic import SecretStr

from jobs.api.app import create_app
from jobs.settings import Settings
from tests.conftest import API_KEY
from tests.live_server import HTTP_TIMEOUT_S, LiveServer, serving
from tests.worker.transports.contract import *  # noqa: F403
from tests.worker.transports.contract import get, put
from tests.worker.transports.tcp_proxy import CuttableProxy, make_proxy  # noqa: F401
from worker.transports.base import (
    ConnectFailed,
    Exists,
    NotEmpty,
    NotFound,
    Permanent,
    PermissionDenied,
    TimedOut,
    Transient,
    TransportError,
)
from worker.transports.gateway import GatewayOptions, GatewayTransport

REMOTE_ID = "remote1"
WRONG_KEY = "wrong-key-9876543210"


@pytest.fixture
def remote(settings: Settings, add_machines: Callable[..., Any]) -> Iterator[LiveServer]:
    """A second dncq, served for real, with one Mock machine."""
    add_machines({"id": REMOTE_ID, "name": "R", "model": "Mock"})
    with serving(create_app(settings)) as live:
        yield live


def gateway(url: str, *, machine_id: str = REMOTE_ID, key: str = API_KEY) -> GatewayTransport:
    return GatewayTransport(GatewayOptions(url=url, machine_id=machine_id,
                                           api_key=SecretStr(key), timeout_s=HTTP_TIMEOUT_S))


@pytest.fixture
def transport(remote: LiveServer) -> Iterator[GatewayTransport]:
    t = gateway(remote.url)
    yield t
    t.close()


def failure(call: Callable[[], object], expected: type[TransportError]) -> TransportError:
    """The error `call` raises, checked to be `expected` and to leave no key in its text."""
    with pytest.raises(expected) as info:
        call()
    text = "".join(traceback.format_exception(info.value))
    assert API_KEY not in text and WRONG_KEY not in text
    return info.value


def test_a_wrong_api_key_is_permission_denied(remote: LiveServer) -> None:
    t = gateway(remote.url, key=WRONG_KEY)
    try:
        failure(lambda: t.list_dir(""), PermissionDenied)
        failure(lambda: t.write("P.nc", iter([b"p"])), PermissionDenied)
    finally:
        t.close()


def test_an_unknown_remote_machine_is_permanent_and_says_so(remote: LiveServer) -> None:
    t = gateway(remote.url, machine_id="nosuch")
    try:
        error = failure(lambda: t.list_dir(""), Permanent)
    finally:
        t.close()
    assert "nosuch" in str(error) and "10003" in str(error)


def test_a_stopped_gateway_is_connect_failed(settings: Settings) -> None:
    with serving(create_app(settings)) as live:
        url = live.url
    t = gateway(url)
    try:
        error = failure(lambda: t.stat("P.nc"), ConnectFailed)
    finally:
        t.close()
    assert isinstance(error, Transient)


def test_the_key_is_sent_only_in_the_header(transport: GatewayTransport) -> None:
    seen: list[str] = []
    transport._client.event_hooks["request"].append(lambda request: seen.append(str(request.url)))
    transport.list_dir("")
    assert seen and all(API_KEY not in url for url in seen)
    assert API_KEY not in repr(transport.options)


def test_an_error_the_gateway_answers_does_not_reveal_the_key(transport: GatewayTransport) -> None:
    failure(lambda: transport.delete("NOPE.nc"), NotFound)


@pytest.mark.parametrize("name", ["A B.nc", "Teil #1.nc", "50%.nc", "a%41+b&c=d.nc",
                                  "Fräse 日本.nc"])
def test_names_with_spaces_and_url_characters_work_at_every_step(
        transport: GatewayTransport, name: str) -> None:
    folder = name.replace(".nc", "")
    transport.make_dir(folder)
    path = f"{folder}/{name}"
    put(transport, path, b"G1 X1\n")
    with pytest.raises(Exists):
        put(transport, path, b"G1 X2\n")

    assert (folder, True) in [(e.name, e.is_dir) for e in transport.list_dir("")]
    assert transport.stat(path).name == name
    assert get(transport, path) == b"G1 X1\n"
    with pytest.raises(NotEmpty):
        transport.remove_dir(folder)
    transport.delete(path)
    transport.remove_dir(folder)
    assert folder not in {e.name for e in transport.list_dir("")}


def test_a_gateway_that_went_away_between_two_steps_is_reached_again(
        remote: LiveServer, make_proxy: Callable[[int], CuttableProxy]) -> None:  # noqa: F811
    proxy = make_proxy(int(remote.url.rsplit(":", 1)[1]))
    t = gateway(f"http://127.0.0.1:{proxy.port}")
    try:
        put(t, "BEFORE.nc", b"G1 X3\n")
        proxy.down()  # the kept connection is closed, and every new one too
        failure(lambda: t.stat("BEFORE.nc"), Transient)
        proxy.up()
        assert get(t, "BEFORE.nc") == b"G1 X3\n"
        put(t, "AFTER.nc", b"G1 X4\n")
    finally:
        t.close()


def test_an_upload_the_gateway_reads_slowly_is_cut_off_at_the_deadline(
        remote: LiveServer, make_proxy: Callable[[int], CuttableProxy]) -> None:  # noqa: F811
    proxy = make_proxy(int(remote.url.rsplit(":", 1)[1]))
    slow = GatewayTransport(GatewayOptions(
        url=f"http://127.0.0.1:{proxy.port}", machine_id=REMOTE_ID, api_key=SecretStr(API_KEY),
        timeout_s=10, transfer_timeout_s=1))
    proxy.throttle(256 * 1024)  # never silent for timeout_s, but 80 s for the upload
    started = time.monotonic()
    try:
        with pytest.raises(TimedOut, match="not complete within 1 s"):
            put(slow, "SLOW.nc", b"G1 X1 Y1\n" * 2_400_000)  # 21.6 MB
    finally:
        slow.close()
    assert time.monotonic() - started < 15
    check = gateway(remote.url)
    try:
        with pytest.raises(NotFound):  # the gateway stored nothing of it
            check.stat("SLOW.nc")
    finally:
        check.close()
