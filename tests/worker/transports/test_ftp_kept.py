"""FTP connections kept between jobs: the next transport of a server and account takes the
last one's connection instead of logging in again, and a kept connection ends in time."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.jobs.helpers import wait_until
from tests.worker.transports.contract import get, put
from tests.worker.transports.ftp_daemons import server_of
from tests.worker.transports.ftp_server import USER, counting, ftp_server_of
from worker.transports import ftp as ftp_module
from worker.transports.ftp_link import FtpOptions
from worker.transports.ftp_pool import KEPT


@pytest.fixture(autouse=True)
def nothing_kept_before_or_after() -> Iterator[None]:
    KEPT.end_all()
    yield
    KEPT.end_all()


@pytest.fixture
def logins_opened(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """One entry per connection the transport logs in on (client side, any server)."""
    opened: list[int] = []
    real = ftp_module.open_link

    def counted(options: FtpOptions) -> Any:
        opened.append(options.port)
        return real(options)

    monkeypatch.setattr(ftp_module, "open_link", counted)
    return opened


@pytest.mark.parametrize("kind", ["plain", "vsftpd", "proftpd", "vsftpd-tls"])
def test_the_next_jobs_transport_takes_the_last_ones_connection(
        kind: str, tmp_path: Path, logins_opened: list[int]) -> None:
    with server_of(kind, tmp_path) as server:
        first = server.transport()
        put(first, "A.nc", b"G0 X1\n")
        first.close()
        assert KEPT.count() == 1
        second = server.transport()  # a new transport, as the next job's task makes
        assert get(second, "A.nc") == b"G0 X1\n"
        put(second, "B.nc", b"G0 X2\n")
        second.close()
        assert len(logins_opened) == 1
        if kind == "plain":
            assert server.logins == [USER]  # the server saw one login too


def test_a_kept_connection_is_ended_once_its_time_is_up(tmp_path: Path) -> None:
    logouts: list[str] = []
    with ftp_server_of("plain", tmp_path, on_logout=lambda self, user: logouts.append(user)
                       ) as server:
        ftp = server.transport(keep_connection_s=2.0)  # kept past the look below on a busy host
        put(ftp, "A.nc", b"a")
        ftp.close()
        assert KEPT.count() == 1 and logouts == []
        wait_until(lambda: logouts != [], timeout_s=10)
        assert logouts == [USER] and KEPT.count() == 0  # QUIT, seen by the server


def test_keep_connection_0_ends_it_when_the_job_is_done(tmp_path: Path) -> None:
    logouts: list[str] = []
    with ftp_server_of("plain", tmp_path, on_logout=lambda self, user: logouts.append(user)
                       ) as server:
        ftp = server.transport(keep_connection_s=0)
        put(ftp, "A.nc", b"a")
        ftp.close()
        assert KEPT.count() == 0
        wait_until(lambda: logouts != [], timeout_s=5)
        assert logouts == [USER]
        assert get(server.transport(keep_connection_s=0), "A.nc") == b"a"
        assert server.logins == [USER, USER]


def test_a_kept_connection_the_server_ended_is_replaced(tmp_path: Path) -> None:
    with ftp_server_of("plain", tmp_path) as server:
        first = server.transport()
        put(first, "A.nc", b"a")
        [(kept, _)] = first._idle
        first.close()
        assert kept.sock is not None
        kept.sock.shutdown(socket.SHUT_RDWR)  # as if the server had hung up meanwhile
        second = server.transport()
        assert get(second, "A.nc") == b"a"  # probed, found dead, replaced: no error
        second.close()
        assert server.logins == [USER, USER]


def test_a_connection_used_moments_ago_is_taken_without_a_probe(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    noops: list[str] = []
    with ftp_server_of("plain", tmp_path, ftp_NOOP=counting("NOOP", noops)) as server:
        first = server.transport()
        put(first, "A.nc", b"a")
        first.close()
        second = server.transport()  # the next job's, a moment later: no round trip more
        assert get(second, "A.nc") == b"a"
        second.close()
        assert noops == [] and server.logins == [USER]
        monkeypatch.setattr(ftp_module, "_IDLE_CHECK_S", 0.1)
        time.sleep(0.2)  # idle longer than the check allows: asked first
        third = server.transport()
        assert get(third, "A.nc") == b"a"
        third.close()
        assert noops == [""] and server.logins == [USER]


def test_a_kept_connection_the_server_timed_out_is_replaced_without_an_error(
        tmp_path: Path) -> None:
    # pyftpdlib's idle timeout: "421 Control connection timed out." and it hangs up
    hung_up = threading.Event()
    with ftp_server_of("plain", tmp_path, timeout=0.3,
                       on_disconnect=lambda self: hung_up.set()) as server:
        first = server.transport()
        put(first, "A.nc", b"a")
        first.close()
        # Its 421 sent and the connection closed, within the idle check's 5 s but for a busy
        # host: a fixed pause let a server thread kept from running hang up mid-command.
        assert hung_up.wait(30)
        second = server.transport()
        assert get(second, "A.nc") == b"a"
        second.close()
        assert server.logins == [USER, USER]


def test_another_account_or_server_never_gets_the_connection(
        tmp_path: Path, logins_opened: list[int]) -> None:
    # (two pyftpdlib servers in one process would share its one IOLoop: one is vsftpd)
    with server_of("plain", tmp_path / "one") as one, \
            server_of("vsftpd", tmp_path / "two") as two:
        first = one.transport()
        put(first, "A.nc", b"a")
        first.close()
        other_server = two.transport()
        put(other_server, "B.nc", b"b")
        other_server.close()
        assert logins_opened == [one.port, two.port]
    fields: dict[str, Any] = {"host": "127.0.0.1", "port": 21, "user": "cnc", "password": "one"}
    key = FtpOptions(**fields).connection_key()
    assert FtpOptions(**fields, transfer_timeout_s=60).connection_key() == key
    for changed in ({"password": "two"}, {"user": "op"}, {"tls": True}, {"port": 2121}):
        assert FtpOptions(**{**fields, **changed}).connection_key() != key
