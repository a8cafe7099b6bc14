"""The options of a shared folder, read by both flavours (mounted and SMB) and the transport."""

from __future__ import annotations

import os

from pydantic import Field, SecretStr, model_validator

from worker.transports.base import HostName, TransportOptions

SMB_MISSING = 'SMB (server and share) needs the smbprotocol package: pip install "dncq[smb]"'


class ShareOptions(TransportOptions):
    """Options of a shared folder (fleet file `options:`): `path`, or `server` and `share`."""

    path: str | None = None
    """Mount point of the share on the worker host (absolute)."""
    server: HostName | None = None
    """SMB server host name or address, for SMB straight from the worker."""
    share: str | None = None
    """SMB share name on `server`."""
    port: int = Field(default=445, gt=0, lt=65536)
    """SMB server TCP port."""
    user: str | None = None
    """SMB user name; None for Kerberos from the worker's ticket."""
    password: SecretStr | None = None
    """SMB password."""
    subfolder: str = ""
    """SMB folder below the share's top that this machine's paths start from."""
    connect_timeout_s: float = Field(default=10.0, gt=0)
    """Time allowed for the SMB connection to be set up."""
    timeout_s: float = Field(default=30.0, gt=0)
    """Longest wait for the SMB server's answer to one operation (a list, a chunk read or
    written): a server silent for longer is cut off."""

    @model_validator(mode="after")
    def _one_flavour(self) -> ShareOptions:
        if (self.path is None) == (self.server is None):
            raise ValueError("give either path (a mounted folder) or server and share (SMB)")
        if self.path is not None:
            if not os.path.isabs(self.path):
                raise ValueError("path must be absolute")
            smb_only = {"server", "share", "port", "user", "password", "subfolder",
                        "timeout_s"}
            if given := sorted(smb_only & self.model_fields_set):
                raise ValueError(f"{', '.join(given)} only apply to SMB (server and share)")
        elif not self.share:
            raise ValueError("share is required with server")
        return self

    def missing_package(self) -> str | None:
        """The SMB extra, for `server` and `share` on a host without smbprotocol."""
        if self.server is None:
            return None
        try:
            import smbclient  # noqa: F401 - whether it imports is the question
        except ImportError:
            return SMB_MISSING
        return None
