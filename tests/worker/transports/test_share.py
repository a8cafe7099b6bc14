"""The share transport passes the conformance suite: on a mounted folder and over SMB to Samba.

The SMB flavour runs against a real `smbd` on a loopback port, with a private smb.conf
and a system user of its own; where Samba cannot run, those tests skip with the reason.
"""

from __future__ import annotations

import errno
import os
import pwd
import shutil
import signal
import subprocess
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from pydantic import SecretStr, ValidationError

from jobs.errors import ErrorCode, from_transport
from tests.servers import free_port, unavailable, wait_for_port
from tests.worker.transports.contract import *  # noqa: F403
from tests.worker.transports.contract import get, names, put
from tests.worker.transports.tcp_proxy import CuttableProxy, make_proxy  # noqa: F401
from worker.transports.base import (
    BadPath,
    ConnectFailed,
    Exists,
    NotFound,
    PermissionDenied,
    TimedOut,
    Transport,
    Unsupported,
)
from worker.transports.share import PART_PREFIX, ShareTransport
from worker.transports.share_options import ShareOptions

SMB_USER = "dncqtest"
SMB_PASSWORD = "dncq-Test-1"  # a throwaway account that only this test's smbd knows
SMB_SHARE = "dncq"


class SambaServer:
    """An smbd on a loopback port serving one share from a temporary folder."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.share_dir = folder / "share"
        self.port = free_port()
        self.conf = folder / "smb.conf"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        smbd, smbpasswd = shutil.which("smbd", path=_SBIN), shutil.which("smbpasswd", path=_SBIN)
        if smbd is None or smbpasswd is None:
            unavailable("Samba is not installed (apt-get install -y samba)")
            return  # unavailable() raises; this tells the type checker
        if os.geteuid() != 0:
            unavailable("smbd needs root here (it switches to the share's user)")
            return
        try:
            pwd.getpwnam(SMB_USER)
        except KeyError:
            subprocess.run(["useradd", "-M", "-s", "/usr/sbin/nologin", SMB_USER],
                           check=True, capture_output=True)
        for sub in ("private", "lock", "state", "cache", "pid", "share"):
            (self.folder / sub).mkdir()
        self.folder.chmod(0o755)  # smbd serves the share as the user, who must reach it
        self.share_dir.chmod(0o777)
        self.conf.write_text(_SMB_CONF.format(folder=self.folder, port=self.port,
                                              share=SMB_SHARE, user=SMB_USER))
        subprocess.run([smbpasswd, "-c", str(self.conf), "-s", "-a", SMB_USER],
                       input=f"{SMB_PASSWORD}\n{SMB_PASSWORD}\n".encode(), check=True,
                       capture_output=True)
        self.proc = subprocess.Popen(
            [smbd, "--foreground", "--no-process-group", f"--configfile={self.conf}"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            wait_for_port(self.port)
        except TimeoutError:
            self.stop()
            log = self.folder / "log.smbd"
            unavailable(f"smbd did not start: {log.read_text()[-500:] if log.exists() else ''}")

    def stop(self) -> None:
        """Stop smbd and the children it forked for each connection (its own session)."""
        if self.proc is not None:
            try:
                os.killpg(self.proc.pid, signal.SIGTERM)
                self.proc.wait(timeout=10)
            except ProcessLookupError:
                pass
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
            self.proc = None

    def options(self, **changes: object) -> ShareOptions:
        values: dict[str, object] = {
            "server": "127.0.0.1", "share": SMB_SHARE, "port": self.port, "user": SMB_USER,
            "password": SecretStr(SMB_PASSWORD), **changes,
        }
        return ShareOptions.model_validate(values)


_SBIN = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"

_SMB_CONF = """\
[global]
  server role = standalone server
  smb ports = {port}
  interfaces = 127.0.0.1
  bind interfaces only = yes
  private dir = {folder}/private
  lock directory = {folder}/lock
  state directory = {folder}/state
  cache directory = {folder}/cache
  pid directory = {folder}/pid
  ncalrpc dir = {folder}/ncalrpc
  log file = {folder}/log.smbd
  max log size = 1000
  passdb backend = tdbsam
  map to guest = never
  server min protocol = SMB2_02
  load printers = no
  printing = bsd
  printcap name = /dev/null
  disable spoolss = yes
  unix charset = UTF-8

[{share}]
  path = {folder}/share
  read only = no
  valid users = {user}
  create mask = 0644
  directory mask = 0755
"""


@pytest.fixture(scope="session")
def samba_server() -> Iterator[SambaServer]:
    folder = Path(tempfile.mkdtemp(prefix="dncq-samba-"))  # not under pytest's 0700 tmp
    server = SambaServer(folder)
    try:
        server.start()
        yield server
    finally:
        server.stop()
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def smb_folder(samba_server: SambaServer, request: pytest.FixtureRequest) -> Iterator[str]:
    """An empty folder in the share, for one test: its name below the share's top."""
    name = f"t-{abs(hash(request.node.nodeid)):x}"
    local = samba_server.share_dir / name
    local.mkdir()
    local.chmod(0o777)
    yield name
    shutil.rmtree(local, ignore_errors=True)


@pytest.fixture(params=["mounted", "mounted-without-hard-links", "smb"])
def transport(
    request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[ShareTransport]:
    if request.param == "smb":
        server: SambaServer = request.getfixturevalue("samba_server")
        share = ShareTransport(server.options(subfolder=request.getfixturevalue("smb_folder")))
    else:
        if request.param == "mounted-without-hard-links":
            monkeypatch.setattr(os, "link", _no_hard_links)  # as on many CIFS and FAT mounts
        share = ShareTransport(ShareOptions(path=str(tmp_path)))
    yield share
    share.close()


def _no_hard_links(src: object, dst: object, **_: object) -> None:
    raise PermissionError(errno.EPERM, "Operation not permitted")


def test_options_take_either_a_mount_or_a_server() -> None:
    with pytest.raises(ValidationError):
        ShareOptions()
    with pytest.raises(ValidationError):
        ShareOptions(path="/mnt/share", server="nas")
    with pytest.raises(ValidationError):
        ShareOptions(server="nas")  # no share
    with pytest.raises(ValidationError):
        ShareOptions(path="relative/dir")
    with pytest.raises(ValidationError):
        ShareOptions(path="/mnt/share", user="u")


def test_a_transport_declares_what_a_shared_folder_is() -> None:
    share = ShareTransport(ShareOptions(path="/nonexistent"))
    assert isinstance(share, Transport)
    assert share.own_storage is False and share.server_row == "Shared folder"
    assert share.capabilities.folders and share.capabilities.make_dirs
    with pytest.raises(Unsupported):
        share.current_program()


def test_paths_that_leave_the_share_are_bad(transport: ShareTransport) -> None:
    for path in ("../x.nc", "/etc/passwd", "a//b.nc", "./x.nc"):
        with pytest.raises(BadPath):
            transport.stat(path)


def test_write_leaves_no_part_file_after_success_or_failure(transport: ShareTransport) -> None:
    put(transport, "A.nc", b"a")
    with pytest.raises(Exists):
        put(transport, "A.nc", b"b")
    assert names(transport.list_dir("")) == {"A.nc"}
    assert not any(n.startswith(PART_PREFIX) for n in _raw_names(transport))


def test_a_part_file_is_never_stat_or_read(transport: ShareTransport) -> None:
    part = f"{PART_PREFIX}abc"
    with transport._folder.create(part) as f:  # a half-written file, there on the share
        f.write(b"half")
    with pytest.raises(NotFound):
        transport.stat(part)
    with pytest.raises(NotFound):
        b"".join(transport.read(part))


def test_a_rename_onto_a_name_taken_meanwhile_is_exists(transport: ShareTransport) -> None:
    """The final rename, not only the early check, refuses to replace."""
    put(transport, "RACE.nc", b"first")
    folder = transport._folder
    part = f"{PART_PREFIX}manual"
    with folder.create(part) as f:
        f.write(b"second")
    with pytest.raises(Exists), transport._mapped("RACE.nc"):
        folder.rename_noreplace(part, "RACE.nc")
    folder.remove(part)
    assert get(transport, "RACE.nc") == b"first"


def test_deleting_a_folder_as_a_file_is_not_found(transport: ShareTransport) -> None:
    transport.make_dir("DIR")
    with pytest.raises(NotFound):
        transport.delete("DIR")
    assert "DIR" in names(transport.list_dir(""))


def test_a_missing_mount_point_is_connect_failed(tmp_path: Path) -> None:
    share = ShareTransport(ShareOptions(path=str(tmp_path / "not-mounted")))
    with pytest.raises(ConnectFailed):
        share.list_dir("")


def test_a_wrong_smb_password_is_permission_denied(samba_server: SambaServer) -> None:
    share = ShareTransport(samba_server.options(password=SecretStr("wrong")))
    try:
        with pytest.raises(PermissionDenied):
            share.list_dir("")
    finally:
        share.close()


def test_an_smb_server_that_does_not_listen_is_connect_failed() -> None:
    share = ShareTransport(ShareOptions(server="127.0.0.1", share="x", port=free_port(),
                                        user="u", password=SecretStr("p")))
    try:
        with pytest.raises(ConnectFailed):
            share.list_dir("")
    finally:
        share.close()


def test_an_smb_share_that_does_not_exist_is_not_found(samba_server: SambaServer) -> None:
    share = ShareTransport(samba_server.options(share="nosuchshare"))
    try:
        with pytest.raises(NotFound):
            share.list_dir("")
    finally:
        share.close()


@pytest.mark.timeout(60)  # before: the wait had no end
def test_an_smb_server_that_stops_answering_is_cut_off_after_timeout_s(
    samba_server: SambaServer, smb_folder: str,
    make_proxy: Callable[[int], CuttableProxy],  # noqa: F811
) -> None:
    proxy = make_proxy(samba_server.port)
    share = ShareTransport(samba_server.options(port=proxy.port, subfolder=smb_folder,
                                                timeout_s=1))
    try:
        put(share, "A.nc", b"a")
        proxy.pause()  # connected, and not a byte back: a switch or a server that froze
        with pytest.raises(TimedOut, match="timeout_s") as caught:
            share.list_dir("")
        assert from_transport(caught.value).code is ErrorCode.MACHINE_TIMEOUT
    finally:
        proxy.resume()
        share.close()


def test_smb_writes_land_in_the_subfolder_on_the_server(
    samba_server: SambaServer, smb_folder: str
) -> None:
    share = ShareTransport(samba_server.options(subfolder=smb_folder))
    try:
        put(share, "Teil-ä.nc", b"%\nO1000\n%\n")
    finally:
        share.close()
    assert (samba_server.share_dir / smb_folder / "Teil-ä.nc").read_bytes() == b"%\nO1000\n%\n"


def _raw_names(transport: ShareTransport) -> set[str]:
    """Every name at the top, part files included."""
    return {e.name for e in transport._folder.list("")}


@pytest.fixture
def mounted(tmp_path: Path) -> Iterator[tuple[ShareTransport, Path, Path]]:
    """A mounted share at `share/`, and a folder beside it that the share must not reach."""
    share_dir, outside = tmp_path / "share", tmp_path / "outside"
    share_dir.mkdir()
    outside.mkdir()
    (outside / "secret.nc").write_bytes(b"SECRET")
    share = ShareTransport(ShareOptions(path=str(share_dir)))
    yield share, share_dir, outside
    share.close()


def test_links_out_of_the_share_are_neither_listed_nor_followed(mounted) -> None:
    share, share_dir, outside = mounted
    (share_dir / "escape.nc").symlink_to(outside / "secret.nc")
    (share_dir / "out").symlink_to(outside)
    (share_dir / "in").mkdir()
    (share_dir / "in" / "A.nc").write_bytes(b"A")
    (share_dir / "inside.nc").symlink_to(share_dir / "in" / "A.nc")  # a link that stays in

    assert names(share.list_dir("")) == {"in", "inside.nc"}
    assert get(share, "inside.nc") == b"A"
    for path in ("escape.nc", "out/secret.nc"):
        with pytest.raises(PermissionDenied):
            get(share, path)
        with pytest.raises(PermissionDenied):
            share.delete(path)
    with pytest.raises(PermissionDenied):
        share.list_dir("out")
    with pytest.raises(PermissionDenied):
        put(share, "out/new.nc", b"X")
    assert sorted(p.name for p in outside.iterdir()) == ["secret.nc"]
    assert (outside / "secret.nc").read_bytes() == b"SECRET"


@pytest.mark.parametrize("odd", ["link loop", "pipe"])
def test_what_is_neither_file_nor_folder_is_not_listed_and_not_found_at_once(
        mounted, odd) -> None:
    share, share_dir, _ = mounted
    if odd == "pipe":
        os.mkfifo(share_dir / "odd.nc")  # opening it to read would wait for a writer
    else:
        (share_dir / "odd.nc").symlink_to(share_dir / "odd.nc")
    (share_dir / "A.nc").write_bytes(b"A")

    assert names(share.list_dir("")) == {"A.nc"}
    with pytest.raises(NotFound):
        share.stat("odd.nc")
    with pytest.raises(NotFound):
        get(share, "odd.nc")


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EDQUOT, errno.EFBIG])
def test_a_full_disk_refuses_the_file_as_permission_denied(mounted, monkeypatch, code) -> None:
    share, share_dir, _ = mounted

    create = share._folder.create

    class FullDisk:
        """The real part file, on a disk that refuses every byte."""

        def __init__(self, path: str) -> None:
            self.file = create(path)

        def write(self, _data: bytes) -> int:
            raise OSError(code, os.strerror(code))

        def close(self) -> None:
            self.file.close()

    monkeypatch.setattr(share._folder, "create", FullDisk)
    with pytest.raises(PermissionDenied):
        put(share, "big.nc", b"X" * 1000)
    assert list(share_dir.iterdir()) == []  # neither the file nor its part file


def test_the_share_tells_its_free_space(transport: ShareTransport, tmp_path: Path) -> None:
    """Samba's and the mounted folder's volume are this host's temporary file system."""
    told = transport.free_bytes()

    assert told is not None
    assert abs(told - shutil.disk_usage(tmp_path).free) < 256 * 1024**2
