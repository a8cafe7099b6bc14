"""The ftp transport against the servers shops run: vsftpd and ProFTPD as shipped.

FTPS with their default TLS settings (data connections must reuse the control
connection's TLS session), failed uploads that leave nothing behind, and replies that
do not say why they refused. pyftpdlib runs beside them where the behaviour is shared.
"""

from __future__ import annotations

import ftplib
import os
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from jobs.errors import ErrorCode, from_transport
from tests.worker.transports.contract import get, names, put
from tests.worker.transports.ftp_daemons import server_of
from tests.worker.transports.ftp_server import FtpServer, ftp_server_of
from tests.worker.transports.tcp_proxy import CuttableProxy, make_proxy  # noqa: F401
from worker.transports import ftp_link
from worker.transports.base import ConnectFailed, TransportError
from worker.transports.ftp import FtpTransport

TLS_DAEMONS = ("vsftpd-tls", "proftpd-tls")
ALL_SERVERS = ("plain", "tls", "vsftpd", "vsftpd-tls", "proftpd", "proftpd-tls")


@pytest.fixture
def fresh_tls_sessions(monkeypatch: pytest.MonkeyPatch) -> None:
    """Data connections with a TLS session of their own, as Python's ftplib opens them."""
    monkeypatch.setattr(ftp_link.SessionReusingFTP, "ntransfercmd", ftplib.FTP_TLS.ntransfercmd)


@pytest.fixture(params=ALL_SERVERS)
def server(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[FtpServer]:
    with server_of(request.param, tmp_path) as started:
        yield started


@pytest.fixture
def transport(server: FtpServer) -> Iterator[FtpTransport]:
    ftp = server.transport()
    yield ftp
    ftp.close()


def code_of(error: TransportError) -> ErrorCode:
    """The errorCode a client is answered for a transport error."""
    return from_transport(error).code


@pytest.mark.parametrize("kind", TLS_DAEMONS)
def test_ftps_lists_writes_and_reads_where_data_connections_must_reuse_the_tls_session(
    kind: str, tmp_path: Path
) -> None:
    with server_of(kind, tmp_path) as server:
        ftp = server.transport()
        program = b"%\nO1000\nG0 X0 Y0\nM30\n%\n" * 1000
        put(ftp, "O1000.nc", program)
        put(ftp, "O1001.nc", b"second")  # a second data connection on the same login
        assert names(ftp.list_dir("")) == {"O1000.nc", "O1001.nc"}
        assert get(ftp, "O1000.nc") == program
        assert (server.home / "O1000.nc").read_bytes() == program
        ftp.close()


@pytest.mark.parametrize("kind", TLS_DAEMONS)
def test_a_write_whose_data_connection_is_refused_leaves_no_temporary_file(
    kind: str, tmp_path: Path, fresh_tls_sessions: None
) -> None:
    """vsftpd creates the file on STOR, then refuses the data connection and hangs up."""
    with server_of(kind, tmp_path) as server:
        ftp = server.transport()
        with pytest.raises(TransportError):
            put(ftp, "P.nc", b"p" * 1000)
        assert list(server.home.iterdir()) == []
        ftp.close()


def test_a_refused_tls_data_connection_is_a_connection_failure_saying_what_was_refused(
    tmp_path: Path, fresh_tls_sessions: None
) -> None:
    with server_of("vsftpd-tls", tmp_path) as server:
        ftp = server.transport()
        with pytest.raises(ConnectFailed) as caught:
            ftp.list_dir("")
        assert "refused the TLS data connection" in str(caught.value)
        assert "session reuse required" in str(caught.value)
        assert code_of(caught.value) is ErrorCode.CONNECTION_FAILED
        ftp.close()


@pytest.mark.parametrize("kind", TLS_DAEMONS)
def test_a_plain_login_where_tls_is_required_is_a_connection_failure_saying_so(
    kind: str, tmp_path: Path
) -> None:
    with server_of(kind, tmp_path) as server:
        ftp = server.transport(tls=False)
        with pytest.raises(ConnectFailed, match="refused the connection's TLS setting") as caught:
            ftp.list_dir("")
        assert code_of(caught.value) is ErrorCode.CONNECTION_FAILED


@pytest.mark.parametrize("kind", ("plain", "vsftpd", "proftpd"))
def test_a_write_whose_source_fails_midway_leaves_no_temporary_file(
    kind: str, tmp_path: Path
) -> None:
    with server_of(kind, tmp_path) as server:
        ftp = server.transport()

        def chunks() -> Iterator[bytes]:
            yield b"x" * 300_000
            raise TransportError("the source broke")

        with pytest.raises(TransportError, match="the source broke"):
            ftp.write("HALF.nc", chunks())
        assert list(server.home.iterdir()) == []
        ftp.close()


@pytest.mark.parametrize("kind", ("plain", "vsftpd"))
def test_a_failed_writes_clean_up_replaces_a_kept_connection_the_server_closed(
    kind: str, tmp_path: Path
) -> None:
    with server_of(kind, tmp_path) as server:
        ftp = server.transport()
        with ftp._session(), ftp._session():
            pass  # two connections kept: the write takes one, its clean-up the other
        dead = ftp._idle[0][0]
        assert dead.sock is not None
        dead.sock.shutdown(socket.SHUT_RDWR)  # as if the server had hung up

        def chunks() -> Iterator[bytes]:
            yield b"x" * 300_000
            raise TransportError("the source broke")

        with pytest.raises(TransportError) as caught:
            ftp.write("HALF.nc", chunks())
        assert "left behind" not in str(caught.value)
        assert list(server.home.iterdir()) == []
        ftp.close()


def test_a_temporary_file_the_server_will_not_delete_is_named_in_the_error(
    tmp_path: Path,
) -> None:
    """An upload-only account: it may write and rename, not delete."""
    with ftp_server_of("plain", tmp_path, perm="elrwf") as server:
        ftp = server.transport()

        def chunks() -> Iterator[bytes]:
            yield b"x" * 300_000
            raise TransportError("the source broke")

        with pytest.raises(TransportError) as caught:
            ftp.write("HALF.nc", chunks())
        [left] = [p.name for p in server.home.iterdir()]
        assert left.startswith(".dncq-part-")
        message = from_transport(caught.value).status_msg or ""
        assert "the source broke" in message
        assert left in message and "left behind" in message
        ftp.close()


@pytest.mark.parametrize("kind", ("plain", "vsftpd"))
def test_a_file_sent_again_after_the_server_went_away_mid_write_leaves_no_temporary_file(
    kind: str, tmp_path: Path, make_proxy: Callable[[int], CuttableProxy]  # noqa: F811
) -> None:
    with server_of(kind, tmp_path) as server:
        proxy = make_proxy(server.port)
        ftp = server.transport(port=proxy.port)

        def chunks() -> Iterator[bytes]:
            yield b"x" * 300_000
            proxy.down()  # the server is gone, and stays away past the write's clean-up
            yield b"x" * 300_000

        with pytest.raises(TransportError, match="left behind"):
            ftp.write("P.nc", chunks())
        proxy.up()
        put(ftp, "P.nc", b"p" * 600_000)  # its retry

        assert [p.name for p in server.home.iterdir()] == ["P.nc"]
        ftp.close()


@pytest.mark.parametrize("kind", ("plain", "vsftpd", "proftpd"))
def test_a_write_removes_the_temporary_files_nobody_wrote_for_longer_than_a_write_lasts(
    kind: str, tmp_path: Path,
) -> None:
    # Left by a write of another process (whose retry may come to any worker), or one killed;
    # a write lasts its transfer_timeout_s and five timeout_s at most. vsftpd lists neither
    # without `-a`, and its LIST gives the minute only.
    with server_of(kind, tmp_path) as server:
        ftp = server.transport(transfer_timeout_s=600.0, timeout_s=10.0)
        stale, live = (server.home / f".dncq-part-{n}" for n in ("a1", "b2"))
        for part, unchanged_s in ((stale, 800), (live, 600)):  # live: waiting for its answer
            part.write_bytes(b"half")
            os.utime(part, (time.time() - unchanged_s,) * 2)

        put(ftp, "P.nc", b"p")

        assert sorted(p.name for p in server.home.iterdir()) == [live.name, "P.nc"]
        ftp.close()


@pytest.mark.parametrize(("withheld", "operation"), [
    ("r", "read"), ("w", "write"), ("l", "list_dir")])
def test_what_a_pyftpdlib_account_may_not_do_is_20010(
    withheld: str, operation: str, tmp_path: Path
) -> None:
    """pyftpdlib answers `550 Not enough privileges.` for the account's rights, files or not."""
    perm = "elradfmwMT".replace(withheld, "")
    with ftp_server_of("plain", tmp_path, perm=perm) as server:
        (server.home / "P.nc").write_bytes(b"p")
        ftp = server.transport()
        attempts: dict[str, Callable[[], object]] = {
            "read": lambda: get(ftp, "P.nc"), "write": lambda: put(ftp, "Q.nc", b"q"),
            "list_dir": lambda: ftp.list_dir("")}
        with pytest.raises(TransportError) as caught:
            attempts[operation]()
        ftp.close()
    assert code_of(caught.value) is ErrorCode.PERMISSION_DENIED
    assert "left behind" not in str(caught.value)


@pytest.mark.parametrize("kind", ("vsftpd", "proftpd"))
def test_a_file_the_server_will_not_delete_is_20010_and_stays(kind: str, tmp_path: Path) -> None:
    """vsftpd answers a refused DELE as it answers one of a missing file."""
    with server_of(kind, tmp_path) as server:
        ftp = server.transport()
        ftp.make_dir("RO")
        put(ftp, "RO/P.nc", b"p")
        (server.home / "RO").chmod(0o555)  # its entries are fixed for the FTP user
        try:
            with pytest.raises(TransportError) as caught:
                ftp.delete("RO/P.nc")
        finally:
            (server.home / "RO").chmod(0o755)
            ftp.close()
        assert code_of(caught.value) is ErrorCode.PERMISSION_DENIED
        assert (server.home / "RO" / "P.nc").read_bytes() == b"p"


@pytest.mark.parametrize("kind", ("vsftpd", "proftpd"))
def test_a_file_the_server_will_not_read_is_20010_and_a_missing_one_158(
    kind: str, tmp_path: Path
) -> None:
    """vsftpd answers `550 Failed to open file.` whether the file is missing or unreadable."""
    with server_of(kind, tmp_path) as server:
        ftp = server.transport()
        put(ftp, "P.nc", b"p")
        (server.home / "P.nc").chmod(0o000)  # the FTP user owns it, and may not read it now
        try:
            with pytest.raises(TransportError) as unreadable:
                get(ftp, "P.nc")
            with pytest.raises(TransportError) as missing:
                get(ftp, "NONE.nc")
        finally:
            ftp.close()
    assert code_of(unreadable.value) is ErrorCode.PERMISSION_DENIED
    assert code_of(missing.value) is ErrorCode.PATH_NOT_FOUND


@pytest.mark.parametrize("kind", ("vsftpd", "proftpd"))
def test_a_write_into_a_folder_the_server_will_not_write_is_20010(
    kind: str, tmp_path: Path
) -> None:
    """vsftpd answers `553 Could not create file.` for any file it cannot create."""
    with server_of(kind, tmp_path) as server:
        ftp = server.transport()
        ftp.make_dir("RO")
        (server.home / "RO").chmod(0o555)
        try:
            with pytest.raises(TransportError) as caught:
                put(ftp, "RO/P.nc", b"p")
        finally:
            (server.home / "RO").chmod(0o755)
            ftp.close()
        assert code_of(caught.value) is ErrorCode.PERMISSION_DENIED


@pytest.mark.parametrize("kind", ("vsftpd", "proftpd", "no-mlsd"))
def test_links_list_as_what_they_lead_to_and_a_link_to_nothing_not_at_all(
    kind: str, tmp_path: Path
) -> None:
    """vsftpd's LIST and ProFTPD's MLSD give a link's own facts: a file of its name's size."""
    with server_of(kind, tmp_path) as server:
        ftp = server.transport()
        ftp.make_dir("D")
        put(ftp, "D/P.nc", b"p")
        put(ftp, "F.nc", b"G0 X1\n")
        for link, to in (("LD", "D"), ("LF.nc", "F.nc"), ("BROKEN.nc", "nowhere")):
            os.symlink(to, server.home / link)
        listed = {e.name: (e.is_dir, e.size) for e in ftp.list_dir("")}
        assert listed == {"D": (True, None), "F.nc": (False, 6), "LD": (True, None),
                          "LF.nc": (False, 6)}
        assert names(ftp.list_dir("LD")) == {"P.nc"}
        ftp.close()


@pytest.mark.parametrize("kind", ("plain", "vsftpd", "proftpd", "no-mlsd"))
def test_a_link_stats_as_it_lists_as_what_it_leads_to(kind: str, tmp_path: Path) -> None:
    """ProFTPD's MLST gives a link to a file `type=file` and the link's own size and time."""
    with server_of(kind, tmp_path) as server:
        ftp = server.transport()
        ftp.make_dir("D")
        put(ftp, "F.nc", b"G0 X1\n")
        for link, to in (("LD", "D"), ("LF.nc", "F.nc")):
            os.symlink(to, server.home / link)
        listed = {e.name: e for e in ftp.list_dir("")}
        assert ftp.stat("LF.nc") == listed["LF.nc"]
        assert ftp.stat("LF.nc").size == 6
        assert ftp.stat("LD").is_dir
        ftp.close()


def test_removing_a_missing_folder_is_158(transport: FtpTransport) -> None:
    with pytest.raises(TransportError) as caught:
        transport.remove_dir("NODIR")
    assert code_of(caught.value) is ErrorCode.PATH_NOT_FOUND


def test_removing_a_folder_that_holds_a_file_is_20009(transport: FtpTransport) -> None:
    transport.make_dir("F")
    put(transport, "F/P.nc", b"p")
    with pytest.raises(TransportError) as caught:
        transport.remove_dir("F")
    assert code_of(caught.value) is ErrorCode.DIR_NOT_EMPTY


def test_making_a_folder_that_is_there_is_142(transport: FtpTransport) -> None:
    transport.make_dir("E")
    with pytest.raises(TransportError) as caught:
        transport.make_dir("E")
    assert code_of(caught.value) is ErrorCode.PATH_EXISTS


def test_making_a_folder_in_a_missing_folder_is_158(transport: FtpTransport) -> None:
    with pytest.raises(TransportError) as caught:
        transport.make_dir("NODIR/SUB")
    assert code_of(caught.value) is ErrorCode.PATH_NOT_FOUND


def test_an_empty_folder_is_removed(transport: FtpTransport) -> None:
    transport.make_dir("E")
    transport.remove_dir("E")
    assert "E" not in names(transport.list_dir(""))


def test_removing_a_folder_that_holds_only_a_dot_file_is_20009(transport: FtpTransport) -> None:
    transport.make_dir("F")
    put(transport, "F/.keep", b"")  # vsftpd lists no dot files
    with pytest.raises(TransportError) as caught:
        transport.remove_dir("F")
    assert code_of(caught.value) is ErrorCode.DIR_NOT_EMPTY


def test_making_a_dot_folder_that_is_there_is_142(transport: FtpTransport) -> None:
    transport.make_dir(".cfg")
    with pytest.raises(TransportError) as caught:
        transport.make_dir(".cfg")
    assert code_of(caught.value) is ErrorCode.PATH_EXISTS


def test_a_missing_file_named_like_tls_is_158_not_a_tls_refusal(transport: FtpTransport) -> None:
    with pytest.raises(TransportError) as caught:
        transport.delete("tls.nc")
    assert code_of(caught.value) is ErrorCode.PATH_NOT_FOUND


def test_servers_without_avbl_do_not_say_their_free_space(transport: FtpTransport) -> None:
    """vsftpd, ProFTPD and pyftpdlib answer AVBL as an unknown command: nothing is invented."""
    assert transport.free_bytes() is None
    assert transport.list_dir("") == []  # the connection is still good after the refusal
