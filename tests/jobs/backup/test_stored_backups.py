"""Backup jobs on the queue: stored ZIPs, best effort, verify, diff, restore."""

from __future__ import annotations

import hashlib
import io
import json
import os
import time
import tracemalloc
import zipfile
import zlib
from typing import Any

import pytest

from jobs import db
from jobs.backup import manifests, store, streamed
from jobs.backup_models import Backup, BackupStatus
from jobs.errors import MESSAGES, ErrorCode
from jobs.fleet import door, registry
from jobs.models import Job, JobKind, JobState, Target, TargetState
from tests.jobs.helpers import mock_file, on_machine, run_backup, wait_done


def fleet(add_machines: Any, settings: Any) -> None:
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock", "tags": ["night"]},
                 {"id": "b2", "name": "Mill", "model": "Mock", "tags": ["night"]})
    mock_file(settings, "a1", "P1.nc", "G0 X1\n")
    mock_file(settings, "a1", "sub/P2.nc", "G0 X2\n")
    mock_file(settings, "b2", "Q1.nc", "G0 Y1\n")


def test_a_backup_job_stores_one_zip_with_every_machine_and_a_manifest(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    backup = run_backup(queue_client, machines={"tags": ["night"]})
    assert backup["status"] == "complete" and backup["files"] == 3
    path = store.backup_dir(queue_settings) / backup["name"]
    with zipfile.ZipFile(path) as archive:
        top = archive.namelist()[0]
        names = sorted(n.removeprefix(top) for n in archive.namelist()[1:])
        manifest = json.loads(archive.read(top + "_manifest.json"))
    assert names == ["_manifest.json", "a1_Lathe/", "a1_Lathe/P1.nc", "a1_Lathe/sub/P2.nc",
                     "b2_Mill/", "b2_Mill/Q1.nc"]
    assert [m["status"] for m in manifest["machines"]] == ["ok", "ok"]
    assert not list(store.backup_dir(queue_settings).glob(".*.part"))
    download = queue_client.get(f"/api/backups/{backup['id']}")
    assert download.content == path.read_bytes()


def test_two_machines_whose_id_and_name_join_alike_keep_folders_and_files_of_their_own(
        queue_client, add_machines, queue_settings):
    # `5_1` named `X` and `5` named `1_X` are both `5_1_X`: one folder held both machines'
    # PROG.NC, the backup failed its own verify, and neither could be restored.
    add_machines({"id": "5_1", "name": "X", "model": "Mock"},
                 {"id": "5", "name": "1_X", "model": "Mock"})
    mock_file(queue_settings, "5_1", "PROG.NC", "G0 X51\n")
    mock_file(queue_settings, "5", "PROG.NC", "G0 X5\n")

    backup = run_backup(queue_client, machines={"ids": ["5_1", "5"]})

    path = store.backup_dir(queue_settings) / backup["name"]
    with zipfile.ZipFile(path) as archive:
        top = archive.namelist()[0]
        files = {n.removeprefix(top): archive.read(n) for n in archive.namelist()
                 if n.endswith("PROG.NC")}
    assert files == {"5_1_X/PROG.NC": b"G0 X51\n", "5_1_X~2/PROG.NC": b"G0 X5\n"}
    assert queue_client.post(f"/api/backups/{backup['id']}/verify").json()["ok"]


def test_the_listing_gives_each_backup_its_file_count_and_finds_one_by_its_job(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    everything = run_backup(queue_client, machines={"tags": ["night"]})
    one_machine = run_backup(queue_client, machines={"ids": ["b2"]})
    listed = queue_client.get("/api/backups").json()
    assert [(b["id"], b["files"]) for b in listed] == [(one_machine["id"], 1),
                                                      (everything["id"], 3)]  # newest first
    assert [m["machineID"] for m in listed[1]["machines"]] == ["a1", "b2"]
    mine = queue_client.get("/api/backups", params={"job": everything["job"]}).json()
    assert mine == [everything]
    assert queue_client.get("/api/backups", params={"job": "no-such-job"}).json() == []
    job = queue_client.get(f"/api/jobs/{everything['job']}").json()
    assert job["backupId"] == everything["id"]  # the job names its ZIP once registered


def test_every_file_of_a_backup_is_recorded_a_file_without_a_date_too(database_url):
    machines = [{"machineID": m, "machineName": m.upper(), "status": "ok", "errorCode": 0,
                 "errorMsg": None, "files": [
                     {"machine_path": f"//CNC_MEM/USER/P{i}.nc", "archivePath": f"T/{m}/P{i}.nc",
                      "size": 5 * 1024 ** 3 + i, "mtime": None if i == 0 else 1.5e9 + i,
                      "sha256": f"{i:064x}"} for i in range(3)]} for m in ("m1", "m2")]
    with db.session_scope(database_url) as session:
        store._record(session, "b1", None, "T.zip", BackupStatus.COMPLETE, 10, "0" * 64,
                             machines)
    with db.session_scope(database_url) as session:
        backup = manifests.get(session=session, backup_id="b1")
        recorded = manifests.manifest(session=session, backup=backup)
    assert recorded["files"] == [
        {"machineID": m["machineID"], "path": f["machine_path"], "archivePath": f["archivePath"],
         "size": f["size"], "mtime": f["mtime"], "sha256": f["sha256"]}
        for m in machines for f in m["files"]]
    assert [m["machineID"] for m in recorded["machines"]] == ["m1", "m2"]


def test_a_machine_offline_is_recorded_and_the_others_are_backed_up(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    add_machines({"id": "c3", "name": "Off", "model": "Mock", "tags": ["night"],
                  "options": {"offline": True}})
    backup = run_backup(queue_client, machines={"tags": ["night"]}, max_attempts=1)
    assert backup["status"] == "partial"
    states = {m["machineID"]: (m["status"], m["errorCode"]) for m in backup["machines"]}
    assert states == {"a1": ("ok", 0), "b2": ("ok", 0), "c3": ("failed", 20004)}
    manifest = queue_client.get(f"/api/backups/{backup['id']}/manifest").json()
    assert {f["machineID"] for f in manifest["files"]} == {"a1", "b2"}
    said = {m["machineID"]: m["statusMsg"] for m in manifest["machines"]}
    assert said == {"a1": None, "b2": None, "c3": "machine is offline (simulated)"}


def test_verify_passes_a_sound_backup_and_catches_a_corrupted_one(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    backup = run_backup(queue_client, machines={"all": True})
    assert queue_client.post(f"/api/backups/{backup['id']}/verify").json()["ok"]
    path = store.backup_dir(queue_settings) / backup["name"]
    raw = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo(next(n for n in archive.namelist() if n.endswith("Q1.nc")))
    spot = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra) + 1
    raw[spot] ^= 0xFF  # one flipped byte inside the member's data
    path.write_bytes(bytes(raw))
    found = queue_client.post(f"/api/backups/{backup['id']}/verify").json()
    assert not found["ok"] and found["problems"]


def test_diff_lists_what_changed_on_one_machine(queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    first = run_backup(queue_client, machines={"all": True})
    mock_file(queue_settings, "a1", "P1.nc", "G0 X100\n")  # changed
    mock_file(queue_settings, "a1", "P3.nc", "G0 X3\n")  # added
    (queue_settings.data_dir / "mock" / "a1" / "files" / "sub" / "P2.nc").unlink()  # removed
    second = run_backup(queue_client, machines={"all": True})
    changes = queue_client.get(f"/api/backups/{first['id']}/diff/{second['id']}").json()
    assert changes["a1"] == {"added": ["/P3.nc"], "removed": ["/sub/P2.nc"],
                             "changed": ["/P1.nc"], "incomplete": {}}
    assert changes["b2"] == {"added": [], "removed": [], "changed": [], "incomplete": {}}


def test_restore_of_a_folder_to_another_machine_recreates_it_there(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    backup = run_backup(queue_client, machines={"all": True})
    job = queue_client.post(f"/api/backups/{backup['id']}/restore",
                            json={"machine": "a1", "path": "/sub", "to": "b2"}).json()
    done = wait_done(queue_client, job["id"])
    assert [t["errorCode"] for t in done["targets"]] == [0]
    restored = queue_settings.data_dir / "mock" / "b2" / "files" / "sub" / "P2.nc"
    assert restored.read_text() == "G0 X2\n"


def test_a_restore_over_a_changed_file_says_it_put_the_backups_back_and_kept_the_one_there(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    backup = run_backup(queue_client, machines={"ids": ["a1"]})
    mock_file(queue_settings, "a1", "P1.nc", "G0 X100\n")  # changed since

    job = queue_client.post(f"/api/backups/{backup['id']}/restore",
                            json={"machine": "a1", "path": "P1.nc", "replace": True}).json()

    [target] = wait_done(queue_client, job["id"])["targets"]
    assert (target["errorCode"], target["statusMsg"]) == (
        0, "put back in place of the file there, which is kept with the job")
    assert on_machine(queue_settings, "a1", "P1.nc").read_text() == "G0 X1\n"


def test_a_restore_onto_a_machine_nobody_registered_is_refused_whole(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    backup = run_backup(queue_client, machines={"ids": ["a1"]})

    refused = queue_client.post(f"/api/backups/{backup['id']}/restore",
                                json={"machine": "a1", "to": "nobody"})

    assert (refused.status_code, refused.json()["errorCode"]) == (422, 10003)
    assert "nobody" in refused.json()["statusMsg"]
    assert queue_client.get("/api/jobs", params={"kind": "restore"}).json() == []


def test_a_restore_job_is_of_kind_restore_and_found_by_that_kind(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    backup = run_backup(queue_client, machines={"ids": ["a1"]})
    job = queue_client.post(f"/api/backups/{backup['id']}/restore",
                            json={"machine": "a1", "to": "b2"}).json()
    wait_done(queue_client, job["id"])

    restores = queue_client.get("/api/jobs", params={"kind": "restore"}).json()
    sends = queue_client.get("/api/jobs", params={"kind": "send"}).json()

    assert job["kind"] == "restore"
    assert [j["id"] for j in restores] == [job["id"]]
    assert sends == []


def test_a_restore_job_is_kept_and_found_by_its_kind_on_each_database(database_url):
    # The kind column is a plain string on both: a new kind needs no migration.
    from jobs import service
    from jobs.models import JobKind

    with db.session_scope(database_url) as session:
        job_id = service.create(session=session, kind=JobKind.RESTORE, targets=[]).id
    with db.session_scope(database_url) as session:
        found = service.list_jobs(session=session, kind=JobKind.RESTORE)

        assert [(j.id, j.kind) for j in found] == [(job_id, JobKind.RESTORE)]


def test_a_job_request_of_kind_restore_is_refused_naming_where_restores_start(queue_client):
    response = queue_client.post("/api/jobs", json={"kind": "restore",
                                                    "machines": {"all": True}})

    assert response.status_code == 422
    assert "/api/backups/{id}/restore" in response.text


@pytest.mark.parametrize("dry_run", [False, True])
def test_a_job_request_of_kind_request_is_refused_saying_where_requests_come_from(
        queue_client, dry_run):
    response = queue_client.post("/api/jobs", json={"kind": "request", "dry_run": dry_run,
                                                    "machines": {"all": True}})

    assert response.status_code == 422
    assert "operator" in response.json()["statusMsg"]
    assert queue_client.get("/api/jobs", params={"kind": "request"}).json() == []


def test_a_restore_reads_the_backup_one_file_at_a_time(
        queue_client, add_machines, queue_settings):
    add_machines({"id": "big", "name": "Big", "model": "Mock"},
                 {"id": "spare", "name": "Spare", "model": "Mock"})
    files = {f"P{i}.nc": os.urandom(1 << 20) for i in range(12)}  # 12 MiB, incompressible
    for name, data in files.items():
        target = queue_settings.data_dir / "mock" / "big" / "files" / name
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
    backup = run_backup(queue_client, machines={"ids": ["big"]})

    tracemalloc.start()
    try:
        job = queue_client.post(f"/api/backups/{backup['id']}/restore",
                                json={"machine": "big", "to": "spare"}).json()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()

    assert peak < 6 * (1 << 20), f"{peak / (1 << 20):.1f} MiB held while queueing the restore"
    done = wait_done(queue_client, job["id"])
    assert [t["errorCode"] for t in done["targets"]] == [0] * len(files)
    spare = queue_settings.data_dir / "mock" / "spare" / "files"
    assert {name: (spare / name).read_bytes() for name in files} == files


@pytest.mark.parametrize("chunks", [[], [b""], [b"G0 X1\n" * 700],
                                    [b"G0 X1\n" * 50_000, b"G1 Y2\n" * 50_000, b"M30\n"]])
def test_a_fetched_file_is_deflated_into_a_member_zip_can_read(chunks):
    data = b"".join(chunks)
    out = io.BytesIO()
    size, sha256, crc, packed = streamed._deflate(iter(chunks), out, 6)
    assert (size, packed) == (len(data), len(out.getvalue()))
    assert (sha256, crc) == (hashlib.sha256(data).hexdigest(), zlib.crc32(data))
    assert zlib.decompress(out.getvalue(), -zlib.MAX_WBITS) == data


@pytest.mark.parametrize("level", [0, 1, 3, 6, 9])  # stored, ISA-L's levels, zlib-ng's
def test_a_fetched_folder_is_deflated_into_members_zip_can_read(add_machines, settings, tmp_path,
                                                                 level):
    # What the assembler copies without looking: the members one after another, each
    # with its own offset, sizes, CRC and hash.
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    programs = {"EMPTY.nc": b"", "SHORT.nc": b"G0 X1\n" * 700, "M30.nc": b"M30\n",
                "sub/LONG.nc": (b"G1 X1.25 Y-3.5 F200\n" * 40_000)}  # 3 chunks of 256 KiB
    # More files than deflate while the next is read, a large one among them.
    programs.update({f"P{i:02}.nc": f"G1 X{i} Y{i * 7}\n".encode() * (300 + 97 * i)
                     for i in range(12)})
    programs["P05_LARGE.nc"] = b"G2 X5 Y5 I1 J0\n" * 50_000
    for name, data in programs.items():
        on_machine(settings, "a1", name).write_bytes(data)
    with db.session_scope(settings.resolved_database_url) as session:
        spec = registry.get(session=session, machine_id="a1")
    fetched: dict[str, streamed.Fetched] = {}
    with door.open_files(spec, data_dir=settings.data_dir) as files:
        for target in [streamed.BackupTarget(machineID="a1", fileName="SHORT.nc"),
                       streamed.BackupTarget(machineID="a1")]:  # SHORT.nc twice: zipped once
            streamed.fetch(files, streamed.check_one(files, target),
                           tmp_path / streamed.MEMBERS, fetched, level=level)

    assert sorted(fetched) == sorted(programs)
    spool = (tmp_path / streamed.MEMBERS).read_bytes()
    records = sorted(fetched.values(), key=lambda f: f.offset)
    end = 0
    for f in records:  # one after another, from the spool file's start to its end
        assert f.offset == end, f.archive_path
        end += f.compressed_size or 0
    assert end == len(spool)
    for f in records:
        data = programs[f.archive_path]
        raw = spool[f.offset:f.offset + (f.compressed_size or 0)]
        assert zlib.decompress(raw, -zlib.MAX_WBITS) == data, f.archive_path
        assert (f.size, f.crc32, f.sha256) == (len(data), zlib.crc32(data),
                                               hashlib.sha256(data).hexdigest())


def test_a_backup_that_retention_deleted_is_not_assembled_again(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    backup = run_backup(queue_client, machines={"tags": ["night"]})
    with db.session_scope(queue_settings.resolved_database_url) as session:  # as prune does
        session.delete(session.get(Backup, backup["id"]))
    (store.backup_dir(queue_settings) / backup["name"]).unlink()

    # The worker's reaper runs every 0.2 s here and looks at jobs finished over 2 s ago.
    time.sleep(4)

    assert [b for b in queue_client.get("/api/backups").json() if b["job"] == backup["job"]] == []
    assert not list(store.backup_dir(queue_settings).glob(".*.part"))


def damage(path: Any, member_suffix: str) -> None:
    """Overwrite the start of a member's deflated data with bytes no inflater takes."""
    raw = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo(next(n for n in archive.namelist() if n.endswith(member_suffix)))
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    raw[start:start + 4] = b"\xff\xff\xff\xff"  # deflate block type 3: invalid
    path.write_bytes(bytes(raw))


def test_a_damaged_or_missing_zip_is_reported_never_restored_and_never_a_500(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    backup = run_backup(queue_client, machines={"all": True})
    path = store.backup_dir(queue_settings) / backup["name"]
    damage(path, "Q1.nc")

    found = queue_client.post(f"/api/backups/{backup['id']}/verify").json()
    assert not found["ok"]
    assert [p.split(":")[0].rsplit("/", 1)[-1] for p in found["problems"]] == ["Q1.nc"]
    refused = queue_client.post(f"/api/backups/{backup['id']}/restore", json={"machine": "b2"})
    assert refused.status_code == 409 and refused.json()["errorCode"] == 20016
    assert queue_client.get("/api/jobs", params={"kind": "send"}).json() == []

    path.unlink()
    assert queue_client.get(f"/api/backups/{backup['id']}").status_code == 404
    gone = queue_client.post(f"/api/backups/{backup['id']}/restore", json={"machine": "a1"})
    assert gone.status_code == 404 and "is missing" in gone.json()["statusMsg"]
    assert not queue_client.post(f"/api/backups/{backup['id']}/verify").json()["ok"]


def test_a_fanuc_18i_is_restored_from_its_own_backup_and_onto_a_0i_f(
        queue_client, add_machines, queue_settings):
    # The 18i takes no folder at all; the 0i-F writes its root //CNC_MEM/.
    add_machines({"id": "f18", "name": "Old", "model": "Fanuc 18i"},
                 {"id": "f0i", "name": "New", "model": "Fanuc 0i-F"})
    program = "%\nO0001\nG0 X1\nM30\n%\n"
    sent = queue_client.post("/api/cnc/sendFile", params={"machineID": "f18"},
                             json={"content": program}).json()
    assert sent["errorCode"] == 0
    backup = run_backup(queue_client, machines={"ids": ["f18"]})

    same = queue_client.post(f"/api/backups/{backup['id']}/restore",
                             json={"machine": "f18", "replace": True}).json()
    assert [t["errorCode"] for t in wait_done(queue_client, same["id"])["targets"]] == [0]
    other = queue_client.post(f"/api/backups/{backup['id']}/restore",
                              json={"machine": "f18", "to": "f0i"}).json()
    assert [t["errorCode"] for t in wait_done(queue_client, other["id"])["targets"]] == [0]
    listed = queue_client.get("/api/cnc/readProgramList", params={"machineID": "f0i"}).json()
    assert (listed["dirAtCNC"], listed["programs"]) == ("//CNC_MEM/", ["1"])


def fanuc_and_heidenhain(client: Any, add_machines: Any) -> dict[str, Any]:
    """A backup of a Fanuc 0i-F (O1234, O8000, USER/O2000 below //CNC_MEM/) and a TNC640
    (demo\\FLANGE.h below TNC:\\nc_prog)."""
    add_machines({"id": "f0i", "name": "Lathe", "model": "Fanuc 0i-F"},
                 {"id": "tnc", "name": "Mill", "model": "Heidenhain TNC640"})
    for number, folder in (("1234", None), ("8000", None), ("2000", "//CNC_MEM/USER")):
        if folder:
            client.get("/api/cnc/createDir",
                       params={"machineID": "f0i", "dirName": "USER", "dirAtCNC": "//CNC_MEM/"})
        sent = client.post("/api/cnc/sendFile", params={"machineID": "f0i", "dirAtCNC": folder},
                           json={"content": f"%\nO{number}\nG0 X1\nM30\n%\n"}).json()
        assert sent["errorCode"] == 0, sent
    client.get("/api/cnc/createDir",
               params={"machineID": "tnc", "dirName": "demo", "dirAtCNC": "TNC:\\nc_prog"})
    sent = client.post("/api/cnc/sendFile",
                       params={"machineID": "tnc", "dirAtCNC": "demo", "fileName": "FLANGE.h"},
                       json={"content": "0 BEGIN PGM FLANGE MM\n"}).json()
    assert sent["errorCode"] == 0, sent
    return run_backup(client, machines={"ids": ["f0i", "tnc"]})


def test_a_restore_takes_a_path_below_the_machines_root_as_the_backup_shows_it(
        queue_client, add_machines):
    backup = fanuc_and_heidenhain(queue_client, add_machines)

    def restored(machine: str, path: str) -> list[str]:
        job = queue_client.post(f"/api/backups/{backup['id']}/restore",
                                json={"machine": machine, "path": path})
        assert job.status_code == 202, job.text
        targets = queue_client.get(f"/api/jobs/{job.json()['id']}").json()["targets"]
        return [f"{t.get('subDir') or ''}/{t['fileName']}" for t in targets]

    assert restored("f0i", "O1234") == ["/O1234"]  # as the ZIP and dncq backup show name it
    assert restored("f0i", "1234") == ["/O1234"]  # a Fanuc program by its number
    assert restored("f0i", "USER") == ["USER/O2000"]  # a folder
    assert restored("f0i", "USER/2000") == ["USER/O2000"]
    assert restored("f0i", "//CNC_MEM/O8000") == ["/O8000"]  # as the manifest holds it
    assert restored("tnc", "demo/FLANGE.h") == ["demo/FLANGE.h"]
    assert restored("tnc", "TNC:\\nc_prog\\demo") == ["demo/FLANGE.h"]


def test_a_restore_of_a_path_the_backup_does_not_hold_names_the_closest_it_holds(
        queue_client, add_machines):
    backup = fanuc_and_heidenhain(queue_client, add_machines)

    def refused(path: str) -> str:
        answer = queue_client.post(f"/api/backups/{backup['id']}/restore",
                                   json={"machine": "f0i", "path": path})
        assert (answer.status_code, answer.json()["errorCode"]) == (404, 158)
        return str(answer.json()["statusMsg"])

    assert refused("O1235").endswith("holds nothing of f0i at O1235 (did you mean O1234?)")
    assert refused("/O8000").endswith("(did you mean O8000?)")  # //CNC_MEM/ is the root
    assert refused("//CNC_MEM/USER/O2001").endswith("(did you mean //CNC_MEM/USER/O2000?)")
    assert "holds nothing of f0i at ../O8000" in refused("../O8000")  # nothing above the root
    assert "holds nothing of f0i at //CNC_MEM/../O8000" in refused("//CNC_MEM/../O8000")
    assert queue_client.get("/api/jobs", params={"kind": "restore"}).json() == []


def test_a_restore_for_a_machine_the_backup_did_not_back_up_names_those_it_did(
        queue_client, add_machines):
    backup = fanuc_and_heidenhain(queue_client, add_machines)
    add_machines({"id": "m9", "name": "New", "model": "Mock"})

    answer = queue_client.post(f"/api/backups/{backup['id']}/restore", json={"machine": "m9"})

    assert (answer.status_code, answer.json()["errorCode"]) == (404, 158)
    assert answer.json()["statusMsg"].endswith(
        f"backup {backup['id']} holds no file of m9: it backed up f0i, tnc")


def test_diff_does_not_call_the_files_of_a_machine_that_failed_removed(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    first = run_backup(queue_client, machines={"all": True})
    options = queue_settings.data_dir / "mock" / "b2" / "options.json"
    options.write_text('{"offline": true}')
    second = run_backup(queue_client, machines={"all": True}, max_attempts=1)
    assert second["status"] == "partial"

    changes = queue_client.get(f"/api/backups/{first['id']}/diff/{second['id']}").json()
    # b2 failed in the second: its files are unknown there, and the diff says so
    assert changes["b2"] == {"added": [], "removed": [], "changed": [],
                             "incomplete": {second["id"]: "failed"}}
    assert changes["a1"]["incomplete"] == {}


def test_diff_compares_what_both_hold_of_a_machine_one_backup_holds_only_part_of(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    first = run_backup(queue_client, machines={"all": True})
    mock_file(queue_settings, "a1", "P1.nc", "G0 X100\n")  # changed
    second = run_backup(queue_client, targets=[{"machineID": "a1", "fileName": "P1.nc"},
                                               {"machineID": "a1", "fileName": "nope.nc"}])
    assert second["machines"][0]["status"] == "partial"

    changes = queue_client.get(f"/api/backups/{first['id']}/diff/{second['id']}").json()

    # sub/P2.nc is not in the second, which does not hold all of a1: unknown, not removed
    assert changes["a1"] == {"added": [], "removed": [], "changed": ["/P1.nc"],
                             "incomplete": {second["id"]: "partial"}}
    assert changes["b2"]["incomplete"] == {second["id"]: "absent"}


def test_a_backup_job_is_not_retried_but_says_how_to_back_up_what_failed(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    add_machines({"id": "c3", "name": "Off", "model": "Mock", "options": {"offline": True}})
    backup = run_backup(queue_client, machines={"all": True}, max_attempts=1)

    refused = queue_client.post(f"/api/jobs/{backup['job']}/retry")

    assert refused.status_code == 409
    assert refused.json()["statusMsg"].endswith("dncq backup run --to c3")
    assert queue_client.get(f"/api/jobs/{backup['job']}").json()["state"] != "running"


def test_one_failed_target_keeps_the_files_of_the_machines_other_targets(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    backup = run_backup(queue_client, targets=[{"machineID": "a1"},
                                               {"machineID": "a1", "dirAtCNC": "nope"}])
    assert backup["status"] == "partial"
    [machine] = backup["machines"]
    assert (machine["status"], machine["errorCode"]) == ("partial", 158)
    manifest = queue_client.get(f"/api/backups/{backup['id']}/manifest").json()
    assert sorted(f["path"] for f in manifest["files"]) == ["/P1.nc", "/sub/P2.nc"]


@pytest.mark.parametrize(("first", "said"), [
    # cancelled first: the failure says why the machine's files are missing
    ((TargetState.CANCELLED, ErrorCode.CANCELLED, "cancelled by alice"),
     (158, "Path is not found.", "no folder nope")),
    # failed first, in no words of its own: none of a later target's are given for it
    ((TargetState.FAILED, ErrorCode.MACHINE_OFFLINE, None),
     (20004, "Machine is offline.", None)),
], ids=["cancelled-first", "failed-first-without-words"])
def test_a_machines_error_and_its_words_are_those_of_one_target_its_first_failed_one(
        client, add_machines, settings, first, said):
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    state, code, words = first
    with db.session_scope(settings.resolved_database_url) as session:
        session.add(Job(id="j1", kind=JobKind.BACKUP, state=JobState.FAILED, targets=[
            Target(position=0, machine_id="a1", state=state, error_code=int(code),
                   error_msg=MESSAGES[code], status_msg=words),
            Target(position=1, machine_id="a1", params={"dirAtCNC": "nope"},
                   state=TargetState.FAILED, error_code=int(ErrorCode.PATH_NOT_FOUND),
                   error_msg=MESSAGES[ErrorCode.PATH_NOT_FOUND], status_msg="no folder nope")]))
    assembled = store.assemble(settings=settings, job_id="j1")
    assert assembled is not None

    manifest = client.get(f"/api/backups/{assembled}/manifest").json()

    [machine] = manifest["machines"]
    assert (machine["errorCode"], machine["errorMsg"], machine["statusMsg"]) == said


def test_a_stored_backup_dates_its_folders_right_on_a_host_not_on_utc(
        queue_client, add_machines, queue_settings, monkeypatch):
    import struct

    from tests.jobs.backup.zip_checks import UNIX_TIME_EXTRA, extras

    monkeypatch.setenv("TZ", "Asia/Kolkata")  # UTC+05:30, no daylight saving
    time.tzset()
    try:
        fleet(add_machines, queue_settings)
        started = time.time()
        backup = run_backup(queue_client, machines={"tags": ["night"]})
    finally:
        monkeypatch.undo()
        time.tzset()
    path = store.backup_dir(queue_settings) / backup["name"]
    with zipfile.ZipFile(path) as archive:
        folders = [i for i in archive.infolist() if i.is_dir()]
    assert folders
    for info in folders:
        _, seconds = struct.unpack("<Bl", extras(info.extra)[UNIX_TIME_EXTRA][:5])
        assert started - 5 <= seconds <= time.time() + 5, info.filename


def test_a_name_that_is_not_text_is_left_out_and_said_the_rest_is_backed_up(
        queue_client, add_machines, queue_settings, tmp_path):
    folder = tmp_path / "share"
    folder.mkdir()
    (folder / "A.nc").write_bytes(b"G0 X1\n")
    with open(os.path.join(os.fsencode(folder), b"bad\xffname.nc"), "wb") as f:
        f.write(b"G0 X2\n")
    add_machines({"id": "s1", "name": "Share", "model": "Shared folder", "transport": "share",
                  "options": {"path": str(folder)}})

    backup = run_backup(queue_client, machines={"all": True})

    assert backup["status"] == "partial" and backup["files"] == 1
    target = queue_client.get(f"/api/jobs/{backup['job']}").json()["targets"][0]
    assert target["errorCode"] == 0
    assert "left out (1)" in target["statusMsg"]
    assert "bad\\xffname.nc" in target["statusMsg"]


def test_a_machine_without_programs_is_an_empty_folder_and_no_work_file_is_left(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    add_machines({"id": "e3", "name": "New", "model": "Mock"})
    backup = run_backup(queue_client, machines={"ids": ["e3", "b2"]})
    assert (backup["status"], backup["files"]) == ("complete", 1)
    with zipfile.ZipFile(store.backup_dir(queue_settings) / backup["name"]) as archive:
        top = archive.namelist()[0]
        names = sorted(n.removeprefix(top) for n in archive.namelist()[1:])
        assert archive.read(top + "b2_Mill/Q1.nc") == b"G0 Y1\n"
    assert names == ["_manifest.json", "b2_Mill/", "b2_Mill/Q1.nc", "e3_New/"]
    # Each target's work file (its deflated programs, then their record) went with the job's.
    work = store.backup_dir(queue_settings) / ".work"
    assert work.is_dir() and list(work.glob("**/*")) == []


def test_the_listing_by_a_mistyped_machine_is_refused_naming_the_machine_meant(
        client, add_machines, settings):
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})

    listed = client.get("/api/backups", params={"machine": "1O10"})  # a letter O for the 0

    assert listed.status_code == 404
    assert listed.json() == {"errorCode": 10003, "errorMsg": "Machine ID does not exist.",
                             "statusMsg": "Invalid MachineID (1O10) (did you mean 1010?)"}


def test_the_listing_by_a_machine_removed_since_finds_its_backups(client, settings):
    gone = [{"machineID": "gone", "machineName": "Old", "status": "ok", "errorCode": 0,
             "errorMsg": None, "files": []}]
    with db.session_scope(settings.resolved_database_url) as session:
        store._record(session, "b1", None, "T.zip", BackupStatus.COMPLETE, 10, "0" * 64, gone)

    listed = client.get("/api/backups", params={"machine": "gone"})

    assert listed.status_code == 200, listed.text
    assert [b["id"] for b in listed.json()] == ["b1"]
