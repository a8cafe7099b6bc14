"""OctoPrint's file listing (seed 002) served per machine: fields, origins, keys, records."""

from __future__ import annotations

import json
import subprocess
from datetime import UTC, datetime, timedelta

import pytest

from jobs import db
from jobs.library.seed_listing import formatted_date, formatted_size
from jobs.models import RunState
from tests.conftest import API_KEY
from tests.jobs.helpers import ended_run, mock_file

SIZES = [0, 1, 1000, 1023, 1024, 1468987, 10**7, int(3.2 * 1024**3), 5 * 1024**4]


def test_sizes_and_dates_are_written_as_octoprint_writes_them() -> None:
    """Against OctoPrint's own formatting (octoprint.util), run in the venv the transport
    tests install it into."""
    from tests.worker.transports.octoprint_server import REQUIREMENT
    from tests.worker.transports.venvs import venv_with

    python = venv_with("octoprint", REQUIREMENT)
    when = datetime(2013, 5, 21, 23, 15)
    script = ("import datetime, json, sys\n"
              "from octoprint.util import get_formatted_size, get_formatted_datetime\n"
              f"sizes = {SIZES!r}\n"
              "print(json.dumps([[get_formatted_size(n) for n in sizes],"
              " get_formatted_datetime(datetime.datetime(2013, 5, 21, 23, 15))]))\n")
    theirs = json.loads(subprocess.run([str(python), "-c", script], check=True,
                                       capture_output=True, text=True, timeout=120).stdout)

    assert [formatted_size(n) for n in SIZES] == theirs[0]
    assert formatted_date(when.astimezone()) == theirs[1]
    assert formatted_size(1468987) == "1.4MB"  # the seed's own example


def test_the_sdcard_origin_lists_the_machines_own_files_with_the_seeds_fields(
        client, add_machines, settings) -> None:
    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})
    mock_file(settings, "1016", "SAMPLE", "G0 X0\n" * 100)
    mock_file(settings, "1016", "1/sample1.nc", "G1 X1\n")

    answer = client.get("/machines/1016/api/gcodefiles/sdcard")

    assert answer.status_code == 200
    body = answer.json()
    assert set(body) == {"files", "free"} and body["free"].endswith("B")
    by_name = {f["name"]: f for f in body["files"]}
    assert set(by_name) == {"SAMPLE", "1/sample1.nc"}
    sample = by_name["SAMPLE"]
    assert sample["origin"] == "sdcard" and sample["bytes"] == 600
    assert sample["size"] == "600.0B"
    assert datetime.strptime(sample["date"], "%Y-%m-%d %H:%M")  # the seed's format
    assert "prints" not in sample  # no run on record


def test_a_programs_runs_are_its_print_record(client, add_machines, settings) -> None:
    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})
    mock_file(settings, "1016", "SAMPLE", "G0 X0\n")
    now = datetime.now(UTC)
    with db.session_scope(settings.resolved_database_url) as session:
        for n, (state, ago) in enumerate([(RunState.SUCCEEDED, 3), (RunState.FAILED, 2),
                                          (RunState.STOPPED, 1.5), (RunState.SUCCEEDED, 1),
                                          (RunState.CANCELLED, 0.5)]):
            session.add(ended_run(f"j{n}", "1016", "SAMPLE", state,
                                  now - timedelta(hours=ago)))

    [sample] = client.get("/machines/1016/api/gcodefiles").json()["files"]

    # a run stopped on request is a failure, as OctoPrint counts a cancelled print; one
    # cancelled before it started never ran
    assert sample["prints"] == {"failure": 2, "success": 2, "last": {
        "date": formatted_date(now - timedelta(hours=1)), "success": True}}


@pytest.mark.parametrize("path", ["/machines/1016/api/gcodefiles/usb",
                                  "/api/gcodefiles/usb?machineID=1016"])
def test_an_origin_other_than_local_or_sdcard_is_400(client, add_machines, path) -> None:
    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})

    assert client.get(path).status_code == 400


def test_the_key_is_needed_and_taken_as_the_seed_sends_it(client, add_machines) -> None:
    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})
    url = "/machines/1016/api/gcodefiles"

    missing = client.get(url, headers={"X-Api-Key": ""})
    wrong = client.get(url, headers={"X-Api-Key": "not-the-key"})
    as_query = client.get(f"{url}?apikey={API_KEY}", headers={"X-Api-Key": ""})

    assert (missing.status_code, wrong.status_code, as_query.status_code) == (401, 403, 200)


def test_one_url_with_machine_id_lists_the_same_as_the_machines_prefix(
        client, add_machines, settings) -> None:
    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})
    mock_file(settings, "1016", "SAMPLE", "G0 X0\n")

    prefixed = client.get("/machines/1016/api/gcodefiles/sdcard").json()
    one_url = client.get("/api/gcodefiles/sdcard", params={"machineID": "1016"}).json()

    assert prefixed["files"] == one_url["files"]
    assert client.get("/machines/nope/api/gcodefiles").status_code == 404


def test_the_seeds_example_local_file_is_reproduced_field_for_field(
        client, add_machines, settings) -> None:
    """A prepared library version and run record that are the seed's `whistle_v2.gcode`:
    1,468,987 bytes, added 2013-05-21 23:15, analysed at 00:31:40 and 0.79 m of filament
    (790 mm extruded at F1580: 30 s, then an 18,700 mm travel at F600: 1,870 s), printed
    23 times well and 4 times not, the last on 2013-11-18 18:00, well."""
    from sqlalchemy import update

    from jobs.library.models import LibraryVersion

    add_machines({"id": "p1", "name": "Printer", "model": "Mock"})
    body = b"G21\nG90\nM82\nG92 E0\nG1 E790 F1580\nG1 X18700 F600\nM84\n"
    padding = 1468987 - len(body)
    data = body + b";" * (padding - 1) + b"\n"
    raw = {"content-type": "application/octet-stream"}
    client.post("/api/library/programs", content=data, headers=raw, params={
        "folder": "PRINTS", "name": "whistle_v2.gcode", "approve": "true"}).raise_for_status()
    client.post("/api/library/assignments",
                json={"folder": "PRINTS", "machines": ["p1"]}).raise_for_status()
    added = datetime(2013, 5, 21, 23, 15).astimezone()
    last = datetime(2013, 11, 18, 18, 0).astimezone()
    with db.session_scope(settings.resolved_database_url) as session:
        session.execute(update(LibraryVersion).values(created_at=added))
        for n in range(27):
            state = RunState.FAILED if n < 4 else RunState.SUCCEEDED
            ended = last - timedelta(days=27 - n) if n < 26 else last
            session.add(ended_run(f"j{n}", "p1", "whistle_v2.gcode", state, ended))

    answer = client.get("/machines/p1/api/gcodefiles/local", params={"apikey": API_KEY})

    assert answer.json()["files"] == [{
        "name": "whistle_v2.gcode", "bytes": 1468987, "size": "1.4MB",
        "date": "2013-05-21 23:15", "origin": "local",
        "gcodeAnalysis": {"estimatedPrintTime": "00:31:40", "filament": "0.79m"},
        "prints": {"failure": 4, "success": 23,
                   "last": {"date": "2013-11-18 18:00", "success": True}}}]


def test_a_file_whose_size_and_date_the_machine_does_not_tell_is_the_seeds_sdcard_entry(
        ) -> None:
    """The seed's `whistle_.gco`: OctoPrint's `0` and `n/a` for what is not known."""
    from jobs.library.seed_listing import ListedFile, seed_entry

    told = seed_entry(ListedFile(name="whistle_.gco", origin="sdcard"), None)

    assert told == {"name": "whistle_.gco", "bytes": 0, "size": "n/a", "date": "n/a",
                    "origin": "sdcard"}


def closed_port() -> int:
    """A loopback port nothing listens on: a connection there is refused."""
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_a_machine_that_cannot_be_reached_lists_its_local_files_as_octoprint_without_a_printer(
        client, add_machines) -> None:
    # OctoPrint lists its uploads while its printer is not connected (no sdcard files then):
    # a client asking for both origins gets the library's files, not a refusal.
    add_machines({"id": "f1", "name": "Down", "model": "FTP server", "transport": "ftp",
                  "options": {"host": "127.0.0.1", "port": closed_port(), "timeout_s": 2}})
    raw = {"content-type": "application/octet-stream"}
    client.post("/api/library/programs", content=b"G0 X0\nM30\n", headers=raw, params={
        "folder": "CAM", "name": "PART.nc", "approve": "true"}).raise_for_status()
    client.post("/api/library/assignments",
                json={"folder": "CAM", "machines": ["f1"]}).raise_for_status()

    seed_shape = client.get("/machines/f1/api/gcodefiles")
    today_shape = client.get("/machines/f1/api/files")
    sdcard_alone = client.get("/machines/f1/api/gcodefiles/sdcard")

    for answer in (seed_shape, today_shape):
        assert answer.status_code == 200
        assert [(f["name"], f["origin"]) for f in answer.json()["files"]] == [
            ("PART.nc", "local")]
        assert answer.headers["X-Dncq-Sdcard-Unreachable"].startswith(
            "20006 Connection to the machine failed. connect '127.0.0.1:")
    assert sdcard_alone.status_code == 409  # asked for the machine's files alone: it says why
    assert sdcard_alone.json()["errorCode"] == 20006


def test_a_machine_refusing_its_listing_for_good_is_not_hidden_behind_the_local_files(
        client, add_machines, settings) -> None:
    # Only a machine that cannot be reached now is left out: one whose answer makes no
    # sense and will not (a mock machine's options.json that is not JSON) is refused.
    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})
    mock_file(settings, "1016", "SAMPLE", "G0 X0\n")
    (settings.data_dir / "mock" / "1016" / "options.json").write_text("{not json")

    answer = client.get("/machines/1016/api/gcodefiles")

    assert answer.status_code == 409, answer.text
    assert answer.json()["errorCode"] == 20006 and "not JSON" in answer.json()["statusMsg"]
    assert "X-Dncq-Sdcard-Unreachable" not in answer.headers
