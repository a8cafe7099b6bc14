"""Temporary files a share's failed uploads leave behind: removed by the file's next upload,
or by an upload into their folder once nobody has written them for long, against Samba."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from tests.worker.transports.contract import get, put
from tests.worker.transports.tcp_proxy import CuttableProxy, make_proxy  # noqa: F401
from tests.worker.transports.test_share import (  # noqa: F401
    SambaServer,
    samba_server,
    smb_folder,
)
from worker.transports import share as share_module
from worker.transports.base import PART_PREFIX, TransportError, parts_of
from worker.transports.left_parts import LeftParts
from worker.transports.share import STILL_WRITING_S, ShareTransport
from worker.transports.share_options import ShareOptions


@pytest.fixture(params=["mounted", "smb"])
def share(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[ShareTransport, Path]]:
    """A share, and the folder on this host that holds its files."""
    if request.param == "smb":
        server: SambaServer = request.getfixturevalue("samba_server")
        folder = request.getfixturevalue("smb_folder")
        transport = ShareTransport(server.options(subfolder=folder))
        yield transport, server.share_dir / folder
    else:
        transport = ShareTransport(ShareOptions(path=str(tmp_path)))
        yield transport, tmp_path
    transport.close()


def test_a_file_sent_again_after_the_server_went_away_mid_write_leaves_no_temporary_file(
    samba_server: SambaServer, smb_folder: str,  # noqa: F811
    make_proxy: Callable[[int], CuttableProxy],  # noqa: F811
) -> None:
    proxy = make_proxy(samba_server.port)
    share = ShareTransport(samba_server.options(port=proxy.port, subfolder=smb_folder,
                                                timeout_s=5, connect_timeout_s=2))
    on_disk = samba_server.share_dir / smb_folder

    def chunks() -> Iterator[bytes]:
        yield b"x" * 300_000
        proxy.down()  # the server is gone, and stays away past the write's clean-up
        yield b"x" * 300_000

    try:
        with pytest.raises(TransportError, match="left behind") as caught:
            share.write("P.nc", chunks())
        [left] = [p.name for p in on_disk.iterdir()]
        assert left.startswith(PART_PREFIX) and repr(left) in str(caught.value)
        proxy.up()
        put(share, "P.nc", b"p" * 600_000)  # its retry

        assert [p.name for p in on_disk.iterdir()] == ["P.nc"]
    finally:
        share.close()


def test_a_write_removes_the_temporary_files_nobody_wrote_for_long(
    share: tuple[ShareTransport, Path],
) -> None:
    # Left by a write of another process (whose retry may come to any worker), or one killed.
    transport, on_disk = share
    stale, recent = (on_disk / f"{PART_PREFIX}{n}" for n in ("a1", "b2"))
    for part, unchanged_s in ((stale, STILL_WRITING_S + 60), (recent, STILL_WRITING_S - 60)):
        with transport._folder.create(part.name) as f:  # its writer, the share's user
            f.write(b"half")
        os.utime(part, (time.time() - unchanged_s,) * 2)

    put(transport, "P.nc", b"p")

    assert sorted(p.name for p in on_disk.iterdir()) == [recent.name, "P.nc"]


def test_a_part_being_written_over_smb_stays_whatever_time_the_server_gives_it(
    samba_server: SambaServer, smb_folder: str,  # noqa: F811
) -> None:
    # Samba gives an open file the time of its first write: a long write looks stale.
    writer, other = (ShareTransport(samba_server.options(subfolder=smb_folder))
                     for _ in range(2))
    on_disk = samba_server.share_dir / smb_folder

    def chunks() -> Iterator[bytes]:
        yield b"x" * 300_000
        [part] = on_disk.iterdir()
        os.utime(part, (time.time() - 2 * STILL_WRITING_S,) * 2)
        put(other, "OTHER.nc", b"o")  # its write sweeps the folder meanwhile
        yield b"x" * 300_000

    try:
        writer.write("LONG.nc", chunks())
        assert get(writer, "LONG.nc") == b"x" * 600_000
        assert sorted(p.name for p in on_disk.iterdir()) == ["LONG.nc", "OTHER.nc"]
    finally:
        writer.close()
        other.close()


def test_a_retry_in_another_process_removes_what_the_cut_off_write_left_but_no_open_part(
    samba_server: SambaServer, smb_folder: str,  # noqa: F811
    make_proxy: Callable[[int], CuttableProxy],  # noqa: F811
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    proxy = make_proxy(samba_server.port)
    share = ShareTransport(samba_server.options(port=proxy.port, subfolder=smb_folder,
                                                timeout_s=5, connect_timeout_s=2))
    retry, writer = (ShareTransport(samba_server.options(subfolder=smb_folder))
                     for _ in range(2))
    on_disk = samba_server.share_dir / smb_folder

    def chunks() -> Iterator[bytes]:
        yield b"x" * 300_000
        proxy.down()
        yield b"x" * 300_000

    try:
        with pytest.raises(TransportError, match="left behind"):
            share.write("P.nc", chunks())
        monkeypatch.setattr(share_module, "_LEFT", LeftParts())  # the retry's process
        still_open = writer._folder.create(f"{parts_of('P.nc')}{'e' * 32}")
        still_open.write(b"a write of P.nc still going")

        put(retry, "P.nc", b"p")
        retry.remove_parts_of("P.nc")

        assert sorted(p.name for p in on_disk.iterdir()) == [
            f"{parts_of('P.nc')}{'e' * 32}", "P.nc"]
        still_open.close()
    finally:
        for transport in (share, retry, writer):
            transport.close()
