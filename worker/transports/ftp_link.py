"""FTP connections: opening one (plain, or explicit FTPS whose data connections resume the
control connection's TLS session), probing a kept one, ending a transfer."""

from __future__ import annotations

import contextlib
import ftplib
import select
import socket
import ssl

from pydantic import Field, SecretStr

from worker.transports.base import HostName, NetworkOptions
from worker.transports.ftp_errors import translated


class FtpOptions(NetworkOptions):
    """Options of an FTP machine (fleet file `options:`)."""

    host: HostName
    """Host name or address of the FTP server."""
    port: int = Field(default=21, ge=1, le=65535)
    """Control connection port."""
    user: str = "anonymous"
    """Login name."""
    password: SecretStr | None = None
    """Login password; None for an empty one (anonymous)."""
    tls: bool = False
    """Explicit FTPS (AUTH TLS), with the data connections protected too (PROT P)."""
    tls_verify: bool = True
    """Check the server's certificate and name; off only for a machine on a trusted link."""
    tls_ca_file: str | None = None
    """PEM file of the certificates to trust instead of the system's (self-signed machines)."""
    passive: bool = True
    """Passive mode (the client opens the data connections)."""
    encoding: str = "utf-8"
    """How the server encodes file names (`latin-1`, `cp932` ... for older controllers)."""
    keep_connection_s: float = Field(default=30.0, ge=0)
    """How long a logged-in connection is kept after a job's last use, for the next job
    (worker.transports.ftp_pool); 0 ends it when the job is done, for a control that
    allows only one session at a time."""

    def connection_key(self) -> tuple[object, ...]:
        """What makes two machines' connections interchangeable: server, account, mode."""
        password = self.password.get_secret_value() if self.password else ""
        return (self.host, self.port, self.user, password, self.tls, self.tls_verify,
                self.tls_ca_file, self.passive, self.encoding, self.timeout_s)


def open_link(opts: FtpOptions) -> ftplib.FTP:
    """A logged-in connection in binary mode; FTPS with the data connections protected."""
    ftp: ftplib.FTP
    if opts.tls:
        context = ssl.create_default_context(cafile=opts.tls_ca_file)
        if not opts.tls_verify:
            context.check_hostname = False
            context.verify_mode = ssl.CERT_NONE
        ftp = SessionReusingFTP(context=context, timeout=opts.timeout_s, encoding=opts.encoding)
    else:
        ftp = DirectDataFTP(timeout=opts.timeout_s, encoding=opts.encoding)
    try:
        with translated("connect", f"{opts.host}:{opts.port}"):
            ftp.connect(opts.host, opts.port)
            password = opts.password.get_secret_value() if opts.password else ""
            ftp.login(opts.user, password)
            if isinstance(ftp, ftplib.FTP_TLS):
                ftp.prot_p()
            ftp.set_pasv(opts.passive)
            ftp.voidcmd("TYPE I")  # binary: NC programs keep their bytes, SIZE is allowed
            if opts.encoding.replace("-", "").lower() == "utf8":
                with contextlib.suppress(ftplib.error_perm):
                    ftp.sendcmd("OPTS UTF8 ON")  # some servers switch only when asked
    except BaseException:
        ftp.close()
        raise
    return ftp


def transfer_directly(ftp: ftplib.FTP, cmd: str, rest: int | str | None
                      ) -> tuple[socket.socket, int | None]:
    """`ftp.ntransfercmd(cmd, rest)`, its passive data connection opened without a name lookup.

    ftplib opens it with `socket.create_connection`, which looks the address up even
    though it is one already (the control connection's peer: ftplib does not trust the
    host a PASV answer names). On a gevent worker a lookup goes to a native thread and
    back: 7 % of a worker's interpreter time in a backup of 1000 programs over FTP. A
    socket's own connect takes an address as it is.
    """
    if not ftp.passiveserver:  # type: ignore[attr-defined]
        return ftplib.FTP.ntransfercmd(ftp, cmd, rest)
    host, port = ftp.makepasv()
    conn = socket.socket(ftp.af, socket.SOCK_STREAM)  # type: ignore[attr-defined]
    try:
        conn.settimeout(ftp.timeout)  # type: ignore[attr-defined]
        conn.connect((host, port))
        if rest is not None:
            ftp.sendcmd(f"REST {rest}")
        reply = ftp.sendcmd(cmd)
        if reply[0] == "2":  # some servers say 2xx before the 1xx of the transfer
            reply = ftp.getresp()
        if reply[0] != "1":
            raise ftplib.error_reply(reply)
    except BaseException:
        conn.close()
        raise
    return conn, ftplib.parse150(reply) if reply[:3] == "150" else None


class DirectDataFTP(ftplib.FTP):
    """Plain FTP whose passive data connections skip the name lookup (`transfer_directly`)."""

    def ntransfercmd(
        self, cmd: str, rest: int | str | None = None
    ) -> tuple[socket.socket, int | None]:
        return transfer_directly(self, cmd, rest)


class SessionReusingFTP(ftplib.FTP_TLS):
    """FTPS whose data connections resume the control connection's TLS session.

    vsftpd (`require_ssl_reuse=YES`) and ProFTPD (mod_tls without
    `NoSessionReuseRequired`) refuse, by default, a data connection with a TLS session
    of its own: it proves the data connection comes from the client that logged in.
    Their passive data connections skip the name lookup too (`transfer_directly`).
    """

    def ntransfercmd(
        self, cmd: str, rest: int | str | None = None
    ) -> tuple[socket.socket, int | None]:
        conn, size = transfer_directly(self, cmd, rest)
        if self._prot_p:  # type: ignore[attr-defined]
            session = self.sock.session if isinstance(self.sock, ssl.SSLSocket) else None
            conn = self.context.wrap_socket(conn, server_hostname=self.host, session=session)
        return conn, size


def alive(ftp: ftplib.FTP) -> bool:
    """Whether a kept connection still answers."""
    try:
        ftp.voidcmd("NOOP")
    except (ftplib.Error, OSError, EOFError):
        return False
    return True


def quiet(ftp: ftplib.FTP) -> bool:
    """Whether the server has sent nothing since its last reply, asked without a round trip.

    A server sends nothing unasked but a 421 before it hangs up, or the end of the stream:
    anything waiting to be read means the connection must be probed (or is gone).
    """
    sock = ftp.sock
    if sock is None:
        return False
    if isinstance(sock, ssl.SSLSocket) and sock.pending():
        return False
    readable, _, _ = select.select([sock], [], [], 0)
    return not readable


def finish(ftp: ftplib.FTP, conn: socket.socket) -> None:
    """End a transfer: close the TLS layer and the data link, then read the final reply."""
    if isinstance(conn, ssl.SSLSocket):
        conn.unwrap()
    conn.close()
    ftp.voidresp()
