"""An upload's retry after an attempt the FTP server cut off removes the temporary file that
attempt left, in whichever worker process the retry runs, against the real servers."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from jobs.errors import ContractError
from jobs.run import targets as runs
from jobs.settings import Settings
from tests.jobs.helpers import wait_until
from tests.jobs.run.test_crash import PROGRAM, claim, create, files_of, register
from tests.worker.transports.ftp_daemons import server_of
from tests.worker.transports.tcp_proxy import CuttableProxy, make_proxy  # noqa: F401
from worker import operations
from worker.transports import ftp
from worker.transports.base import PART_PREFIX


@pytest.mark.parametrize("kind", ("plain", "vsftpd", "proftpd"))
def test_a_retry_after_the_server_cut_an_upload_off_leaves_only_the_file(
        kind: str, settings: Settings, tmp_path: Path,
        make_proxy: Callable[[int], CuttableProxy],  # noqa: F811
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ftp, "_LEFT", ftp.LeftParts())  # none of an earlier test's
    s = settings.model_copy(update={"retry_base_s": 0.0, "retry_max_s": 0.0})
    with server_of(kind, tmp_path / "ftp") as server:
        proxy = make_proxy(server.port)
        register(s, [{"id": "m000", "name": "M0", "model": "FTP server", "transport": "ftp",
                      "options": {**server.options, "port": proxy.port, "timeout_s": 2.0,
                                  "keep_connection_s": 0}}])
        (server.home / f"{PART_PREFIX}0123abcd-{'f' * 32}").write_bytes(b"another file's")
        job_id = create(s, [{"machineID": "m000", "fileName": "P.nc"}])

        first, holder = claim(s, job_id)
        other = {p.name for p in server.home.iterdir()}

        def server_gone() -> None:  # once the server made the temporary file for the upload
            wait_until(lambda: len(list(server.home.iterdir())) > len(other), timeout_s=10)
            proxy.down()

        proxy.cut_after(b"STOR", server_gone)
        with files_of(s, "m000") as files, pytest.raises(ContractError, match="left behind") \
                as cut:
            operations.execute(s, files, first)
        left = {p.name for p in server.home.iterdir()}
        proxy.up()
        runs.finish(settings=s, work=first, holder=holder, error=cut.value)

        ftp._LEFT.clear()  # the retry runs in another worker process
        again, holder = claim(s, job_id)
        with files_of(s, "m000") as files:
            assert operations.execute(s, files, again).error is None
        runs.finish(settings=s, work=again, holder=holder, error=None)

        assert len(left) == 2  # the attempt's temporary file beside the other file's
        assert {p.name for p in server.home.iterdir()} == {
            "P.nc", f"{PART_PREFIX}0123abcd-{'f' * 32}"}
        assert (server.home / "P.nc").read_bytes() == PROGRAM
