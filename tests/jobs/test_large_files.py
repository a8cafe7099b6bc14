"""Memory with files far larger than it: comparing, backing up and restoring 1 GiB files.

The 1 GiB files are sparse files in the mock machines' storage (real files on disk, read
and written through the mock transport like any other). tracemalloc traces every Python
allocation of every thread of the process: the API's and the in-process worker's.
"""

from __future__ import annotations

import contextlib
import io
import tracemalloc
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.jobs.helpers import on_machine, run_backup, wait_done

GIB = 1 << 30
# The most a process may hold while moving one file, whatever its size (256 KiB chunks).
MEMORY_BOUND_BYTES = 16 << 20

pytestmark = pytest.mark.slow


@pytest.fixture
def big_file(queue_settings: Any, add_machines: Any) -> Path:
    """`BIG.nc`, 1 GiB of zeros but for a program head, on the mock machine `big`."""
    add_machines({"id": "big", "name": "Big", "model": "Mock"},
                 {"id": "spare", "name": "Spare", "model": "Mock"})
    path = on_machine(queue_settings, "big", "BIG.nc")
    with open(path, "wb") as f:
        f.write(b"%\nO1000\nG0 X1\n")
        f.truncate(GIB)  # sparse: costs no disk
    return path


@contextlib.contextmanager
def traced() -> Iterator[list[int]]:
    """Trace allocations; once the block ends, the list holds the peak in bytes."""
    peak = [0]
    tracemalloc.start()
    try:
        yield peak
        peak[0] = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def mib(n: int) -> str:
    return f"{n / (1 << 20):.1f} MiB held"


def test_a_send_onto_a_1_gib_file_answers_142_without_holding_it(queue_client, big_file):
    with traced() as peak:
        body = queue_client.post("/api/cnc/batchSendFile", json={
            "content": "G0 X2\n", "targets": [{"machineID": "big", "fileName": "BIG.nc"}]}).json()
        job = queue_client.post("/api/jobs", json={
            "kind": "send", "content": "G0 X2\n", "skip_identical": True,
            "targets": [{"machineID": "big", "fileName": "BIG.nc"}]}).json()
        done = wait_done(queue_client, job["id"])

    assert body == [{"errorCode": 142, "errorMsg": "Path exists."}]
    assert [t["errorCode"] for t in done["targets"]] == [142]
    assert peak[0] < MEMORY_BOUND_BYTES, mib(peak[0])
    assert big_file.stat().st_size == GIB


def test_a_replace_of_a_file_too_large_to_keep_is_refused_and_leaves_it_there(
        queue_client, big_file):
    with traced() as peak:
        job = queue_client.post("/api/jobs", json={
            "kind": "send", "content": "G0 X2\n", "replace": True,
            "targets": [{"machineID": "big", "fileName": "BIG.nc"}]}).json()
        [target] = wait_done(queue_client, job["id"])["targets"]

    assert target["errorCode"] == 20012
    assert "delete it first" in target["statusMsg"]
    assert peak[0] < MEMORY_BOUND_BYTES, mib(peak[0])
    assert big_file.stat().st_size == GIB


def test_a_1_gib_file_is_backed_up_within_the_memory_bound(queue_client, big_file):
    with traced() as peak:
        backup = run_backup(queue_client, machines={"ids": ["big"]})
        verified = queue_client.post(f"/api/backups/{backup['id']}/verify").json()

    assert peak[0] < MEMORY_BOUND_BYTES, mib(peak[0])
    assert (backup["status"], backup["files"], verified["ok"]) == ("complete", 1, True)
    manifest = queue_client.get(f"/api/backups/{backup['id']}/manifest").json()
    assert [f["size"] for f in manifest["files"]] == [GIB]


def test_a_1_gib_file_is_downloaded_by_backup_files_within_the_memory_bound(
        queue_client, big_file):
    with traced() as peak:
        response = queue_client.post("/api/cnc/backupFiles", json=[{"machineID": "big"}])

    assert peak[0] < MEMORY_BOUND_BYTES + len(response.content), mib(peak[0])
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        [member] = [i for i in archive.infolist() if i.filename.endswith("/BIG.nc")]
    assert member.file_size == GIB


def test_a_1_gib_file_is_restored_within_the_memory_bound(
        queue_client, queue_settings, big_file):
    backup = run_backup(queue_client, machines={"ids": ["big"]})
    restored = on_machine(queue_settings, "spare", "BIG.nc")

    with traced() as peak:
        job = queue_client.post(f"/api/backups/{backup['id']}/restore",
                                json={"machine": "big", "to": "spare"}).json()
        done = wait_done(queue_client, job["id"], timeout_s=300)

    try:
        assert [t["errorCode"] for t in done["targets"]] == [0]
        assert peak[0] < MEMORY_BOUND_BYTES, mib(peak[0])
        assert same_file(restored, big_file)
    finally:
        restored.unlink(missing_ok=True)  # a real 1 GiB on disk, not sparse


def same_file(a: Path, b: Path) -> bool:
    """Whether two files hold the same bytes, read a MiB at a time."""
    with open(a, "rb") as fa, open(b, "rb") as fb:
        while True:
            x, y = fa.read(1 << 20), fb.read(1 << 20)
            if x != y:
                return False
            if not x:
                return True

