"""A worker killed in the middle of an upload to vsftpd or ProFTPD: its target ends with one
result, run again by another worker, and the machine holds the file alone."""

from __future__ import annotations

import os
import signal
from collections.abc import Callable
from pathlib import Path

import pytest

from jobs import db, rollout, service
from jobs.job_options import JobOptions
from jobs.models import JobKind, TargetState
from jobs.settings import Settings
from tests.jobs.helpers import wait_until
from tests.jobs.run.test_crash import INTERRUPTED, finished, register, target_rows
from tests.worker.transports.ftp_daemons import ftp_daemon_of
from tests.workers import WorkerProcess
from worker.transports.base import PART_PREFIX

pytestmark = pytest.mark.slow

PROGRAM = b"G1 X1 Y1 F100\n" * 150_000  # 2.1 MB: seconds at the server's rate below
UPLOAD_BYTES_PER_S = 300_000


@pytest.mark.parametrize("kind", ["vsftpd", "proftpd"])
def test_a_worker_killed_mid_upload_leaves_the_file_once_and_no_temporary_file(
        kind: str, crash_settings: Settings, tmp_path: Path,
        start_worker: Callable[..., WorkerProcess]) -> None:
    s = crash_settings
    with ftp_daemon_of(kind, tmp_path / "ftp", upload_bytes_per_s=UPLOAD_BYTES_PER_S) as server:
        register(s, [{"id": "f1", "name": "F", "model": "FTP server", "transport": "ftp",
                      "options": server.options}])
        first = start_worker("a", s)
        first.wait_ready()
        with db.session_scope(s.resolved_database_url) as session:
            job_id = rollout.submit(
                session=session, settings=s, kind=JobKind.SEND,
                targets=[service.TargetIn.parse({"machineID": "f1", "fileName": "P.nc"})],
                options=JobOptions(),
                payload_id=service.store_payload(session=session, data=PROGRAM)).id

        def uploading() -> bool:
            return any(p.name.startswith(PART_PREFIX) and p.stat().st_size > UPLOAD_BYTES_PER_S
                       for p in server.home.iterdir())

        wait_until(uploading, timeout_s=30)
        os.kill(first.pid, signal.SIGKILL)
        second = start_worker("b", s)
        wait_until(lambda: finished(s, job_id), timeout_s=90)

        [target] = target_rows(s, job_id)
        assert target.state is TargetState.SUCCEEDED
        assert [(a.worker, a.error_code, a.error_msg) for a in target.history] == [
            (first.worker_name, None, INTERRUPTED), (second.worker_name, 0, None)]
        assert sorted(p.name for p in server.home.iterdir()) == ["P.nc"]
        assert (server.home / "P.nc").read_bytes() == PROGRAM
