"""Backups whose folder is full or read-only: a real tmpfs of a few hundred KB mounted on
the backups folder (root only; skipped where nothing can be mounted, a failure in CI)."""

from __future__ import annotations

import contextlib
import os
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select

from jobs import db, schedules
from jobs.backup import store
from jobs.backup_models import Backup
from jobs.folders import backup_dir, job_folder
from jobs.models import Job, Target, TargetState
from jobs.run import queue, reaper
from tests.jobs.cli.runner import dncq
from tests.jobs.helpers import mock_file, wait_done, wait_until
from tests.servers import unavailable

FULL = "No space left on device"


@pytest.fixture
def backups_on_tmpfs(settings: Any) -> Iterator[Callable[..., Path]]:
    """Factory: the backups folder on a tmpfs of its own, `size_kb` big, read-only if
    asked; unmounted after the test."""
    mounted: list[Path] = []

    def mount(*, size_kb: int = 0, read_only: bool = False) -> Path:
        folder = backup_dir(settings)
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        options = f"size={size_kb}k,mode=0700" + (",ro" if read_only else "")
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)],
                              capture_output=True, text=True)
        if done.returncode != 0:
            unavailable(f"no tmpfs can be mounted here: {done.stderr.strip()}")
        mounted.append(folder)
        return folder

    yield mount
    for folder in mounted:
        subprocess.run(["umount", "--lazy", str(folder)], check=True)


def a_machine_with(add_machines: Any, settings: Any, size_bytes: int) -> None:
    """Machine a1 with one program of `size_bytes` that deflates to about half of it."""
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    mock_file(settings, "a1", "BIG.nc", os.urandom(size_bytes // 2).hex())


def files_in(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def job_of(client: Any, job_id: str) -> dict[str, Any]:
    return client.get(f"/api/jobs/{job_id}").json()


@dataclass
class ReaperPass:
    """One look of the reaper at the backup jobs that ended without their ZIP."""

    began: float  # monotonic
    now: datetime  # the pass's clock, which it compares the jobs' ends with
    asked: int  # how many assemblies it queued


def reaper_passes(monkeypatch: pytest.MonkeyPatch) -> list[ReaperPass]:
    """The reaper's looks at backup jobs from now on, each once it is over."""
    passes: list[ReaperPass] = []
    asked: list[str] = []
    enqueue, look = queue.enqueue_assembly, reaper._assemble_forgotten_backups

    def asking(settings: Any, job_id: str) -> None:
        asked.append(job_id)
        enqueue(settings, job_id)

    def recorded(settings: Any, now: datetime) -> None:
        began, before = time.monotonic(), len(asked)
        look(settings, now)
        passes.append(ReaperPass(began, now, len(asked) - before))

    monkeypatch.setattr(queue, "enqueue_assembly", asking)
    monkeypatch.setattr(reaper, "_assemble_forgotten_backups", recorded)
    return passes


def test_a_machine_whose_files_do_not_fit_fails_naming_the_folder_and_leaves_no_work_file(
        queue_client, add_machines, queue_settings, backups_on_tmpfs):
    folder = backups_on_tmpfs(size_kb=256)
    a_machine_with(add_machines, queue_settings, 1024 * 1024)

    job = queue_client.post("/api/jobs", json={"kind": "backup", "machines": {"ids": ["a1"]}})
    done = wait_done(queue_client, job.json()["id"])
    wait_until(lambda: queue_client.get("/api/backups").json() != [])

    [target] = job_of(queue_client, done["id"])["targets"]
    assert (target["state"], target["errorCode"]) == ("failed", 20017)
    assert target["statusMsg"] == f"backups folder {folder}: {FULL}"
    [backup] = queue_client.get("/api/backups").json()  # the failed one, which says so
    assert files_in(folder) == [backup["name"]]


def test_a_zip_that_does_not_fit_fails_the_job_and_is_not_assembled_again(
        queue_client, add_machines, queue_settings, backups_on_tmpfs):
    # The machine's work file fits, the ZIP that copies it beside it does not.
    folder = backups_on_tmpfs(size_kb=1024)
    a_machine_with(add_machines, queue_settings, 1200 * 1024)

    job_id = queue_client.post("/api/jobs", json={
        "kind": "backup", "machines": {"ids": ["a1"]}}).json()["id"]
    wait_until(lambda: job_of(queue_client, job_id)["state"] == "failed")

    [target] = job_of(queue_client, job_id)["targets"]
    assert (target["errorCode"], target["statusMsg"]) == (20017, f"backups folder {folder}: {FULL}")
    assert files_in(folder) == []  # no half ZIP, and no work folder for the reaper to assemble
    assert not job_folder(queue_settings, job_id).exists()
    assert queue_client.get("/api/backups").json() == []


def test_a_scheduled_backup_whose_zip_does_not_fit_sends_its_alert(
        queue_client, add_machines, queue_settings, backups_on_tmpfs, webhook_server):
    alerts = webhook_server()
    folder = backups_on_tmpfs(size_kb=1024)
    a_machine_with(add_machines, queue_settings, 1200 * 1024)
    with db.session_scope(queue_settings.resolved_database_url) as session:
        schedules.upsert(
            session=session, data_dir=queue_settings.data_dir, schedule_in=schedules.ScheduleIn(
                name="nightly", cron="0 2 * * *", notify=[alerts.url()]))

    job_id = schedules.run_now(settings=queue_settings, name="nightly")
    wait_until(lambda: bool(alerts.requests))

    alert = alerts.requests[0].json()
    assert alert["title"] == "dncq: backup nightly is failed"
    assert f"backups folder {folder}: {FULL}" in alert["body"] and job_id in alert["body"]
    with db.session_scope(queue_settings.resolved_database_url) as session:
        assert session.scalar(select(Backup.id)) is None


def test_a_backup_into_a_read_only_folder_answers_its_job_which_fails_saying_why(
        queue_client, add_machines, queue_settings, backups_on_tmpfs):
    folder = backups_on_tmpfs(read_only=True)
    a_machine_with(add_machines, queue_settings, 1024)

    answer = queue_client.post("/api/jobs", json={"kind": "backup", "machines": {"ids": ["a1"]}})

    assert answer.status_code == 202
    done = wait_done(queue_client, answer.json()["id"])
    [target] = job_of(queue_client, done["id"])["targets"]
    assert (done["state"], target["errorCode"]) == ("failed", 20017)
    assert target["statusMsg"] == f"backups folder {folder}: Read-only file system"


def test_a_disk_remounted_read_only_before_the_zip_fails_the_backup_once(
        queue_client, add_machines, queue_settings, backups_on_tmpfs, webhook_server,
        monkeypatch):
    # ext4's errors=remount-ro after the machines were fetched: the job's work folder cannot
    # be removed, and the reaper, which assembles a finished job's work folder, took it for a
    # ZIP still owed: one assembly and one alert every five minutes, for a day.
    alerts = webhook_server()
    folder = backups_on_tmpfs(size_kb=4096)
    a_machine_with(add_machines, queue_settings, 1024)
    remounted: list[bool] = []
    remounting = threading.Lock()  # a second assembly beside the first waits for it
    assemble = store.assemble

    def remounted_first(**kwargs: Any) -> Any:
        with remounting:
            if not remounted:
                subprocess.run(["mount", "-o", "remount,ro", str(folder)], check=True)
                remounted.append(True)
        return assemble(**kwargs)

    monkeypatch.setattr(store, "assemble", remounted_first)
    passes = reaper_passes(monkeypatch)
    with db.session_scope(queue_settings.resolved_database_url) as session:
        schedules.upsert(
            session=session, data_dir=queue_settings.data_dir, schedule_in=schedules.ScheduleIn(
                name="nightly", cron="0 2 * * *", notify=[alerts.url()]))

    job_id = schedules.run_now(settings=queue_settings, name="nightly")
    wait_until(lambda: bool(alerts.requests))
    failed = time.monotonic()  # the failure is recorded before its alert goes
    with db.session_scope(queue_settings.resolved_database_url) as session:
        finished_at = session.scalars(select(Job.finished_at).where(Job.id == job_id)).one()

    forgotten = finished_at + timedelta(seconds=reaper.FORGOTTEN_AFTER_S)

    def passes_since() -> list[ReaperPass]:  # those that take the job for a forgotten one
        return [p for p in passes if p.began > failed and p.now > forgotten]

    # Waited for, not slept on: the reaper (every 0.2 s here) asks a forgotten job's
    # assembly at its first look. An ask from before the failure was recorded is no fault
    # (a first assembly kept from running for 2 s on a busy host meets one): only later ones.
    wait_until(lambda: len(passes_since()) >= 3)
    assert [p.asked for p in passes_since()[:3]] == [0, 0, 0]
    assert len(alerts.requests) == 1
    assert f"backups folder {folder}: Read-only file system" in alerts.requests[0].json()["body"]
    assert job_of(queue_client, job_id)["state"] == "failed"
    asked = time.monotonic()  # a client waiting for the ZIP (dncq backup run) hears none comes
    assert queue_client.get("/api/backups", params={"job": job_id, "wait_s": 20}).json() == []
    assert time.monotonic() - asked < 10


@pytest.mark.parametrize(("host", "age_s", "left_to_it"), [
    ("here", 0, True), ("elsewhere", 0, True),  # a writer at work: this host's pid 1, another's
    ("here", 3600, False), ("elsewhere", 3600, False)])  # a part untouched for an hour: none
def test_an_assembly_with_no_room_beside_another_writing_the_zip_leaves_the_job_to_it(
        settings, add_machines, backups_on_tmpfs, host: str, age_s: int, left_to_it: bool):
    # The reaper asks a second assembly of a job whose first one still writes: on a disk
    # with room for one ZIP, the second failed the job and removed the work files the first
    # was reading, and a backup that fitted alone was lost. A part an assembler killed on
    # another host left behind (nothing removes it from here) must not stop the job for ever.
    from jobs.errors import ContractError
    from tests.jobs.backup.test_assembly import fetched_job
    from worker.transports import parts

    folder = backups_on_tmpfs(size_kb=1024)
    a_machine_with(add_machines, settings, 1200 * 1024)
    job_id = fetched_job(settings, "a1")
    writer = parts.WRITER if host == "here" else "another_host"
    writing = folder / f"{store.ASSEMBLING}{writer}-1-B-{job_id}-b1.zip.part"  # pid 1
    writing.write_bytes(b"PK\x03\x04")
    os.utime(writing, (time.time() - age_s,) * 2)

    if left_to_it:
        assert store.assemble(settings=settings, job_id=job_id) is None
    else:
        with pytest.raises(ContractError, match=FULL):
            store.assemble(settings=settings, job_id=job_id)

    assert job_folder(settings, job_id).is_dir() is left_to_it  # the first one's to read
    with db.session_scope(settings.resolved_database_url) as session:
        assert session.scalars(select(Target.state)).all() == [
            TargetState.SUCCEEDED if left_to_it else TargetState.FAILED]


@pytest.mark.parametrize(("folder", "machine_kb", "why"), [
    ({"read_only": True}, 1, "Read-only file system"),  # the machine's files: nowhere to go
    ({"size_kb": 1024}, 1200, FULL)])  # the machine's files fit, the ZIP beside them does not
def test_backup_run_that_stores_no_zip_says_at_once_that_none_was_stored_and_why(
        live_with_worker, add_machines, queue_settings, backups_on_tmpfs,
        folder: dict[str, Any], machine_kb: int, why: str):
    mounted = backups_on_tmpfs(**folder)
    a_machine_with(add_machines, queue_settings, machine_kb * 1024)

    run = dncq("backup", "run", "--to", "a1")

    assert run.exit_code == 1, run.output
    assert f"No backup was stored: backups folder {mounted}: {why}" in run.output
    assert "not registered yet" not in run.output


def test_an_assembly_with_no_room_beside_another_of_this_process_leaves_the_job_to_it(
        settings, add_machines, backups_on_tmpfs, monkeypatch):
    # Two deliveries of one assembly in one worker (its threads or greenlets share a pid):
    # the one that found no room must not take the work files from under the other.
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from jobs.errors import ContractError
    from tests.jobs.backup.test_assembly import fetched_job

    backups_on_tmpfs(size_kb=1024)
    a_machine_with(add_machines, settings, 1200 * 1024)
    job_id = fetched_job(settings, "a1")
    writing, go_on = threading.Event(), threading.Event()
    write_zip = store.write_zip

    def first_held(members: Any) -> Any:
        if not writing.is_set():  # the first assembly, held at its first byte
            writing.set()
            go_on.wait(30)
        yield from write_zip(members)

    monkeypatch.setattr(store, "write_zip", first_held)
    with ThreadPoolExecutor(1) as pool:
        first = pool.submit(store.assemble, settings=settings, job_id=job_id)
        assert writing.wait(30)
        second = store.assemble(settings=settings, job_id=job_id)
        left = job_folder(settings, job_id).is_dir()
        go_on.set()
        with pytest.raises(ContractError, match=FULL):  # the first says why, once
            first.result(30)

    assert second is None and left


def test_two_assemblies_that_fail_at_once_record_the_failure_once(
        settings, add_machines, backups_on_tmpfs, monkeypatch):
    # Two deliveries of one assembly (the reaper's ask beside the runner's) on a disk
    # remounted read-only: both read the job before either recorded its failure, and on
    # SQLite, where FOR UPDATE takes no lock, both recorded it, and both alerted.
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from sqlalchemy import event

    from jobs.errors import ContractError
    from tests.jobs.backup.test_assembly import fetched_job

    folder = backups_on_tmpfs(size_kb=4096)
    a_machine_with(add_machines, settings, 1024)
    job_id = fetched_job(settings, "a1")
    subprocess.run(["mount", "-o", "remount,ro", str(folder)], check=True)
    recording, both_read = threading.local(), threading.Barrier(2, timeout=2)
    unstored = store._unstored

    def each_recording(*args: Any) -> Any:
        recording.on = True
        return unstored(*args)

    def read_the_job(_conn: Any, _cursor: Any, statement: str, *_: Any) -> None:
        # Each holds on once it has read the job, until the other has too (the fault) or
        # 2 s passed: the other waits for the first's recording to read it.
        if getattr(recording, "on", False) and statement.startswith("SELECT jobs."):
            recording.on = False
            with contextlib.suppress(threading.BrokenBarrierError):
                both_read.wait()

    monkeypatch.setattr(store, "_unstored", each_recording)
    engine = db.engine_for(settings.resolved_database_url)
    event.listen(engine, "after_cursor_execute", read_the_job)
    try:
        with ThreadPoolExecutor(2) as pool:
            assemblies = [pool.submit(store.assemble, settings=settings, job_id=job_id)
                          for _ in range(2)]
            said = []
            for assembly in assemblies:
                try:
                    said.append(assembly.result(60))
                except ContractError as exc:
                    said.append(exc.status_msg)
    finally:
        event.remove(engine, "after_cursor_execute", read_the_job)

    assert sorted(said, key=str) == sorted(  # one says why, the other that it was said
        [f"backups folder {folder}: Read-only file system", None], key=str)
