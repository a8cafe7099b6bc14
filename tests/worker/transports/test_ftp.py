"""The ftp transport against real pyftpdlib servers on loopback: plain, FTPS, no MLSD, latin-1."""

from __future__ import annotations

import socket
import time
import traceback
from collections.abc import Iterator
from pathlib import Path

import pytest
from pydantic import SecretStr

from tests.servers import free_port
from tests.worker.transports.contract import *  # noqa: F403
from tests.worker.transports.contract import get, put
from tests.worker.transports.ftp_daemons import DAEMON_KINDS, server_of
from tests.worker.transports.ftp_server import (
    KINDS,
    PASSWORD,
    USER,
    FtpServer,
    counting,
    ftp_server_of,
)
from worker.transports import ftp as ftp_module
from worker.transports.base import (
    BadPath,
    ConnectFailed,
    Entry,
    PermissionDenied,
    TimedOut,
    Unsupported,
)
from worker.transports.ftp import FtpOptions, FtpTransport
from worker.transports.ftp_listing import parse_list_line, parse_mlsx
from worker.transports.ftp_lookups import size_of


@pytest.fixture(params=KINDS + DAEMON_KINDS)
def ftp_server(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[FtpServer]:
    with server_of(request.param, tmp_path) as server:
        yield server


@pytest.fixture
def plain_server(tmp_path: Path) -> Iterator[FtpServer]:
    with ftp_server_of("plain", tmp_path) as server:
        yield server


@pytest.fixture
def transport(ftp_server: FtpServer) -> Iterator[FtpTransport]:
    ftp = ftp_server.transport()
    yield ftp
    ftp.close()


def test_a_read_asks_the_size_only_when_progress_is_wanted(tmp_path: Path) -> None:
    # SIZE tells progress the total; RETR alone decides the end. A backup reads every
    # program without progress, so SIZE would be one round trip per file for nothing.
    sizes: list[str] = []
    with ftp_server_of("plain", tmp_path, ftp_SIZE=counting("SIZE", sizes)) as server:
        transport = server.transport()
        put(transport, "P1.nc", b"x" * 70_000)
        asked_by_put = len(sizes)
        assert get(transport, "P1.nc") == b"x" * 70_000
        assert len(sizes) == asked_by_put
        totals: list[int | None] = []
        data = b"".join(transport.read("P1.nc", progress=lambda done, total: totals.append(total)))
        assert data == b"x" * 70_000
        assert len(sizes) == asked_by_put + 1 and totals[-1] == 70_000
        transport.close()


def test_the_password_never_shows_in_options_or_transport() -> None:
    options = FtpOptions(host="127.0.0.1", user=USER, password=SecretStr(PASSWORD))
    for text in (repr(options), str(options), options.model_dump_json(),
                 repr(FtpTransport(options)), str(FtpTransport(options))):
        assert PASSWORD not in text


@pytest.mark.parametrize("kind", ["plain", "vsftpd", "proftpd-tls"])
def test_a_wrong_password_is_permission_denied_and_not_in_the_error(
    kind: str, tmp_path: Path
) -> None:
    wrong = "wrong-" + PASSWORD
    with server_of(kind, tmp_path) as server:
        ftp = server.transport(password=wrong)
        with pytest.raises(PermissionDenied) as caught:
            ftp.list_dir("")
    text = "".join(traceback.format_exception(caught.value))
    for shown in (text, repr(caught.value), repr(caught.value.__cause__)):
        assert wrong not in shown and PASSWORD not in shown


def test_a_server_that_is_not_listening_is_connect_failed() -> None:
    ftp = FtpTransport(FtpOptions(host="127.0.0.1", port=free_port(), timeout_s=5))
    with pytest.raises(ConnectFailed):
        ftp.list_dir("")


def test_a_server_that_never_answers_is_timed_out() -> None:
    with socket.socket() as listener:  # accepts the connection (backlog) but never greets
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        port = listener.getsockname()[1]
        ftp = FtpTransport(FtpOptions(host="127.0.0.1", port=port, timeout_s=0.3))
        with pytest.raises(TimedOut):
            ftp.list_dir("")


def test_a_server_that_trickles_a_transfer_is_cut_off_at_the_deadline(tmp_path: Path) -> None:
    from pyftpdlib.handlers import ThrottledDTPHandler

    # Never silent for `timeout_s`, but 30 s or more for each transfer at this pace.
    slow = type("SlowDTP", (ThrottledDTPHandler,), {"read_limit": 128 * 1024,
                                                    "write_limit": 4 * 1024})
    with ftp_server_of("plain", tmp_path, dtp_handler=slow) as server:
        program = b"G1 X1 Y1\n" * 15_000  # 135 KB
        (server.home / "BIG.nc").write_bytes(program)
        ftp = server.transport(transfer_timeout_s=1.0)

        started = time.monotonic()
        with pytest.raises(TimedOut, match="not complete within 1 s"):
            get(ftp, "BIG.nc")
        with pytest.raises(TimedOut, match="not complete within 1 s"):  # more than the
            put(ftp, "UP.nc", program * 64)  # socket buffers hold, sent at 128 KB/s
        assert time.monotonic() - started < 15

        assert [p.name for p in server.home.iterdir()] == ["BIG.nc"]  # no part file left
        assert ftp.stat("BIG.nc").size == len(program)  # and the machine still answers
        ftp.close()


def test_one_login_serves_several_operations(plain_server: FtpServer) -> None:
    ftp = plain_server.transport()
    put(ftp, "A.nc", b"a")
    ftp.make_dir("SUB")
    put(ftp, "SUB/B.nc", b"b")
    assert get(ftp, "SUB/B.nc") == b"b"
    ftp.stat("A.nc")
    ftp.list_dir("SUB")
    ftp.delete("A.nc")
    ftp.close()
    assert plain_server.logins == [USER]


def test_a_connection_the_server_closed_while_idle_is_replaced(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(ftp_module, "_IDLE_CHECK_S", 0.0)  # probe every kept connection
    with ftp_server_of("plain", tmp_path) as server:
        ftp = server.transport()
        put(ftp, "A.nc", b"a")
        for kept, _ in ftp._idle:
            assert kept.sock is not None
            kept.sock.shutdown(socket.SHUT_RDWR)  # as if the server had hung up
        assert get(ftp, "A.nc") == b"a"
        ftp.close()
        assert server.logins == [USER, USER]


@pytest.mark.parametrize("kind", ["plain", "vsftpd-tls", "proftpd-tls"])
def test_active_mode_transfers_work(kind: str, tmp_path: Path) -> None:
    with server_of(kind, tmp_path) as server:
        ftp = server.transport(passive=False)
        put(ftp, "ACT.nc", b"active" * 1000)
        assert get(ftp, "ACT.nc") == b"active" * 1000
        ftp.close()


@pytest.mark.parametrize("kind", ["plain", "vsftpd", "proftpd"])
def test_the_temporary_file_is_gone_after_a_write(kind: str, tmp_path: Path) -> None:
    with server_of(kind, tmp_path) as server:
        ftp = server.transport()
        put(ftp, "P.nc", b"p")
        assert [p.name for p in server.home.iterdir()] == ["P.nc"]
        ftp.close()


def test_a_failed_write_removes_its_temporary_file(plain_server: FtpServer) -> None:
    ftp = plain_server.transport()

    def chunks() -> Iterator[bytes]:
        yield b"x" * 100_000
        raise RuntimeError("the source broke")

    with pytest.raises(RuntimeError):
        ftp.write("HALF.nc", chunks())
    assert list(plain_server.home.iterdir()) == []
    ftp.close()


def test_a_name_the_server_encoding_cannot_take_is_bad_path(tmp_path: Path) -> None:
    with ftp_server_of("latin-1", tmp_path) as server:
        ftp = server.transport()
        with pytest.raises(BadPath):
            put(ftp, "部品.nc", b"x")
        ftp.close()


def test_paths_above_the_top_are_bad_path(plain_server: FtpServer) -> None:
    ftp = plain_server.transport()
    with pytest.raises(BadPath):
        ftp.stat("../etc/passwd")
    with pytest.raises(BadPath):
        ftp.delete("A.nc\r\nDELE B.nc")


def test_machine_only_operations_are_unsupported(plain_server: FtpServer) -> None:
    ftp = plain_server.transport()
    with pytest.raises(Unsupported):
        ftp.select_program("P.nc")
    with pytest.raises(Unsupported):
        ftp.current_program()
    with pytest.raises(Unsupported):
        ftp.lock_range(1, 2, True)
    assert plain_server.logins == []


def test_stat_gives_size_and_time_with_and_without_mlst(tmp_path: Path) -> None:
    for kind in ("plain", "no-mlsd", "vsftpd", "proftpd"):  # vsftpd has no MLSD nor MLST
        with server_of(kind, tmp_path / kind) as server:
            ftp = server.transport()
            put(ftp, "T.nc", b"12345")
            entry = ftp.stat("T.nc")
            local = (server.home / "T.nc").stat().st_mtime
            assert entry.size == 5 and entry.mtime is not None
            assert abs(entry.mtime - local) < 2  # whole seconds on the wire
            listed = {e.name: e for e in ftp.list_dir("")}["T.nc"]
            assert listed.size == 5 and listed.mtime is not None
            # the fallbacks were used where the server lacks MLSD and MLST
            assert ftp._has_mlsd is ftp._has_mlst is (kind in ("plain", "proftpd"))
            ftp.close()


@pytest.mark.parametrize(("line", "entry"), [
    ("-rw-r--r--   1 owner    group        1234 Jan 02  2020 O1000.nc",
     Entry("O1000.nc", False, 1234, 1577923200.0)),
    ("drwxr-xr-x   2 owner    group        4096 Mar 04  2021 my dir",
     Entry("my dir", True, None, 1614816000.0)),
    ("-rw-r--r-- 1 ftp 42 Jan 02  2020 NOGROUP.nc", Entry("NOGROUP.nc", False, 42, 1577923200.0)),
    ("lrwxrwxrwx   1 owner    group          10 Jan 02  2020 link -> target",
     Entry("link", False, 10, 1577923200.0)),
    ("01-02-20  01:30PM       <DIR>          PROGS", Entry("PROGS", True, None, 1577971800.0)),
    ("01-02-2020  09:05AM              77 O0001", Entry("O0001", False, 77, 1577955900.0)),
    ("something else entirely", None),
])
def test_list_lines_of_unix_and_dos_servers_parse(line: str, entry: Entry | None) -> None:
    assert parse_list_line(line) == entry


@pytest.mark.parametrize(("stamp", "seconds"), [
    ("20250101000000", 1735689600.0),
    ("20241231235959.123", 1735689599.123),
    ("20240229120000", 1709208000.0),  # a leap day
    ("20250101235960", 1735776000.0),  # a leap second, as RFC 3659 allows
    ("20230229120000", None),  # no such day
    ("20251301000000", None),
    ("00000101000000", None),  # no year 0
    ("20250101240000", None),
    ("2025010100000", None),  # RFC 3659: four digits of year, two of everything else
    ("202501010000000", None),
    ("2025-01-01 00:00", None),
    ("", None),
])
def test_a_modify_fact_is_read_as_utc_seconds_or_unknown(stamp: str, seconds: float | None
                                                         ) -> None:
    entry = parse_mlsx(f"type=file;size=1;modify={stamp}; O1.nc")
    assert entry is not None and entry.mtime == seconds


def test_a_size_fact_that_is_not_a_count_is_unknown_not_a_crash() -> None:
    for size in ("abc", "-7", "1e3", ""):
        entry = parse_mlsx(f"type=file;size={size};modify=20250101000000; weird.nc")
        assert entry is not None and entry.name == "weird.nc" and entry.size is None
    assert parse_mlsx("type=file;size=42; ok.nc").size == 42


def test_a_size_reply_that_is_not_a_count_is_unknown() -> None:
    def answering(reply: str):  # as ftplib's FTP.size parses a 213 reply
        return lambda _path: int(reply)

    assert size_of(answering("abc"), "/x") is None
    assert size_of(answering("-7"), "/x") is None
    assert size_of(answering("512"), "/x") == 512
