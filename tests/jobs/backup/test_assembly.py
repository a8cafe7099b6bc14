"""Stored backups assembled at once, files a backup could not take, names in the ZIP."""

from __future__ import annotations

import dataclasses
import json
import os
import threading
import zipfile
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest
from sqlalchemy import select

from jobs import db, service
from jobs.backup import archive_names, manifests, restore, store
from jobs.backup_models import Backup
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import door, registry
from jobs.models import JobKind, Target, TargetState
from jobs.run import settle
from tests.jobs.backup.zip_checks import unzipped
from tests.jobs.helpers import mock_file, on_machine, run_backup, wait_done

SECOND = "BackupFiles_2026.12.01.10.00.00"


def fetched_job(settings: Any, machine_id: str, **target: Any) -> str:
    """A backup job of one target on `machine_id`, fetched and waiting for its assembly."""
    url = settings.resolved_database_url
    with db.session_scope(url) as session:
        job = service.create(session=session, kind=JobKind.BACKUP,
                             targets=[service.TargetIn(machineID=machine_id, **target)])
        job_id = job.id
        spec = registry.get(session=session, machine_id=machine_id)
    with db.session_scope(url) as session:
        [row] = session.scalars(select(Target).where(Target.job_id == job_id))
        with door.open_files(spec, data_dir=settings.data_dir) as files:
            count = store.fetch_target(settings, files, job_id=job_id, target_id=row.id,
                                       machine_id=machine_id, params=row.params)
        settle.finish_target(row, state=TargetState.SUCCEEDED, error=None,
                             status_msg=f"{count} files")
    return job_id


def test_an_assembly_removes_the_half_written_zip_of_an_assembler_that_was_killed(
        settings, add_machines):
    # A worker killed while it wrote a ZIP leaves its part (hundreds of MB for a large
    # backup); the next assembly on the host removes it, and no live writer's.
    import subprocess

    from worker.transports import parts

    add_machines({"id": "m1", "name": "M1", "model": "Mock"})
    mock_file(settings, "m1", "P1.nc", "G0 X1\n")
    folder = store.backup_dir(settings)
    folder.mkdir(parents=True, exist_ok=True)
    ended = subprocess.Popen(["true"])
    ended.wait()
    dead = folder / f"{store.ASSEMBLING}{parts.WRITER}-{ended.pid}-{SECOND}-j1-b1.zip.part"
    live = folder / parts.part_name(store.ASSEMBLING, f"{SECOND}-j2-b2.zip.part")
    elsewhere = folder / f"{store.ASSEMBLING}otherhost-{ended.pid}-{SECOND}-j3-b3.zip.part"
    for part in (dead, live, elsewhere):
        part.write_bytes(b"PK\x03\x04 half a ZIP")

    assert store.assemble(settings=settings, job_id=fetched_job(settings, "m1")) is not None
    assert not dead.exists() and live.exists() and elsewhere.exists()


def test_thirty_backups_assembled_in_the_same_second_each_keep_their_own_machine(
        settings, add_machines, monkeypatch):
    machines = [f"m{i:02}" for i in range(30)]
    add_machines(*[{"id": m, "name": f"M{m}", "model": "Mock"} for m in machines])
    for m in machines:
        mock_file(settings, m, "P1.nc", f"G0 X1 ; {m}\n" * 2000)
    jobs = [fetched_job(settings, m) for m in machines]
    # Every assembler names its ZIP after the same second, as when they finish together.
    monkeypatch.setattr(archive_names, "backup_name", lambda _when: SECOND)
    start = threading.Barrier(len(jobs))

    def assemble(job_id: str) -> str | None:
        start.wait()
        return store.assemble(settings=settings, job_id=job_id)

    with ThreadPoolExecutor(len(jobs)) as pool:
        assembled = list(pool.map(assemble, jobs))

    assert None not in assembled and len(set(assembled)) == len(jobs)  # a backup each
    with db.session_scope(settings.resolved_database_url) as session:
        backups = [session.get(Backup, a) for a in assembled if a]
        for machine, backup in zip(machines, backups, strict=True):
            assert backup is not None
            assert manifests.verify(settings=settings, backup=backup) == [], backup.name
            with zipfile.ZipFile(store.backup_dir(settings) / backup.name) as archive:
                names = archive.namelist()
                listed = json.loads(archive.read(names[0] + archive_names.MANIFEST_NAME))
            assert names[0] == SECOND + "/"
            assert {n.split("/")[1] for n in names[1:]} == {f"{machine}_M{machine}",
                                                            archive_names.MANIFEST_NAME}
            assert [m["machineID"] for m in listed["machines"]] == [machine]
            assert {f.machine_id for f in backup.files} == {machine}
    assert len({b.name for b in backups if b}) == len(jobs)
    assert not list(store.backup_dir(settings).glob(".*.part"))


def test_an_assembly_another_registers_meanwhile_leaves_the_steps_after_to_that_one(
        settings, add_machines, monkeypatch):
    # Two deliveries of one job's assembly (the reaper asks again while the first writes):
    # one backup, which each answers; the steps after it are taken once, by whichever asks
    # first (jobs.backup.follow_up.after_backup, tests/jobs/test_schedules.py).
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    mock_file(settings, "a1", "P1.nc", "G0 X1\n")
    job_id = fetched_job(settings, "a1")
    record, other = store._record, []

    def the_other_first(*args: Any) -> None:
        monkeypatch.setattr(store, "_record", record)
        other.append(store.assemble(settings=settings, job_id=job_id))
        record(*args)

    monkeypatch.setattr(store, "_record", the_other_first)
    mine = store.assemble(settings=settings, job_id=job_id)
    again = store.assemble(settings=settings, job_id=job_id)  # delivered once more, later

    assert other[0] is not None and mine == other[0] == again
    assert len(list(store.backup_dir(settings).glob("*.zip"))) == 1


def test_an_assembly_delivered_while_another_writes_the_zip_leaves_it_to_that_one(
        settings, add_machines, monkeypatch):
    # Two deliveries that both wrote would need twice the room and the disk's time.
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    mock_file(settings, "a1", "P1.nc", "G0 X1\n")
    job_id = fetched_job(settings, "a1")
    writing, held, pieces, first = threading.Event(), threading.Event(), store.joined, []

    def held_after_a_piece(members: Any, size: int) -> Any:
        for piece in pieces(members, size):
            yield piece
            writing.set()
            held.wait(30)

    monkeypatch.setattr(store, "joined", held_after_a_piece)
    assembly = threading.Thread(target=lambda: first.append(
        store.assemble(settings=settings, job_id=job_id)))
    assembly.start()
    try:
        assert writing.wait(30)
        second = store.assemble(settings=settings, job_id=job_id)
        parts_meanwhile = list(store.backup_dir(settings).glob(".*.part"))
    finally:
        held.set()
        assembly.join(30)

    assert second is None and len(parts_meanwhile) == 1
    assert first[0] is not None
    assert len(list(store.backup_dir(settings).glob("*.zip"))) == 1


def test_an_assembly_cut_off_from_the_database_as_it_registered_leaves_one_zip_once_done_again(
        request, settings, monkeypatch):
    # PostgreSQL restarted (its connection killed) after the ZIP was placed: the next
    # delivery (the reaper's) writes and registers a ZIP of its own, and the first one,
    # registered by none, must not stay beside it for retention never to remove.
    from sqlalchemy import text
    from sqlalchemy.exc import DBAPIError

    url = request.getfixturevalue("postgres_url")
    s = settings.model_copy(update={"database_url": url})
    with db.session_scope(url) as session:
        registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(
            {"id": "cut1", "name": "Mill", "model": "Mock"}), data_dir=s.data_dir)
    mock_file(s, "cut1", "P1.nc", "G0 X1\n")
    job_id = fetched_job(s, "cut1")
    record = store._record

    def cut_off(session: Any, *args: Any) -> None:
        pid = session.scalar(text("SELECT pg_backend_pid()"))
        with db.session_scope(url) as other:
            other.execute(text("SELECT pg_terminate_backend(:pid)"), {"pid": pid})
        record(session, *args)

    monkeypatch.setattr(store, "_record", cut_off)
    with pytest.raises(DBAPIError):
        store.assemble(settings=s, job_id=job_id)
    monkeypatch.setattr(store, "_record", record)
    backup_id = store.assemble(settings=s, job_id=job_id)  # delivered again

    with db.session_scope(url) as session:
        backup = session.get(Backup, backup_id)
        assert backup is not None
        assert manifests.verify(settings=s, backup=backup) == []
        assert [z.name for z in store.backup_dir(s).glob("*.zip")] == [backup.name]


def test_an_assembly_never_replaces_a_zip_already_there(settings, add_machines, monkeypatch):
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    mock_file(settings, "a1", "P1.nc", "G0 X1\n")
    job_id = fetched_job(settings, "a1")
    monkeypatch.setattr(archive_names, "backup_name", lambda _when: SECOND)
    folder = store.backup_dir(settings)
    folder.mkdir(parents=True, exist_ok=True)
    taken = folder / f"{SECOND}-{job_id}.zip"
    taken.write_bytes(b"another assembly's bytes")  # one that was never registered
    record, at_registration = store._record, []

    def registering(*args: Any) -> None:
        at_registration.append(taken.read_bytes())
        record(*args)

    monkeypatch.setattr(store, "_record", registering)
    assembled = store.assemble(settings=settings, job_id=job_id)

    assert assembled is not None
    assert at_registration == [b"another assembly's bytes"]  # placed beside it, not over it
    with db.session_scope(settings.resolved_database_url) as session:
        backup = session.get(Backup, assembled)
        assert backup is not None and backup.name != taken.name
        assert manifests.verify(settings=settings, backup=backup) == []


def test_a_folder_the_backup_cannot_walk_into_is_in_the_manifest_and_makes_it_partial(
        queue_client, add_machines, queue_settings, tmp_path):
    folder = tmp_path / "share"
    (folder / "odd\\name").mkdir(parents=True)  # one folder on the share, a path to a model
    (folder / "odd\\name" / "P2.nc").write_bytes(b"G0 X2\n")
    (folder / "A.nc").write_bytes(b"G0 X1\n")
    with open(os.path.join(os.fsencode(folder), b"bad\xffname.nc"), "wb") as f:
        f.write(b"G0 X3\n")
    add_machines({"id": "s1", "name": "Share", "model": "Shared folder", "transport": "share",
                  "options": {"path": str(folder)}})

    backup = run_backup(queue_client, machines={"all": True})

    assert (backup["status"], backup["files"]) == ("partial", 1)
    [machine] = backup["machines"]
    assert machine["status"] == "partial"
    left_out = {(x["path"], x["isDir"]): x["reason"] for x in machine["leftOut"]}
    assert set(left_out) == {("odd\\name", True), ("bad\\xffname.nc", False)}
    assert all(left_out.values())
    with zipfile.ZipFile(store.backup_dir(queue_settings) / backup["name"]) as archive:
        top = archive.namelist()[0]
        listed = json.loads(archive.read(top + archive_names.MANIFEST_NAME))
    [in_zip] = listed["machines"]
    assert (in_zip["status"], in_zip["leftOut"]) == ("partial", machine["leftOut"])
    assert [f["path"] for f in in_zip["files"]] == ["A.nc"]


def test_letters_outside_ascii_stay_as_they_are_in_the_zip_and_restore_exactly(
        queue_client, add_machines, queue_settings):
    add_machines({"id": "a1", "name": "Drehmaschine Ä", "model": "Mock"},
                 {"id": "b2", "name": "Fräse", "model": "Mock"})
    program = "G0 X1 ; Übergabe\n".encode()
    on_machine(queue_settings, "a1", "Sicherung_Ä/Teil ß_加工.nc").write_bytes(program)

    backup = run_backup(queue_client, machines={"ids": ["a1"]})
    with zipfile.ZipFile(store.backup_dir(queue_settings) / backup["name"]) as archive:
        top = archive.namelist()[0]
        info = archive.getinfo(top + "a1_Drehmaschine Ä/Sicherung_Ä/Teil ß_加工.nc")
        assert archive.read(info) == program
    assert info.flag_bits & 0x0800  # the name is flagged UTF-8
    job = queue_client.post(f"/api/backups/{backup['id']}/restore",
                            json={"machine": "a1", "to": "b2"}).json()
    assert [t["errorCode"] for t in wait_done(queue_client, job["id"])["targets"]] == [0]

    restored = queue_settings.data_dir / "mock" / "b2" / "files"
    assert [p.relative_to(restored).as_posix() for p in restored.rglob("*.nc")] == [
        "Sicherung_Ä/Teil ß_加工.nc"]
    assert (restored / "Sicherung_Ä" / "Teil ß_加工.nc").read_bytes() == program


def test_a_restored_file_whose_bytes_differ_from_the_manifest_is_never_completed(
        settings, add_machines):
    [spec] = add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    mock_file(settings, "a1", "P1.nc", "G0 X1\n" * 100_000)  # a few chunks
    job_id = fetched_job(settings, "a1")
    assembled = store.assemble(settings=settings, job_id=job_id)
    assert assembled is not None
    with db.session_scope(settings.resolved_database_url) as session:
        backup = session.get(Backup, assembled)
        assert backup is not None
        [member] = backup.files
        archive_path = member.archive_path
    zip_path, found = restore.find_member(settings=settings, backup_id=assembled,
                                          archive_path=archive_path)
    wrong = dataclasses.replace(found, sha256="0" * 64)

    with door.open_files(spec, data_dir=settings.data_dir) as files:
        ref = files.ref("P2.nc", None, None)
        with pytest.raises(ContractError) as refused:
            files.send_chunks(ref, restore.read_member(zip_path, wrong))

    assert refused.value.code is ErrorCode.VERIFY_MISMATCH
    assert sorted(p.name for p in (settings.data_dir / "mock" / "a1" / "files").iterdir()) == [
        "P1.nc"]  # neither P2.nc nor a part of it


def test_a_listed_file_whose_name_is_a_path_is_left_out_and_the_rest_is_backed_up(
        queue_client, add_machines, queue_settings, tmp_path):
    from pyftpdlib.filesystems import AbstractedFS

    from tests.worker.transports.ftp_server import ftp_server_of

    class ListingAPath(AbstractedFS):  # an FTP server that lists a file named `x/y.nc`
        def format_mlsx(self, basedir: str, listing: list[str], *args: Any,
                        **kwargs: Any) -> Any:
            yield from super().format_mlsx(basedir, listing, *args, **kwargs)
            if basedir == self.root:
                yield b"type=file;size=6;modify=20261201100000; x/y.nc\r\n"

    with ftp_server_of("plain", tmp_path, abstracted_fs=ListingAPath) as server:
        (server.home / "A.nc").write_bytes(b"G0 X1\n")
        add_machines({"id": "f1", "name": "Mill", "model": "Brother S", "transport": "ftp",
                      "options": server.options})

        backup = run_backup(queue_client, machines={"ids": ["f1"]}, max_attempts=1)

    [machine] = backup["machines"]
    assert (machine["status"], backup["files"]) == ("partial", 1)
    [left_out] = machine["leftOut"]
    assert (left_out["path"], left_out["isDir"]) == ("/x/y.nc", False)
    assert "/" in left_out["reason"]
    manifest = queue_client.get(f"/api/backups/{backup['id']}/manifest").json()
    assert [f["path"] for f in manifest["files"]] == ["/A.nc"]


def test_a_file_another_gateway_lists_as_dot_dot_is_left_out_and_the_rest_is_backed_up(
        queue_client, add_machines, queue_settings):
    from fastapi import FastAPI
    from fastapi.responses import Response

    from tests.live_server import serving

    other = FastAPI()  # another gateway, whose listing names a file `..`

    @other.get("/api/cnc/readProgramList")
    def listing() -> dict[str, Any]:
        return {"errorCode": 0, "dirAtCNC": "", "programs": ["..", "A.nc"], "subDirs": []}

    @other.get("/api/cnc/receiveFileStream")
    def read(fileName: str) -> Response:  # noqa: N803 (the contract's name)
        if fileName != "A.nc":
            return Response('{"errorCode": 158}', 200, media_type="application/json")
        return Response(b"G0 X1\n", media_type="application/octet-stream")

    with serving(other) as live:
        add_machines({"id": "g1", "name": "Far", "model": "Mock", "transport": "gateway",
                      "options": {"url": live.url, "machine_id": "x"}})
        backup = run_backup(queue_client, machines={"ids": ["g1"]}, max_attempts=1)

    [machine] = backup["machines"]
    assert (machine["status"], backup["files"]) == ("partial", 1)
    assert [(x["path"], x["isDir"]) for x in machine["leftOut"]] == [("/..", False)]


def test_a_machine_whose_folder_would_be_too_long_a_name_is_cut_short_and_unzips(
        queue_client, add_machines, queue_settings, tmp_path):
    # 200 letters of two bytes each: `a1_` and 400 bytes, past the 255 of a name on disk
    add_machines({"id": "a1", "name": "Ä" * 200, "model": "Mock"},
                 {"id": "a2", "name": "Ä" * 200, "model": "Mock"})
    on_machine(queue_settings, "a1", "P1.nc").write_bytes(b"G0 X1\n")
    on_machine(queue_settings, "a2", "P1.nc").write_bytes(b"G0 X2\n")
    on_machine(queue_settings, "a1", ":" * 100 + ".nc").write_bytes(b"G0 X3\n")  # %3A each

    backup = run_backup(queue_client, machines={"ids": ["a1", "a2"]})

    files = unzipped(store.backup_dir(queue_settings) / backup["name"], tmp_path / "out")
    programs = {path.split("/", 1)[1]: data for path, data in files.items()
                if not path.endswith(archive_names.MANIFEST_NAME)}
    assert sorted(programs.values()) == [b"G0 X1\n", b"G0 X2\n", b"G0 X3\n"]
    for path in programs:
        assert all(len(part.encode()) <= 255 for part in path.split("/")), path
    folder_of = {data: path.split("/")[0] for path, data in programs.items()}
    assert folder_of[b"G0 X1\n"].startswith("a1_ÄÄ") and folder_of[b"G0 X2\n"].startswith("a2_")
    manifest = queue_client.get(f"/api/backups/{backup['id']}/manifest").json()
    assert sorted(f["path"] for f in manifest["files"]) == ["/" + ":" * 100 + ".nc", "/P1.nc",
                                                            "/P1.nc"]
    assert queue_client.post(f"/api/backups/{backup['id']}/verify").json()["ok"]


def test_a_file_with_a_backslash_in_its_name_is_restored_under_its_own_name(
        queue_client, add_machines, queue_settings):
    # On a machine whose folders are split by `/` (a Unix FTP server), `\` is a letter.
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    on_machine(queue_settings, "a1", "sub/a\\b.nc").write_bytes(b"G0 X1\n")
    backup = run_backup(queue_client, machines={"ids": ["a1"]})
    on_machine(queue_settings, "a1", "sub/a\\b.nc").unlink()

    job = queue_client.post(f"/api/backups/{backup['id']}/restore",
                            json={"machine": "a1"}).json()

    assert [t["errorCode"] for t in wait_done(queue_client, job["id"])["targets"]] == [0]
    restored = queue_settings.data_dir / "mock" / "a1" / "files"
    assert [p.relative_to(restored).as_posix() for p in restored.rglob("*")
            if p.is_file()] == ["sub/a\\b.nc"]
    assert on_machine(queue_settings, "a1", "sub/a\\b.nc").read_bytes() == b"G0 X1\n"


def test_a_restore_of_a_folder_leaves_out_a_file_whose_name_only_begins_with_it_and_a_backslash(
        queue_client, add_machines, queue_settings):
    # `/sub/a\b.nc` on a machine of `/` folders is the file `a\b.nc` of /sub, not of /sub/a.
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    on_machine(queue_settings, "a1", "sub/a/P1.nc").write_bytes(b"G0 X1\n")
    on_machine(queue_settings, "a1", "sub/a\\b.nc").write_bytes(b"G0 X2\n")
    backup = run_backup(queue_client, machines={"ids": ["a1"]})

    job = queue_client.post(f"/api/backups/{backup['id']}/restore",
                            json={"machine": "a1", "path": "/sub/a"}).json()

    assert [t["fileName"] for t in wait_done(queue_client, job["id"])["targets"]] == ["P1.nc"]


def test_a_machine_failure_no_transport_mapped_is_not_blamed_on_the_backups_folder(
        settings, add_machines, monkeypatch):
    # A transport maps its machine's failures to the contract's codes; one it missed (a
    # dropped connection, raised here as the transport would) was reported as "backups
    # folder …: Connection reset by peer", sending the administrator to a sound disk.
    # It is the machine's connection failing: 20006, tried again.
    from jobs.fleet.rules import MachineFiles

    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    mock_file(settings, "a1", "P1.nc", "G0 X1\n")

    def dropped(*_: Any, **__: Any) -> Any:
        raise ConnectionResetError(104, "Connection reset by peer")

    monkeypatch.setattr(MachineFiles, "open", dropped)

    with pytest.raises(ContractError) as failed:
        fetched_job(settings, "a1")
    # the machine's connection, tried again, in its own words
    assert (failed.value.code, failed.value.status_msg, failed.value.transient) == (
        ErrorCode.CONNECTION_FAILED, "Connection reset by peer", True)
    assert not list(store.backup_dir(settings).rglob("*.spool"))  # no half work file
