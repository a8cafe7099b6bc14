"""pyftpdlib servers on loopback for the tests: plain, FTPS, no MLSD, latin-1."""

from __future__ import annotations

import contextlib
import datetime
import ipaddress
import logging
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from tests.servers import unavailable
from worker.transports.ftp import FtpOptions, FtpTransport

pyftpdlib = pytest.importorskip("pyftpdlib", reason="pyftpdlib is not installed")
from pyftpdlib.authorizers import DummyAuthorizer  # noqa: E402
from pyftpdlib.handlers import FTPHandler  # noqa: E402
from pyftpdlib.ioloop import IOLoop  # noqa: E402
from pyftpdlib.servers import FTPServer  # noqa: E402

PASSWORD = "s3cret-Pa55-word"
USER = "cnc"
KINDS = ("plain", "tls", "no-mlsd", "latin-1")

logging.getLogger("pyftpdlib").setLevel(logging.WARNING)


@dataclass
class FtpServer:
    """A pyftpdlib server running in a thread; `logins` counts successful logins."""

    port: int
    home: Path
    options: dict[str, Any]
    logins: list[str] = field(default_factory=list)

    def transport(self, **changes: Any) -> FtpTransport:
        return FtpTransport(FtpOptions(**{**self.options, **changes}))


def self_signed_cert(folder: Path) -> Path:
    """A certificate and key for 127.0.0.1 in one PEM file."""
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import NameOID
    except ImportError:
        unavailable("the cryptography package is needed to make a test certificate")
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder().subject_name(name).issuer_name(name)
        .public_key(key.public_key()).serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.SubjectAlternativeName(
            [x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), critical=False)
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    pem = folder / "server.pem"
    pem.write_bytes(
        cert.public_bytes(serialization.Encoding.PEM)
        + key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                            serialization.NoEncryption()))
    return pem


def _handler_class(kind: str, folder: Path, logins: list[str]) -> type[FTPHandler]:
    base: type[FTPHandler] = FTPHandler
    attrs: dict[str, Any] = {"auth_failed_timeout": 0}  # no 3 s pause after a bad password
    if kind == "tls":
        try:
            from pyftpdlib.handlers import TLS_FTPHandler
        except ImportError:
            unavailable("pyftpdlib needs pyOpenSSL for FTPS (pip install pyopenssl)")
        base = TLS_FTPHandler
        attrs.update(certfile=str(self_signed_cert(folder)), tls_control_required=True,
                     tls_data_required=True)
    if kind == "no-mlsd":
        attrs["proto_cmds"] = {k: v for k, v in FTPHandler.proto_cmds.items()
                               if k not in ("MLSD", "MLST")}
    if kind == "latin-1":
        attrs["encoding"] = "latin-1"

    def on_login(self: FTPHandler, username: str) -> None:
        logins.append(username)

    attrs["on_login"] = on_login
    return type(f"Handler_{kind.replace('-', '_')}", (base,), attrs)


def counting(command: str, seen: list[str]) -> Any:
    """A handler method for `command` (`"SIZE"`): each argument noted in `seen`, then
    answered as pyftpdlib answers it. Given to `ftp_server_of` as `ftp_<command>=`."""
    answer = getattr(FTPHandler, f"ftp_{command}")

    def counted(self: FTPHandler, line: str) -> None:
        seen.append(line)
        answer(self, line)

    return counted


@contextlib.contextmanager
def ftp_server_of(kind: str, folder: Path, *, perm: str = "elradfmwMT",
                  **handler_attrs: Any) -> Iterator[FtpServer]:
    """A pyftpdlib server of `kind` on a loopback port, with a user that has a password
    and the rights `perm` (pyftpdlib's letters: all by default)."""
    home = folder / "home"
    home.mkdir(parents=True)
    logins: list[str] = []
    handler = _handler_class(kind, folder, logins)
    for name, value in handler_attrs.items():
        setattr(handler, name, value)
    authorizer = DummyAuthorizer()
    authorizer.add_user(USER, PASSWORD, str(home), perm=perm)
    handler.authorizer = authorizer
    # A loop of its own: pyftpdlib's default is one per process, and closing a server
    # closes that loop with every socket on it, another test's server's among them.
    server = FTPServer(("127.0.0.1", 0), handler, ioloop=IOLoop())
    port = server.address[1]
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            server.serve_forever(timeout=0.01, blocking=False, handle_exit=False)
        server.close_all()

    thread = threading.Thread(target=serve, name=f"ftpd-{kind}", daemon=True)
    thread.start()
    options: dict[str, Any] = {"host": "127.0.0.1", "port": port, "user": USER,
                               "password": PASSWORD, "timeout_s": 10.0}
    if kind == "tls":
        options.update(tls=True, tls_ca_file=str(folder / "server.pem"))
    if kind == "latin-1":
        options["encoding"] = "latin-1"
    try:
        yield FtpServer(port, home, options, logins)
    finally:
        stop.set()
        thread.join(timeout=30)
        assert not thread.is_alive(), f"the {kind} FTP server on port {port} did not stop"
