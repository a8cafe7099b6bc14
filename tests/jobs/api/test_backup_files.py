"""2.6.13 backupFiles: the seed's layout, its error behaviour, safe names, the manifest."""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from urllib.parse import unquote

import httpx
import pytest
from fastapi.testclient import TestClient

from jobs.api.app import create_app
from jobs.backup import download, store
from jobs.errors import ContractError, ErrorCode
from jobs.folders import job_folder
from tests.conftest import API_KEY
from tests.jobs.backup.zip_checks import unzipped
from tests.jobs.helpers import mock_of, on_machine
from tests.live_server import HTTP_TIMEOUT_S, serving

SEED_EXAMPLE = [
    {"machineID": "1010", "fileName": "08000"},
    {"machineID": "1011", "DirAtCNC": "dir1", "includeSubDir": False},
    {"machineID": "1012", "fileName": "sample.NC", "SubDir": "Dir/Prog"},
]


def put(client, machine_id: str, name: str, content: str, **where: str) -> None:
    body = client.post("/api/cnc/sendFile", params={"machineID": machine_id, "fileName": name,
                                                     **where}, json={"content": content}).json()
    assert body["errorCode"] == 0, body


def mkdir(client, machine_id: str, name: str, **where: str) -> None:
    body = client.get("/api/cnc/createDir",
                      params={"machineID": machine_id, "dirName": name, **where}).json()
    assert body["errorCode"] in (0, 142), body


def backup(client, body) -> zipfile.ZipFile:
    response = client.post("/api/cnc/backupFiles", json=body)
    assert response.headers["content-type"] == "application/octet-stream", response.text
    return zipfile.ZipFile(io.BytesIO(response.content))


@pytest.fixture
def client(queue_client):
    """The API with a worker behind it: backupFiles' targets are fetched by the workers."""
    return queue_client


@pytest.fixture
def seed_fleet(client, demo_fleet):
    """The demo fleet plus what the seed's example needs: a subfolder to leave out on 1011,
    Dir/Prog/sample.NC on 1012."""
    mkdir(client, "1011", "deeper", dirAtCNC="dir1")
    put(client, "1011", "skip.NC", "G0\n", dirAtCNC="dir1/deeper")
    mkdir(client, "1012", "Dir")
    mkdir(client, "1012", "Prog", subDir="Dir")
    put(client, "1012", "sample.NC", "G1 X1\n", subDir="Dir/Prog")


def test_seed_example_gives_the_seed_tree(client, seed_fleet):
    archive = backup(client, SEED_EXAMPLE)
    names = archive.namelist()
    top = names[0]
    assert top.startswith("BackupFiles_") and top.endswith("/")
    assert len(top) == len("BackupFiles_2024.03.07.12.04.46/")
    assert sorted(n.removeprefix(top) for n in names[1:]) == [
        "1010_Lathe-A/", "1010_Lathe-A/O8000",
        "1011_Mill-B/", "1011_Mill-B/dir1/sample.NC",
        "1012_Mill-C/", "1012_Mill-C/Dir/Prog/sample.NC",
        "_manifest.json",
    ]
    assert archive.read(top + "1012_Mill-C/Dir/Prog/sample.NC") == b"G1 X1\n"
    assert archive.testzip() is None


def test_every_entry_is_inside_the_one_top_folder(client, seed_fleet):
    names = backup(client, SEED_EXAMPLE).namelist()
    assert {n.split("/", 1)[0] for n in names} == {names[0].rstrip("/")}


def test_include_sub_dir_true_takes_the_subfolders(client, seed_fleet):
    names = backup(client, [{"machineID": "1011", "dirAtCNC": "dir1"}]).namelist()
    assert any(n.endswith("1011_Mill-B/dir1/deeper/skip.NC") for n in names)


def test_include_sub_dir_false_leaves_the_subfolders_out_in_any_case_it_is_written(
        client, seed_fleet):
    # as a client's classes write their fields (the seed's own DirAtCNC, and IncludeSubDir)
    names = backup(client, [{"MachineID": "1011", "DirAtCNC": "dir1",
                             "IncludeSubDir": False}]).namelist()
    assert any(n.endswith("1011_Mill-B/dir1/sample.NC") for n in names)
    assert not any("deeper" in n for n in names)


def test_a_whole_machine_backs_up_its_root_tree(client, demo_fleet):
    names = backup(client, [{"machineID": "1016"}]).namelist()
    files = sorted(n.split("/", 2)[2] for n in names if n.count("/") >= 2 and not n.endswith("/"))
    assert files == ["1/1/sample2.nc", "1/sample1.nc", "SAMPLE"]


def test_unknown_machine_aborts_before_any_byte_with_the_seed_error(client, seed_fleet):
    response = client.post("/api/cnc/backupFiles", json=[*SEED_EXAMPLE, {"machineID": "1099"}])
    assert response.json() == {"errorCode": 10003, "errorMsg": "Machine ID does not exist.",
                               "statusMsg": "Invalid MachineID (1099)"}


@pytest.mark.parametrize(("target", "named"), [
    ({"machineID": "1016", "includeSubDir": "maybe"}, "target 2: includeSubDir: "),
    ({"machineID": "1016", "fileName": ["a.nc"]}, "target 2: fileName: "),
    ({"fileName": "x.nc"}, "target 2: machineID: Field required"),
])
def test_a_malformed_target_is_refused_naming_its_field(client, demo_fleet, target, named):
    response = client.post("/api/cnc/backupFiles", json=[{"machineID": "1016"}, target])
    body = response.json()
    assert body["errorCode"] == 20001 and body["statusMsg"].startswith(named), body


def test_missing_file_or_folder_aborts_with_158_naming_the_target(client, demo_fleet):
    response = client.post("/api/cnc/backupFiles",
                           json=[{"machineID": "1011", "dirAtCNC": "nodir"}])
    body = response.json()
    assert body["errorCode"] == 158 and "1011" in body["statusMsg"]
    missing = client.post("/api/cnc/backupFiles",
                          json=[{"machineID": "1016", "fileName": "nope.nc"}]).json()
    assert missing["errorCode"] == 158


@pytest.mark.parametrize(("body", "code", "named"), [
    ([{"machineID": "1011", "dirAtCNC": "nodir"}, {"machineID": "1010", "fileName": "nope"}],
     158, "(1011: nodir)"),
    ([{"machineID": "1010", "fileName": "nope"}, {"machineID": "1011", "dirAtCNC": "nodir"}],
     158, "(1010: nope)"),
    ([{"machineID": "1010"}, {"machineID": "1011", "dirAtCNC": "nodir"}, {"machineID": "1099"}],
     158, "(1011: nodir)"),
    ([{"machineID": "1010"}, {"machineID": "1099"}, {"machineID": "1011", "dirAtCNC": "nodir"}],
     10003, "(1099)"),
    ([{"machineID": "1011", "dirAtCNC": "nodir"}, {"fileName": "x.nc"}], 158, "(1011: nodir)"),
    ([{"fileName": "x.nc"}, {"machineID": "1099"}], 20001, "target 1: machineID"),
])
def test_of_several_failing_targets_the_first_in_the_request_is_answered(
        client, demo_fleet, body, code, named):
    """The machines are probed at once; which one answers first must not decide the error."""
    answer = client.post("/api/cnc/backupFiles", json=body).json()
    assert answer["errorCode"] == code and named in answer["statusMsg"], answer


def test_the_machines_are_probed_at_once_each_one_operation_at_a_time(
        client, settings, seed_fleet):
    """A request for many machines must not wait one round trip per machine before its
    answer begins; two targets on one machine are still probed one after the other."""
    machines = [mock_of(settings, m) for m in ("1010", "1011", "1012")]
    for machine in machines:
        machine.set_options(latency_ms=1000, trace=True)  # long: probes started apart still meet

    archive = backup(client, [*SEED_EXAMPLE, {"machineID": "1010"}])

    probes = [min(_traced(machine)) for machine in machines]  # each machine's first operation
    assert max(start for start, _ in probes) < min(end for _, end in probes)  # all at once
    assert [machine.peak_active() for machine in machines] == [1, 1, 1]
    assert archive.testzip() is None


def _traced(machine) -> list[tuple[float, float]]:
    """The (start, end) of every operation a mock machine with `trace` on has done."""
    lines = (machine.folder / "trace").read_text().split("\n")
    return [(float(start), float(end)) for start, end in (line.split() for line in lines if line)]


def test_manifest_records_every_file_with_its_hash(client, seed_fleet):
    archive = backup(client, SEED_EXAMPLE)
    top = archive.namelist()[0]
    manifest = json.loads(archive.read(top + "_manifest.json"))
    files = [f for m in manifest["machines"] for f in m["files"]]
    assert len(files) == 3
    for f in files:
        data = archive.read(f["archivePath"])
        assert hashlib.sha256(data).hexdigest() == f["sha256"] and len(data) == f["size"]
    assert {f["path"] for f in files} >= {"//CNC_MEM/O8000", "mpf.dir/dir1/sample.NC"}


def test_files_come_deflated_and_nothing_stays_in_the_work_folder(client, settings, seed_fleet):
    response = client.post("/api/cnc/backupFiles", json=SEED_EXAMPLE)
    archive = zipfile.ZipFile(io.BytesIO(response.content))
    members = [i for i in archive.infolist() if not i.is_dir()]
    assert members and {i.compress_type for i in members} == {zipfile.ZIP_DEFLATED}
    assert archive.testzip() is None  # every member's CRC-32 matches its bytes
    assert not job_folder(settings, response.headers["X-Dncq-Job"]).exists()


def test_hostile_names_stay_inside_their_machine_folder_and_come_back_exactly(
        client, settings, add_machines):
    add_machines({"id": "h1", "name": "../../etc", "model": "Mock"})
    storage = settings.data_dir / "mock" / "h1" / "files"
    storage.mkdir(parents=True, exist_ok=True)
    hostile = ["a:b", "%41", "@root", "weird\\name", "ünï cødé"]
    for name in hostile:
        (storage / name).write_text(name)
    archive = backup(client, [{"machineID": "h1"}])
    top = archive.namelist()[0]
    for entry in archive.namelist():
        assert ".." not in entry.split("/") and not entry.startswith("/")
        assert entry.startswith(top)
    folder = top + "h1_..%2F..%2Fetc/"
    files = [n.removeprefix(folder) for n in archive.namelist()
             if n.startswith(folder) and n != folder]
    assert sorted(unquote(f) for f in files) == sorted(hostile)
    for f in files:
        assert archive.read(folder + f).decode() == unquote(f)


def test_a_file_of_another_root_goes_under_its_root_mark(client, demo_fleet):
    names = backup(client, [{"machineID": "1013", "dirAtCNC": "IC1"}]).namelist()
    assert any(n.endswith("1013_Lathe-D/@IC1/200") for n in names)


def test_a_file_below_the_default_root_reached_from_a_wider_root_is_filed_once_as_the_root_files_it(
        client, demo_fleet):  # the demo's 1012 holds TNC:\\nc_prog\\PLATE.h
    names = backup(client, [{"machineID": "1012", "dirAtCNC": "TNC:\\"},
                            {"machineID": "1012", "fileName": "PLATE.h"}]).namelist()

    assert [n.split("/", 2)[2] for n in names if n.endswith("PLATE.h")] == ["PLATE.h"]
    assert not any("/@TNC/nc_prog/" in n for n in names)


def test_a_failure_after_streaming_began_gives_an_incomplete_download(
        queue_settings, celery_worker, demo_fleet, monkeypatch):
    real_fetch = store.fetch_target

    def fetch(settings_, files, *, machine_id, **kwargs):
        if machine_id == "1016":
            raise RuntimeError("machine dropped the connection")
        return real_fetch(settings_, files, machine_id=machine_id, **kwargs)

    monkeypatch.setattr(store, "fetch_target", fetch)  # in the worker, which is in-process
    # More than the first piece the download sends, in 1010's //CNC_MEM/.
    big = on_machine(queue_settings, "1010", "CNC_MEM/O9999")
    big.write_bytes(b"%\nO9999\n" + os.urandom(download.SENT_BYTES).hex().encode() + b"\n%\n")
    body = [{"machineID": "1010"}, {"machineID": "1016"}]
    with serving(create_app(queue_settings)) as live, httpx.Client(
            base_url=live.url, timeout=HTTP_TIMEOUT_S) as http:
        received = bytearray()
        with pytest.raises(httpx.RemoteProtocolError):  # cut off, not timed out
            with http.stream("POST", "/api/cnc/backupFiles", json=body,
                             headers={"X-Api-Key": API_KEY}) as response:
                assert response.status_code == 200
                job_id = response.headers["X-Dncq-Job"]
                for chunk in response.iter_bytes():
                    received += chunk
        live.wait_idle()
    with pytest.raises(zipfile.BadZipFile):
        zipfile.ZipFile(io.BytesIO(bytes(received)))
    assert not job_folder(queue_settings, job_id).exists()  # no partial file left

    # ... and is recorded: a failed job naming the machine that broke the download.
    with TestClient(create_app(queue_settings), headers={"X-Api-Key": API_KEY}) as client:
        [job] = client.get("/api/jobs", params={"kind": "backup"}).json()
        detail = client.get(f"/api/jobs/{job['id']}").json()
        assert detail["state"] == "failed"
        by_machine = {t["machineID"]: t for t in detail["targets"]}
        assert by_machine["1016"]["state"] == "failed"
        assert by_machine["1016"]["errorCode"] == 20017
        assert by_machine["1010"]["state"] == "cancelled"  # the client has none of it
        retried = client.post(f"/api/jobs/{job['id']}/retry")
        assert retried.status_code == 409  # it went to its client; nothing to run again
        assert retried.json()["errorCode"] == 20001


def test_a_target_that_fails_before_the_first_bytes_is_answered_with_its_error(
        client, queue_settings, demo_fleet, monkeypatch):
    real_fetch = store.fetch_target

    def fetch(settings_, files, *, machine_id, **kwargs):
        if machine_id == "1016":
            raise ContractError(ErrorCode.CONNECTION_FAILED, "the machine dropped the line")
        return real_fetch(settings_, files, machine_id=machine_id, **kwargs)

    monkeypatch.setattr(store, "fetch_target", fetch)  # in the worker, which is in-process
    response = client.post("/api/cnc/backupFiles",
                           json=[{"machineID": "1010"}, {"machineID": "1016"}])

    assert response.status_code == 200
    assert response.json() == {"errorCode": 20006, "errorMsg": "Connection to the machine failed.",
                               "statusMsg": "Connection to the machine failed. (1016)"}
    [job] = client.get("/api/jobs", params={"kind": "backup"}).json()
    assert response.headers["X-Dncq-Job"] == job["id"]  # where the client finds the record
    assert job["state"] == "failed"
    assert not job_folder(queue_settings, job["id"]).exists()  # no partial file left


def test_a_whole_download_is_recorded_as_a_succeeded_backup_job(client, demo_fleet):
    backup(client, [{"machineID": "1010", "fileName": "08000"}, {"machineID": "1011"}])
    [job] = client.get("/api/jobs", params={"kind": "backup"}).json()
    detail = client.get(f"/api/jobs/{job['id']}").json()
    assert detail["state"] == "succeeded"
    assert [t["machineID"] for t in detail["targets"]] == ["1010", "1011"]
    assert client.get("/api/backups").json() == []  # nothing stored: the client has the ZIP


def test_a_folder_the_download_cannot_walk_into_is_in_its_manifest_as_left_out(
        client, add_machines, tmp_path):
    folder = tmp_path / "share"
    (folder / "odd\\name").mkdir(parents=True)
    (folder / "A.nc").write_bytes(b"G0 X1\n")
    add_machines({"id": "s1", "name": "Share", "model": "Shared folder", "transport": "share",
                  "options": {"path": str(folder)}})

    archive = backup(client, [{"machineID": "s1"}])

    top = archive.namelist()[0]
    [machine] = json.loads(archive.read(top + "_manifest.json"))["machines"]
    assert machine["status"] == "partial"
    assert [(x["path"], x["isDir"]) for x in machine["leftOut"]] == [("odd\\name", True)]
    assert [f["path"] for f in machine["files"]] == ["A.nc"]


def test_a_machine_whose_folder_would_be_too_long_a_name_unzips_from_the_stream(
        client, add_machines, queue_settings, tmp_path):
    add_machines({"id": "a1", "name": "加" * 200, "model": "Mock"})  # 3 bytes each
    on_machine(queue_settings, "a1", "P1.nc").write_bytes(b"G0 X1\n")
    response = client.post("/api/cnc/backupFiles", json=[{"machineID": "a1"}])
    assert response.headers["content-type"] == "application/octet-stream", response.text
    (tmp_path / "backup.zip").write_bytes(response.content)

    files = unzipped(tmp_path / "backup.zip", tmp_path / "out")

    [(path, data)] = [(p, d) for p, d in files.items() if p.endswith("P1.nc")]
    folder = path.split("/")[1]
    assert data == b"G0 X1\n"
    assert folder.startswith("a1_加加") and len(folder.encode()) <= 255
