"""The OctoPrint transport passes the conformance suite against a real OctoPrint on loopback.

OctoPrint is installed from PyPI into a virtual environment of its own (see `octoprint_server`).
Its `sdcard` origin is not run here: it needs the virtual printer connected over a
serial emulation, has no folders and no download, and streams uploads asynchronously.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator

import pytest
from pydantic import SecretStr

from tests.worker.transports.contract import *  # noqa: F403
from tests.worker.transports.octoprint_server import OctoPrintServer, empty_octoprint
from worker.transports.base import BadPath, PermissionDenied
from worker.transports.octoprint import OctoPrintOptions, OctoPrintTransport


@pytest.fixture
def transport(octoprint_server: OctoPrintServer) -> Iterator[OctoPrintTransport]:
    empty_octoprint(octoprint_server)
    octo = OctoPrintTransport(OctoPrintOptions(url=octoprint_server.url,  # type: ignore[arg-type]
                                               api_key=SecretStr(octoprint_server.api_key)))
    yield octo
    octo.close()


def test_a_wrong_api_key_is_permission_denied(octoprint_server: OctoPrintServer) -> None:
    octo = OctoPrintTransport(OctoPrintOptions(url=octoprint_server.url,  # type: ignore[arg-type]
                                               api_key=SecretStr("wrong-key")))
    try:
        with pytest.raises(PermissionDenied) as raised:
            octo.list_dir("")
        assert "wrong-key" not in str(raised.value)
    finally:
        octo.close()


def test_the_api_key_never_shows_in_the_options_repr(octoprint_server: OctoPrintServer) -> None:
    options = OctoPrintOptions(url=octoprint_server.url,  # type: ignore[arg-type]
                               api_key=SecretStr(octoprint_server.api_key))
    assert octoprint_server.api_key not in repr(options)
    assert octoprint_server.api_key not in options.model_dump_json()


def test_a_name_octoprint_does_not_take_is_bad_path(transport: OctoPrintTransport) -> None:
    with pytest.raises(BadPath):
        transport.write("P.exe", iter([b"x"]))


def test_octoprint_tells_the_free_space_of_its_uploads(transport: OctoPrintTransport) -> None:
    """OctoPrint's uploads folder is on this host's temporary file system."""
    import tempfile

    told = transport.free_bytes()

    assert told is not None
    assert abs(told - shutil.disk_usage(tempfile.gettempdir()).free) < 256 * 1024**2
