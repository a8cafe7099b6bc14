"""vsftpd and ProFTPD on loopback for the tests, set up as an administrator would.

A local user with a password and a writable home (chrooted there), plain or explicit
FTPS with the servers' default TLS settings: both require a data connection to reuse
the control connection's TLS session. The user is a system account made here, so the
servers need root; ProFTPD is unpacked, not installed (its package conflicts with
vsftpd's), under DNCQ_PROFTPD_ROOT (scripts/test puts it there).
"""

from __future__ import annotations

import contextlib
import os
import pwd
import shutil
import signal
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from tests.servers import free_port, unavailable, wait_for_port
from tests.worker.transports.ftp_server import (
    PASSWORD,
    FtpServer,
    ftp_server_of,
    self_signed_cert,
)

DAEMON_KINDS = ("vsftpd", "vsftpd-tls", "proftpd", "proftpd-tls")
SYSTEM_USER = "dncqftp"  # the account both servers log in; its home is set per server
ACCOUNT_HOME = Path("/var/lib/dncq-ftp-test")  # exists so PAM's session opens; never used
PROFTPD_ROOT = Path(os.environ.get("DNCQ_PROFTPD_ROOT", "/opt/dncq-test/proftpd"))

_password_set: list[bool] = []  # once per test process: chpasswd is slow-ish


def _system_user() -> None:
    """The local account the servers authenticate, with the tests' password."""
    if os.geteuid() != 0:
        unavailable("vsftpd and ProFTPD log in a local user the tests create: run as root")
    ACCOUNT_HOME.mkdir(parents=True, exist_ok=True)
    try:
        pwd.getpwnam(SYSTEM_USER)
    except KeyError:
        made = subprocess.run(["useradd", "--system", "--no-create-home", "--home-dir",
                               str(ACCOUNT_HOME), "--shell", "/bin/sh", SYSTEM_USER],
                              capture_output=True)
        if made.returncode != 0:
            pwd.getpwnam(SYSTEM_USER)  # made meanwhile by another test process, or fail here
        _password_set.clear()
    if not _password_set:
        subprocess.run(["chpasswd"], input=f"{SYSTEM_USER}:{PASSWORD}".encode(), check=True)
        _password_set.append(True)


def _home() -> Path:
    """An empty home the user owns, outside pytest's folders, which only root may enter."""
    home = Path(tempfile.mkdtemp(prefix="dncq-ftp-home-"))
    home.chmod(0o755)
    user = pwd.getpwnam(SYSTEM_USER)
    os.chown(home, user.pw_uid, user.pw_gid)
    return home


def _vsftpd_config(folder: Path, home: Path, port: int, tls: bool,
                   upload_bytes_per_s: int | None) -> list[str]:
    binary = shutil.which("vsftpd") or "/usr/sbin/vsftpd"
    if not os.access(binary, os.X_OK):
        unavailable("vsftpd is not installed (apt-get install -y vsftpd)")
    empty = folder / "empty"  # vsftpd's secure_chroot_dir: root's, empty, not writable
    empty.mkdir(mode=0o755)
    lines = [
        "listen=YES", "listen_address=127.0.0.1", f"listen_port={port}", "background=NO",
        "anonymous_enable=NO", "local_enable=YES", "write_enable=YES", "local_umask=022",
        f"local_root={home}", "chroot_local_user=YES", "allow_writeable_chroot=YES",
        f"secure_chroot_dir={empty}", "pam_service_name=vsftpd", "xferlog_enable=NO",
        f"vsftpd_log_file={folder / 'vsftpd.log'}",
    ]
    if tls:  # the rest as shipped: require_ssl_reuse=YES, TLS forced for login and data
        lines += ["ssl_enable=YES", f"rsa_cert_file={folder / 'server.pem'}"]
    if upload_bytes_per_s:  # downloads too: vsftpd has one rate
        lines.append(f"local_max_rate={upload_bytes_per_s}")
    config = folder / "vsftpd.conf"
    config.write_text("\n".join(lines) + "\n")
    return [binary, str(config)]


def _proftpd_config(folder: Path, home: Path, port: int, tls: bool,
                    upload_bytes_per_s: int | None) -> list[str]:
    binary = PROFTPD_ROOT / "usr/sbin/proftpd"
    if not os.access(binary, os.X_OK):
        unavailable(f"ProFTPD is not unpacked under {PROFTPD_ROOT} (scripts/test does it)")
    lines = [
        "ServerType standalone", 'ServerName "dncq test"', "DefaultAddress 127.0.0.1",
        f"Port {port}", "UseIPv6 off", "UseReverseDNS off", "User nobody", "Group nogroup",
        f"PidFile {folder / 'proftpd.pid'}", f"ScoreboardFile {folder / 'proftpd.scoreboard'}",
        f"DelayTable {folder / 'proftpd.delay'}", "WtmpLog off",
        f"SystemLog {folder / 'proftpd.log'}", f"ModulePath {PROFTPD_ROOT / 'usr/lib/proftpd'}",
        "AuthOrder mod_auth_unix.c", f"DefaultRoot {home}",
    ]
    if tls:  # the rest as shipped: no NoSessionReuseRequired in TLSOptions
        pem = folder / "server.pem"
        lines += ["LoadModule mod_tls.c", "TLSEngine on", "TLSRequired on",
                  f"TLSECCertificateFile {pem}", f"TLSECCertificateKeyFile {pem}",
                  f"TLSLog {folder / 'proftpd-tls.log'}"]
    if upload_bytes_per_s:
        lines.append(f"TransferRate STOR {upload_bytes_per_s / 1024:g}")  # in KB/s
    config = folder / "proftpd.conf"
    config.write_text("\n".join(lines) + "\n")
    return [str(binary), "--nodaemon", "--quiet", "--config", str(config)]


@contextlib.contextmanager
def ftp_daemon_of(kind: str, folder: Path, *,
                  upload_bytes_per_s: int | None = None) -> Iterator[FtpServer]:
    """A vsftpd or ProFTPD server of `kind` (DAEMON_KINDS) on a loopback port; uploads to it
    as slow as `upload_bytes_per_s` if given."""
    name, _, variant = kind.partition("-")
    tls = variant == "tls"
    _system_user()
    folder.mkdir(parents=True, exist_ok=True)
    home = _home()
    if tls:
        self_signed_cert(folder)
    port = free_port()
    configure = _vsftpd_config if name == "vsftpd" else _proftpd_config
    command = configure(folder, home, port, tls, upload_bytes_per_s)
    log = (folder / f"{name}.out").open("wb")
    # A session of its own: each FTP session is a child process, stopped with the server.
    proc = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    try:
        try:
            wait_for_port(port, timeout_s=10)
        except TimeoutError:
            raise RuntimeError(f"{name} did not start: {(folder / f'{name}.out').read_text()}"
                               ) from None
        options: dict[str, Any] = {"host": "127.0.0.1", "port": port, "user": SYSTEM_USER,
                                   "password": PASSWORD, "timeout_s": 10.0}
        if tls:
            options.update(tls=True, tls_ca_file=str(folder / "server.pem"))
        yield FtpServer(port, home, options)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        log.close()
        shutil.rmtree(home, ignore_errors=True)


def server_of(kind: str, folder: Path) -> contextlib.AbstractContextManager[FtpServer]:
    """A pyftpdlib server (ftp_server.KINDS) or a real vsftpd or ProFTPD of `kind`."""
    return (ftp_daemon_of if kind in DAEMON_KINDS else ftp_server_of)(kind, folder)
