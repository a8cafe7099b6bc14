"""Today's OctoPrint listing (`GET /api/files`) of a machine: its shape, and the OctoPrint
client libraries nobody here wrote reading it."""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from datetime import UTC, datetime

import pytest

from jobs import db
from jobs.api.app import create_app
from jobs.models import RunState
from tests.conftest import API_KEY
from tests.jobs.helpers import ended_run, mock_file
from tests.live_server import HTTP_TIMEOUT_S, LiveServer, serving
from tests.worker.transports.octoprint_server import OctoPrintServer, empty_octoprint
from tests.worker.transports.venvs import venv_with


@pytest.fixture
def machine(add_machines, settings) -> None:
    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})
    mock_file(settings, "1016", "SAMPLE", "G0 X0\n" * 100)
    mock_file(settings, "1016", "1/sample1.nc", "G1 X1\n")


def test_the_sdcard_origin_lists_files_in_bytes_and_posix_seconds_as_octoprint_does(
        client, machine) -> None:
    answer = client.get("/machines/1016/api/files/sdcard")

    assert answer.status_code == 200
    body = answer.json()
    assert set(body) == {"files"}  # OctoPrint tells no space beside its SD card
    by_path = {f["path"]: f for f in body["files"]}
    assert set(by_path) == {"SAMPLE", "1/sample1.nc"}
    sample, nested = by_path["SAMPLE"], by_path["1/sample1.nc"]
    assert (sample["name"], sample["display"], sample["origin"]) == ("SAMPLE", "SAMPLE", "sdcard")
    assert (sample["type"], sample["typePath"]) == ("machinecode", ["machinecode", "gcode"])
    assert sample["size"] == 600 and isinstance(sample["date"], int)
    assert abs(sample["date"] - datetime.now(UTC).timestamp()) < 600
    assert sample["refs"]["resource"] == "http://testserver/machines/1016/api/files/sdcard/SAMPLE"
    assert nested["name"] == "sample1.nc"


def test_every_file_comes_with_the_local_stores_space_in_bytes(client, machine) -> None:
    body = client.get("/api/files", params={"machineID": "1016"}).json()

    assert isinstance(body["free"], int) and isinstance(body["total"], int)
    assert body["free"] <= body["total"]
    assert {f["origin"] for f in body["files"]} == {"sdcard"}  # no library folder assigned
    sample = next(f for f in body["files"] if f["path"] == "SAMPLE")
    assert sample["refs"]["resource"] == "http://testserver/api/files/sdcard/SAMPLE?machineID=1016"
    assert client.get(sample["refs"]["resource"]).json()["path"] == "SAMPLE"


def test_a_programs_runs_are_its_prints_in_posix_seconds(client, machine, settings) -> None:
    ended = datetime(2026, 12, 1, 12, 0, tzinfo=UTC)
    with db.session_scope(settings.resolved_database_url) as session:
        session.add(ended_run("j", "1016", "SAMPLE", RunState.SUCCEEDED, ended))

    sample = client.get("/machines/1016/api/files/sdcard/SAMPLE").json()

    assert sample["prints"] == {"success": 1, "failure": 0,
                                "last": {"date": int(ended.timestamp()), "success": True}}


@pytest.mark.parametrize("path", ["/machines/1016/api/files/usb",
                                  "/machines/1016/api/files/sdcard/NOPE",
                                  "/machines/1016/api/files/sdcard/1",  # no folders, as OctoPrint's
                                  "/machines/nope/api/files"])
def test_an_origin_file_or_machine_that_is_not_there_is_404(client, machine, path) -> None:
    assert client.get(path).status_code == 404


def test_a_file_in_a_machines_folder_is_asked_for_by_its_listed_path(client, machine) -> None:
    nested = client.get("/machines/1016/api/files/sdcard/1/sample1.nc")

    assert nested.status_code == 200
    assert (nested.json()["path"], nested.json()["size"]) == ("1/sample1.nc", 6)


def test_a_local_files_download_ref_gives_its_bytes_as_octoprints_does(
        client, machine, octoprint_server: OctoPrintServer) -> None:
    """A client downloads a listed file by its `refs.download`, which OctoPrint gives every
    local file (and no file of the SD card)."""
    import httpx

    program = b"G21 G90\nG0 X0 Y0\nG1 X10 F300\nM30\n"
    upload = {"file": ("PART.gcode", program)}
    headers = {"X-Api-Key": octoprint_server.api_key}
    with httpx.Client(base_url=octoprint_server.url, headers=headers,
                      timeout=HTTP_TIMEOUT_S) as octoprint:
        try:
            octoprint.post("/api/files/local", files=upload).raise_for_status()
            [theirs] = octoprint.get("/api/files/local").json()["files"]
            their_bytes = octoprint.get(theirs["refs"]["download"]).content
        finally:
            empty_octoprint(octoprint_server)
    client.post("/machines/1016/api/files/local", files=upload).raise_for_status()

    [ours] = client.get("/machines/1016/api/files/local").json()["files"]

    assert their_bytes == program
    assert client.get(ours["refs"]["download"]).content == program
    assert "download" not in client.get("/machines/1016/api/files/sdcard/SAMPLE").json()["refs"]


def test_one_name_in_two_assigned_folders_is_two_files_each_found_by_its_path(
        client, machine) -> None:
    for folder, program in (("CAM", b"G0 X1\n"), ("OLD", b"G0 X22\n")):
        client.post("/machines/1016/api/files/local", files={"file": ("PART.nc", program)},
                    data={"path": folder}).raise_for_status()

    listed = client.get("/machines/1016/api/files/local").json()["files"]

    assert sorted(f["path"] for f in listed) == ["CAM/PART.nc", "OLD/PART.nc"]
    assert {f["name"] for f in listed} == {"PART.nc"}
    for listed_file in listed:
        found = client.get(listed_file["refs"]["resource"]).json()
        assert found == listed_file
        assert client.get(found["refs"]["download"]).content == (
            b"G0 X1\n" if found["path"] == "CAM/PART.nc" else b"G0 X22\n")


@pytest.mark.parametrize("path", ["/machines/1016/api/files/local",
                                  "/machines/1016/api/gcodefiles/local",
                                  "/machines/1016/api/files/local/CAM/PART.nc"])
def test_a_local_file_whose_content_is_gone_is_still_listed_and_its_download_is_404(
        client, machine, settings, path) -> None:
    client.post("/machines/1016/api/files/local", files={"file": ("PART.nc", b"G0 X1\n")},
                data={"path": "CAM"}).raise_for_status()
    [blob] = (p for p in (settings.data_dir / "blobs").rglob("*") if p.is_file())
    blob.unlink()  # lost from the store (a restore of the database without its blobs)

    answer = client.get(path)

    assert answer.status_code == 200  # the listing, not the missing content's 158 under it
    assert "errorCode" not in answer.json()
    listed = answer.json() if path.endswith("PART.nc") else next(
        f for f in answer.json()["files"] if f["origin"] == "local")
    assert "gcodeAnalysis" not in listed  # as OctoPrint lists a file not analysed
    if "/api/files/" in path:  # OctoPrint's files API gives each file its download
        assert client.get(listed["refs"]["download"]).status_code == 404


@pytest.fixture
def live(settings, machine) -> Iterator[LiveServer]:
    with serving(create_app(settings)) as server:
        yield server


@pytest.mark.parametrize(("client_library", "requirement", "make"), [
    ("octorest", "octorest==0.4", "from octorest import OctoRest as Client"),
    ("octoclient", "octoclient==0.2.dev1", "from octoclient import OctoClient as Client"),
])
def test_octoprint_client_libraries_list_a_machines_files_with_a_machine_scoped_key(
        live: LiveServer, client_library: str, requirement: str, make: str) -> None:
    python = venv_with(client_library, requirement)
    script = (f"import json\n{make}\n"
              f"client = Client(url={live.url!r}, apikey={API_KEY + '@1016'!r})\n"
              "print(json.dumps([client.files(), client.files('sdcard'),"
              " client.files('sdcard/SAMPLE')]))\n")

    done = subprocess.run([str(python), "-c", script], capture_output=True, text=True,
                          timeout=120)

    assert done.returncode == 0, done.stdout + done.stderr
    every, sdcard, one = json.loads(done.stdout)
    assert sorted(f["path"] for f in every["files"]) == ["1/sample1.nc", "SAMPLE"]
    assert sdcard["files"] == every["files"]
    assert one["path"] == "SAMPLE" and one["size"] == 600


@pytest.mark.parametrize(("client_library", "requirement", "make"), [
    ("octorest", "octorest==0.4", "from octorest import OctoRest as Client"),
    ("octoclient", "octoclient==0.2.dev1", "from octoclient import OctoClient as Client"),
])
def test_octoprint_client_libraries_find_their_upload_into_a_folder_by_the_path_it_answers(
        live: LiveServer, client_library: str, requirement: str, make: str) -> None:
    """Neither library can send `path` beside the file (octoclient has no such argument,
    octorest's is dropped): a folder is the file's name, `CAM/PART.gcode`, which lands in
    CAM; the path the upload answers is the one the listing gives and that finds it."""
    python = venv_with(client_library, requirement)
    script = (f"import io, json\n{make}\n"
              f"client = Client(url={live.url!r}, apikey={API_KEY + '@1016'!r})\n"
              "sent = client.upload(('CAM/PART.gcode', io.BytesIO(b'G0 X1\\n')))\n"
              "path = sent['files']['local']['path']\n"
              "print(json.dumps([path, client.files('local'), client.files(path)]))\n")

    done = subprocess.run([str(python), "-c", script], capture_output=True, text=True,
                          timeout=120)

    assert done.returncode == 0, done.stdout + done.stderr
    path, local, one = json.loads(done.stdout)
    assert path == "CAM/PART.gcode"
    assert [f["path"] for f in local["files"]] == [path]
    assert (one["path"], one["size"]) == (path, 6)
