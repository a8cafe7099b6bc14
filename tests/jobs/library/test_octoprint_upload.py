"""OctoPrint's upload, for slicers and CAM: real OctoPrint clients nobody here wrote send a
program to a machine through dncq, into the library and, with `print`, to the machine."""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from jobs.api.app import create_app
from tests.conftest import API_KEY
from tests.jobs.helpers import on_machine, wait_until
from tests.live_server import HTTP_TIMEOUT_S, LiveServer, serving
from tests.worker.transports.octoprint_server import REQUIREMENT, OctoPrintServer, empty_octoprint
from tests.worker.transports.venvs import venv_with

PROGRAM = b"G21 G90\nG0 X0 Y0\nG1 X10 F300\nM30\n"


@pytest.fixture
def live(queue_settings, celery_worker, add_machines) -> Iterator[LiveServer]:
    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"},
                 {"id": "1017", "name": "Sim-H", "model": "Mock",
                  "tags": ["needs-approval"]})
    with serving(create_app(queue_settings)) as server:
        yield server


def library_versions(live: LiveServer, path: str) -> list[dict]:
    import httpx

    return httpx.get(f"{live.url}/api/library/history/{path}",
                     headers={"X-Api-Key": API_KEY}, timeout=HTTP_TIMEOUT_S).json()


def test_octoprints_own_client_uploads_and_prints_through_the_machines_address(
        live: LiveServer, queue_settings, tmp_path: Path) -> None:
    """`octoprint client` (from the OctoPrint package) with the machine's URL prefix."""
    python = venv_with("octoprint", REQUIREMENT)
    part = tmp_path / "PART.gcode"
    part.write_bytes(PROGRAM)
    port = live.url.rsplit(":", 1)[1]

    done = subprocess.run(
        [str(python), "-m", "octoprint", "client", "-h", "127.0.0.1", "-p", port,
         "--prefix", "/machines/1016", "-a", API_KEY, "upload", "api/files/local", str(part),
         "-P", "path", "CAM", "-P", "print", "true"],
        capture_output=True, text=True, timeout=120)

    assert done.returncode == 0, done.stdout + done.stderr
    assert "201" in done.stdout or '"done": true' in done.stdout.lower()
    [version] = library_versions(live, "CAM/PART.gcode")
    assert version["state"] == "approved"
    landed = on_machine(queue_settings, "1016", "PART.gcode")
    wait_until(lambda: landed.exists() and landed.read_bytes() == PROGRAM)


def test_a_client_library_that_keeps_only_the_host_uploads_with_a_machine_scoped_key(
        live: LiveServer, queue_settings, tmp_path: Path) -> None:
    """octorest (from the package index) drops the URL's path: the key names the machine.
    It sends its form fields (path, print) as JSON beside the file, which its HTTP library
    drops: the upload takes the machine's folder (`uploads`, none being assigned). The
    machine asks for approval, so the upload waits in the library and nothing is sent."""
    python = venv_with("octorest", "octorest==0.4")
    part = tmp_path / "PLATE.gcode"
    part.write_bytes(PROGRAM)
    script = ("import sys, json\nfrom octorest import OctoRest\n"
              f"client = OctoRest(url={live.url!r}, apikey={API_KEY + '@1017'!r})\n"
              f"answer = client.upload({str(part)!r}, path='CAM', print=True)\n"
              "print(json.dumps(answer))\n")

    done = subprocess.run([str(python), "-c", script], capture_output=True, text=True,
                          timeout=120)

    assert done.returncode == 0, done.stdout + done.stderr
    # Waiting for approval: not listed yet, as OctoPrint answers an upload still under way.
    assert '"done": false' in done.stdout and '"effectivePrint": false' in done.stdout
    [version] = library_versions(live, "uploads/PLATE.gcode")
    assert version["state"] == "pending"
    assert not on_machine(queue_settings, "1017", "PLATE.gcode").exists()


def test_the_upload_is_listed_in_the_machines_local_origin(live: LiveServer) -> None:
    import httpx

    headers = {"X-Api-Key": API_KEY}
    sent = httpx.post(f"{live.url}/machines/1016/api/files/local", headers=headers,
                      files={"file": ("PART.gcode", PROGRAM)}, data={"path": "CAM"},
                      timeout=HTTP_TIMEOUT_S)
    listing = httpx.get(f"{live.url}/machines/1016/api/gcodefiles/local",
                        headers=headers, timeout=HTTP_TIMEOUT_S).json()

    assert sent.status_code == 201 and sent.headers["location"].endswith("CAM/PART.gcode")
    refs = sent.json()["files"]["local"]["refs"]  # where a client looks the file up
    resource = httpx.get(refs["resource"], headers=headers, timeout=HTTP_TIMEOUT_S)
    download = httpx.get(refs["download"], headers=headers, timeout=HTTP_TIMEOUT_S)
    assert resource.status_code == 200 and resource.json()["path"] == "CAM/PART.gcode"
    assert download.content == PROGRAM
    [entry] = listing["files"]
    assert entry["name"] == "PART.gcode" and entry["origin"] == "local"
    assert entry["bytes"] == len(PROGRAM) and entry["size"] == f"{len(PROGRAM):.1f}B"
    # 10 mm at F300: 2 s; a machine tool's program uses no filament
    assert entry["gcodeAnalysis"] == {"estimatedPrintTime": "00:00:02", "filament": "n/a"}


def test_an_upload_waiting_for_approval_is_not_done_and_found_at_its_location_once_approved(
        live: LiveServer, tmp_path: Path) -> None:
    """OctoPrint's own client library uploads for a machine that asks for approval. As
    OctoPrint answers an upload whose work goes on after the answer (one still streaming to
    the printer's SD card), `done` is false and `Location` is the file's entry, which is 404
    until the file is listed: here, once a programmer approved it."""
    import httpx

    python = venv_with("octoprint", REQUIREMENT)
    part = tmp_path / "PART.gcode"
    part.write_bytes(PROGRAM)
    script = ("import json\nfrom octoprint_client import Client\n"
              f"client = Client({live.url + '/machines/1017'!r}, {API_KEY!r})\n"
              f"answer = client.upload('api/files/local', {str(part)!r}, "
              "additional={'path': 'CAM', 'print': 'true'})\n"
              "print(json.dumps({'status': answer.status_code, 'body': answer.json(), "
              "'location': answer.headers['Location']}))\n")
    done = subprocess.run([str(python), "-c", script], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    answer = json.loads(done.stdout)
    headers = {"X-Api-Key": API_KEY}

    assert answer["status"] == 201
    assert answer["body"]["done"] is False and answer["body"]["effectivePrint"] is False
    assert answer["body"]["dncq"]["state"] == "pending"
    location = answer["location"]
    assert location == answer["body"]["files"]["local"]["refs"]["resource"] == (
        f"{live.url}/machines/1017/api/files/local/CAM/PART.gcode")
    waiting = httpx.get(location, headers=headers, timeout=HTTP_TIMEOUT_S)
    assert waiting.status_code == 404 and waiting.json()["errorCode"] == 158

    approved = httpx.post(f"{live.url}/api/library/approve/CAM/PART.gcode", headers=headers,
                          timeout=HTTP_TIMEOUT_S)
    assert approved.status_code == 200, approved.text
    found = httpx.get(location, headers=headers, timeout=HTTP_TIMEOUT_S)
    assert found.status_code == 200
    assert (found.json()["path"], found.json()["size"]) == ("CAM/PART.gcode", len(PROGRAM))


@pytest.mark.parametrize(("asked", "effective"), [
    ({"select": "true"}, {"effectiveSelect": True, "effectivePrint": False}),
    ({"print": "true"}, {"effectiveSelect": False, "effectivePrint": True}),
    ({"select": "true", "print": "true"}, {"effectiveSelect": True, "effectivePrint": True}),
], ids=["select", "print", "both"])
def test_the_upload_answers_effective_select_and_print_for_what_was_asked_and_done(
        live: LiveServer, queue_settings, asked, effective) -> None:
    import httpx

    sent = httpx.post(f"{live.url}/machines/1016/api/files/local",
                      headers={"X-Api-Key": API_KEY}, files={"file": ("PART.gcode", PROGRAM)},
                      data=asked, timeout=HTTP_TIMEOUT_S).json()

    assert {k: sent[k] for k in effective} == effective
    landed = on_machine(queue_settings, "1016", "PART.gcode")  # sent all the same
    wait_until(lambda: landed.exists() and landed.read_bytes() == PROGRAM)


def test_an_upload_without_a_machine_is_refused(live: LiveServer) -> None:
    import httpx

    answer = httpx.post(f"{live.url}/api/files/local", headers={"X-Api-Key": API_KEY},
                        files={"file": ("PART.gcode", PROGRAM)}, timeout=HTTP_TIMEOUT_S)

    assert answer.status_code == 400 and "machine" in answer.json()["statusMsg"]


def test_an_uploads_file_name_that_climbs_out_of_its_folder_is_refused_as_octoprint_does(
        client, add_machines, octoprint_server: OctoPrintServer) -> None:
    """OctoPrint refuses `../PART.gcode`; dncq refuses it too, with 20001 and nothing kept,
    no longer keeping it as `PART.gcode`."""
    import httpx

    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})
    upload = {"file": ("../PART.gcode", PROGRAM)}
    try:
        theirs = httpx.post(f"{octoprint_server.url}/api/files/local", files=upload,
                            headers={"X-Api-Key": octoprint_server.api_key},
                            timeout=HTTP_TIMEOUT_S)
    finally:
        empty_octoprint(octoprint_server)

    ours = client.post("/machines/1016/api/files/local", files=upload)

    assert (theirs.status_code, ours.status_code) == (400, 400)
    assert ours.json()["errorCode"] == 20001
    assert client.get("/api/library/programs").json() == []


def test_another_client_library_uploads_and_prints_with_a_machine_scoped_key(
        live: LiveServer, queue_settings, tmp_path: Path) -> None:
    """octoclient (from the package index) keeps only the host too, and sends `print` as a
    form field: the upload is approved (the machine asks for no approval) and sent."""
    python = venv_with("octoclient", "octoclient==0.2.dev1")
    part = tmp_path / "BRACKET.gcode"
    part.write_bytes(PROGRAM)
    script = ("import json\nfrom octoclient import OctoClient\n"
              f"client = OctoClient(url={live.url!r}, apikey={API_KEY + '@1016'!r})\n"
              f"print(json.dumps(client.upload({str(part)!r}, print=True)))\n")

    done = subprocess.run([str(python), "-c", script], capture_output=True, text=True,
                          timeout=120)

    assert done.returncode == 0, done.stdout + done.stderr
    assert '"effectivePrint": true' in done.stdout
    [version] = library_versions(live, "uploads/BRACKET.gcode")
    assert version["state"] == "approved"
    landed = on_machine(queue_settings, "1016", "BRACKET.gcode")
    wait_until(lambda: landed.exists() and landed.read_bytes() == PROGRAM)


def _followed(answer, get) -> tuple[str, dict, dict]:
    """An upload's answered path, and what its `Location` and `refs.resource` lead to."""
    told = answer.json()["files"]["local"]
    at_location = get(answer.headers["location"]).json()
    return told["path"], at_location, get(told["refs"]["resource"]).json()


def test_an_uploads_location_and_resource_lead_to_its_entry_in_the_listing_as_octoprints_do(
        client, add_machines, octoprint_server: OctoPrintServer) -> None:
    """A client that follows the upload's `Location` (or `refs.resource`) finds the file's
    entry, of the path the answer and the listing give it, no longer the library program."""
    import httpx

    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})
    upload = {"files": {"file": ("PART.gcode", PROGRAM)}, "data": {"path": "CAM"}}
    with httpx.Client(base_url=octoprint_server.url, timeout=HTTP_TIMEOUT_S,
                      headers={"X-Api-Key": octoprint_server.api_key}) as octoprint:
        try:
            theirs = _followed(octoprint.post("/api/files/local", **upload), octoprint.get)
        finally:
            empty_octoprint(octoprint_server)

    sent = client.post("/machines/1016/api/files/local", **upload)
    ours = _followed(sent, client.get)

    for path, at_location, at_resource in (theirs, ours):
        assert path == "CAM/PART.gcode"
        assert at_location == at_resource
        assert (at_location["path"], at_location["name"]) == (path, "PART.gcode")
    listed = client.get("/machines/1016/api/files/local").json()["files"]
    assert [f["path"] for f in listed] == ["CAM/PART.gcode"]
    assert sent.headers["location"] == (
        "http://testserver/machines/1016/api/files/local/CAM/PART.gcode")


def test_an_upload_to_the_host_alone_is_located_with_the_machine_it_named(
        client, add_machines) -> None:
    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})

    sent = client.post("/api/files/local", params={"machineID": "1016"},
                       files={"file": ("PART.gcode", PROGRAM)}, data={"path": "CAM"})

    location = sent.headers["location"]
    assert location == "http://testserver/api/files/local/CAM/PART.gcode?machineID=1016"
    assert client.get(location).json()["path"] == "CAM/PART.gcode"


@pytest.mark.parametrize(("file_name", "form", "landed"), [
    ("CAM/PART.gcode", {}, "CAM/PART.gcode"),
    ("CAM/5AX/PART.gcode", {}, "CAM/5AX/PART.gcode"),
    ("CAM/PART.gcode", {"path": "FIXTURE"}, "FIXTURE/PART.gcode"),
    ("CAM/PART.gcode", {"filename": "OP20.gcode"}, "CAM/OP20.gcode"),
    ("CAM/PART.gcode", {"path": "FIXTURE", "filename": "OP20.gcode"}, "FIXTURE/OP20.gcode"),
], ids=["name's folder", "name's folders", "path over the name's folder",
        "filename over the name", "path and filename"])
def test_an_upload_lands_in_the_folder_its_name_gives_as_octoprint_makes_it(
        client, add_machines, octoprint_server: OctoPrintServer, file_name, form, landed
        ) -> None:
    """No longer kept as `uploads/PART.gcode`, its folders dropped: a library folder is the
    local folder OctoPrint would make, and the file is listed in it."""
    import httpx

    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})
    upload = {"files": {"file": (file_name, PROGRAM)}, "data": form}
    try:
        theirs = httpx.post(f"{octoprint_server.url}/api/files/local", **upload,
                            headers={"X-Api-Key": octoprint_server.api_key},
                            timeout=HTTP_TIMEOUT_S)
    finally:
        empty_octoprint(octoprint_server)

    ours = client.post("/machines/1016/api/files/local", **upload)

    assert (theirs.status_code, ours.status_code) == (201, 201)
    assert theirs.json()["files"]["local"]["path"] == ours.json()["files"]["local"]["path"]
    assert ours.json()["files"]["local"]["path"] == landed
    assert client.get(f"/api/library/content/{landed}").content == PROGRAM
    listed = client.get("/machines/1016/api/files/local").json()["files"]
    assert [f["path"] for f in listed] == [landed]


def test_an_upload_with_no_overwrite_over_a_kept_program_is_refused_409_as_octoprint_does(
        client, add_machines, octoprint_server: OctoPrintServer) -> None:
    """OctoPrint's `noOverwrite` refuses a file that is there; dncq refuses the program's
    next version the same way, and keeps the first, no longer adding the second."""
    import httpx

    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})
    first = {"files": {"file": ("PART.gcode", PROGRAM)}, "data": {"path": "CAM"}}
    again = {"files": {"file": ("PART.gcode", PROGRAM + b"M2\n")},
             "data": {"path": "CAM", "noOverwrite": "true"}}
    with httpx.Client(base_url=octoprint_server.url, timeout=HTTP_TIMEOUT_S,
                      headers={"X-Api-Key": octoprint_server.api_key}) as octoprint:
        try:
            octoprint.post("/api/files/local", **first).raise_for_status()
            theirs = octoprint.post("/api/files/local", **again)
        finally:
            empty_octoprint(octoprint_server)
    client.post("/machines/1016/api/files/local", **first).raise_for_status()

    ours = client.post("/machines/1016/api/files/local", **again)

    assert (theirs.status_code, ours.status_code) == (409, 409)
    assert ours.json()["errorCode"] == 142 and "noOverwrite" in ours.json()["statusMsg"]
    assert [v["version"] for v in client.get("/api/library/history/CAM/PART.gcode").json()] == [1]
    assert client.get("/api/library/content/CAM/PART.gcode").content == PROGRAM
    elsewhere = {"files": again["files"], "data": {**again["data"], "path": "OLD"}}
    assert client.post("/machines/1016/api/files/local", **elsewhere).status_code == 201


@pytest.mark.parametrize("url", ["/machines/1016/api/files/local",
                                 "/api/files/local?machineID=1016"])
def test_an_upload_larger_than_a_json_body_is_taken_up_to_the_stream_limit(
        settings, add_machines, url) -> None:
    """A CAM program is often larger than the 20 MB a JSON body may be, and OctoPrint takes
    one of up to 1 GB: the upload is a stream, with the stream limit, no longer the
    JSON one."""
    from fastapi.testclient import TestClient

    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})
    limits = settings.model_copy(update={"max_json_body_bytes": 64 * 1024,
                                         "max_stream_body_bytes": 1024 * 1024})
    large = b"G1 X10.000 Y20.000 Z-1.000 F300\n" * 8192  # 256 KB
    too_large = large * 5

    with TestClient(create_app(limits), headers={"X-Api-Key": API_KEY}) as client:
        taken = client.post(url, files={"file": ("SURFACE.nc", large)}, data={"path": "CAM"})
        refused = client.post(url, files={"file": ("HUGE.nc", too_large)}, data={"path": "CAM"})
        kept = client.get("/api/library/content/CAM/SURFACE.nc").content

    assert taken.status_code == 201 and kept == large
    assert refused.status_code == 413 and refused.json()["errorCode"] == 20013


def test_an_upload_too_large_for_a_send_job_is_kept_and_answered_not_printed(
        client, add_machines, settings, monkeypatch) -> None:
    """A send job holds its payload whole; a larger upload is kept in the library and not
    sent, as a send job of it is refused, and the answer says it did not print."""
    from jobs.api import library_send

    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})
    monkeypatch.setattr(library_send, "SEND_MAX_BYTES", len(PROGRAM) - 1)

    sent = client.post("/machines/1016/api/files/local", files={"file": ("PART.gcode", PROGRAM)},
                       data={"path": "CAM", "print": "true"})

    assert sent.status_code == 201
    assert (sent.json()["effectivePrint"], sent.json()["dncq"]["job"]) == (False, None)
    assert client.get("/api/library/content/CAM/PART.gcode").content == PROGRAM
    assert client.get("/api/jobs").json() == []


def test_an_uploads_filename_with_a_folder_is_refused_as_octoprint_does(
        client, add_machines, octoprint_server: OctoPrintServer) -> None:
    import httpx

    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})
    upload = {"files": {"file": ("PART.gcode", PROGRAM)}, "data": {"filename": "CAM/OP20.gcode"}}
    try:
        theirs = httpx.post(f"{octoprint_server.url}/api/files/local", **upload,
                            headers={"X-Api-Key": octoprint_server.api_key},
                            timeout=HTTP_TIMEOUT_S)
    finally:
        empty_octoprint(octoprint_server)

    ours = client.post("/machines/1016/api/files/local", **upload)

    assert (theirs.status_code, ours.status_code) == (400, 400)
    assert ours.json()["errorCode"] == 20001 and "filename" in ours.json()["statusMsg"]
    assert client.get("/api/library/programs").json() == []


@pytest.mark.parametrize(("value", "taken"), [
    ("true", True), ("TRUE", True), ("yes", True), ("Y", True), ("y", True), ("1", True),
    ("false", False), ("on", False), ("0", False), (" true", False)])
def test_select_is_taken_as_octoprint_takes_a_boolean(client, add_machines, value, taken) -> None:
    """OctoPrint's `valid_boolean_trues`: true, yes, y and 1 in any case, nothing else."""
    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})

    sent = client.post("/machines/1016/api/files/local", files={"file": ("PART.gcode", PROGRAM)},
                       data={"select": value})

    assert sent.status_code == 201
    assert (sent.json()["effectiveSelect"], sent.json()["dncq"]["job"] is not None) \
        == (taken, taken)


def test_an_upload_with_userdata_is_refused_saying_dncq_does_not_keep_it(
        client, add_machines) -> None:
    """OctoPrint keeps `userdata` with the file and lists it; dncq would drop it unseen."""
    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})

    sent = client.post("/machines/1016/api/files/local", files={"file": ("PART.gcode", PROGRAM)},
                       data={"userdata": '{"slicer": "cam-post"}'})

    assert sent.status_code == 400
    assert sent.json()["errorCode"] == 20001 and "userdata" in sent.json()["statusMsg"]
    assert client.get("/api/library/programs").json() == []
