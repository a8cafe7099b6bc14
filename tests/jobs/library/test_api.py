"""The library's HTTP API: uploads streamed in, versions, decisions, assignments, errors."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from jobs.library import blobs

V1 = b"%\nO0010\nG0 X0\nM30\n%\n"
V2 = b"%\nO0010\nG0 X0\nG1 X10 F200\nM30\n%\n"
RAW = {"content-type": "application/octet-stream"}


def _add(client, data: bytes, path: str = "VIPROS/0010", **params):
    folder, _, name = path.rpartition("/")
    return client.post("/api/library/programs", content=data, headers=RAW,
                       params={"folder": folder, "name": name, **params})


def test_an_upload_becomes_a_version_with_its_note_and_author(client) -> None:
    answer = _add(client, V1, note="first cut", by="anna", approve="true")

    assert answer.status_code == 201
    body = answer.json()
    assert body["added"] is True
    assert {k: body["version"][k] for k in ("version", "size", "state", "note", "createdBy",
                                            "decidedBy", "source")} == {
        "version": 1, "size": len(V1), "state": "approved", "note": "first cut",
        "createdBy": "anna", "decidedBy": "anna", "source": "upload"}
    assert body["program"]["path"] == "VIPROS/0010"


def test_an_empty_upload_is_refused_with_20001_and_adds_no_version(client) -> None:
    refused = _add(client, b"", approve="true")

    assert (refused.status_code, refused.json()["errorCode"]) == (400, 20001)
    assert "empty program" in refused.json()["statusMsg"]
    assert client.get("/api/library/programs").json() == []


@pytest.mark.parametrize("door", ["library", "octoprint"])
def test_an_empty_upload_refused_leaves_no_blob(client, add_machines, settings,
                                                door: str) -> None:
    # Its empty blob stayed, named by nothing.
    add_machines({"id": "1016", "name": "Sim-G", "model": "Mock"})

    refused = _add(client, b"") if door == "library" else client.post(
        "/machines/1016/api/files/local", files={"file": ("0010", b"")}, data={"path": "CAM"})

    assert (refused.status_code, refused.json()["errorCode"]) == (400, 20001)
    assert [p for p in blobs.blob_dir(settings).rglob("*") if p.is_file()] == []


def test_the_same_bytes_twice_are_one_version_and_one_blob(client, settings) -> None:
    _add(client, V1)
    again = _add(client, V1).json()
    other = _add(client, V1, "VIPROS/OLD/0099").json()

    assert (again["added"], again["version"]["version"]) == (False, 1)
    assert other["version"]["sha256"] == again["version"]["sha256"]
    assert len([p for p in blobs.blob_dir(settings).rglob("*") if p.is_file()]) == 1


def test_list_show_history_diff_and_restore(client) -> None:
    _add(client, V1)
    _add(client, V2, "VIPROS/0010", note="finish pass")
    _add(client, V1, "LATHE/0020")

    assert [p["path"] for p in client.get("/api/library/programs").json()] == [
        "LATHE/0020", "VIPROS/0010"]
    assert [p["path"] for p in client.get("/api/library/programs",
                                          params={"folder": "VIPROS"}).json()] == ["VIPROS/0010"]
    shown = client.get("/api/library/programs/VIPROS/0010").json()
    assert [v["version"] for v in shown["versions"]] == [2, 1]
    assert shown["approved"] is None
    history = client.get("/api/library/history/VIPROS/0010").json()
    assert [(v["version"], v["note"]) for v in history] == [(2, "finish pass"), (1, "")]
    diff = client.get("/api/library/diff/VIPROS/0010", params={"old": 1, "new": 2})
    assert diff.status_code == 200 and "+G1 X10 F200\n" in diff.text

    restored = client.post("/api/library/restore/VIPROS/0010", params={"version": 1}).json()
    assert (restored["version"]["version"], restored["version"]["note"]) == (3, "restore of v1")
    assert restored["version"]["sha256"] == history[1]["sha256"]


def test_approve_reject_and_the_content_of_the_approved_version(client) -> None:
    _add(client, V1)
    _add(client, V2)

    assert client.post("/api/library/approve/VIPROS/0010", params={"version": 1}).json()[
        "version"]["state"] == "approved"
    rejected = client.post("/api/library/reject/VIPROS/0010", params={"version": 2}).json()
    assert rejected["version"]["state"] == "rejected"
    assert rejected["program"]["approved"]["version"] == 1
    content = client.get("/api/library/content/VIPROS/0010")
    assert (content.content, content.headers["x-library-version"]) == (V1, "1")
    assert client.get("/api/library/content/VIPROS/0010", params={"version": 2}).content == V2


def test_delete_keeps_the_history(client) -> None:
    _add(client, V1)

    assert client.delete("/api/library/programs/VIPROS/0010").json()["deleted"] is True
    assert client.get("/api/library/programs").json() == []
    assert [p["path"] for p in client.get("/api/library/programs",
                                          params={"deleted": "true"}).json()] == ["VIPROS/0010"]
    assert len(client.get("/api/library/history/VIPROS/0010").json()) == 1
    gone = client.delete("/api/library/programs/VIPROS/0010")
    assert (gone.status_code, gone.json()["errorCode"]) == (404, 158)


def test_assignments_give_machines_folders(client, add_machines) -> None:
    add_machines(*({"id": m, "name": m, "model": "Mock"} for m in ("1010", "1011")))
    made = client.post("/api/library/assignments",
                       json={"folder": "VIPROS", "machines": ["1010", "1011"]})

    assert [a["machineID"] for a in made.json()] == ["1010", "1011"]
    assert [a["folder"] for a in client.get("/api/library/assignments",
                                            params={"machine": "1010"}).json()] == ["VIPROS"]
    removed = client.post("/api/library/assignments/remove",
                          json={"folder": "VIPROS", "machines": ["1011"]}).json()
    assert removed["removed"] == 1


def test_assigning_to_a_machine_nobody_registered_is_404_naming_the_id_it_was_typed_for(
        client, add_machines) -> None:
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})

    refused = client.post("/api/library/assignments",
                          json={"folder": "VIPROS", "machines": ["1010", "1O10"]})

    assert (refused.status_code, refused.json()["errorCode"]) == (404, 10003)
    assert "1O10 (did you mean 1010?)" in refused.json()["statusMsg"]
    assert client.get("/api/library/assignments").json() == []


def test_bad_names_are_refused_with_20001_before_anything_is_stored(client, settings) -> None:
    for folder, name in (("../etc", "passwd"), ("/abs", "P"), ("VIPROS", "a\x01b"),
                         ("VIPROS", "..")):
        answer = client.post("/api/library/programs", content=V1, headers=RAW,
                             params={"folder": folder, "name": name})
        assert answer.status_code == 400
        assert answer.json()["errorCode"] == 20001
        assert set(answer.json()) == {"errorCode", "errorMsg", "statusMsg"}
    assert client.get("/api/library/history/VIPROS/a%07b").json()["errorCode"] == 20001
    assert not blobs.blob_dir(settings).exists() or not any(
        p.is_file() for p in blobs.blob_dir(settings).rglob("*"))


def test_a_missing_program_or_version_is_404_with_158(client) -> None:
    _add(client, V1)

    for answer in (client.get("/api/library/programs/VIPROS/NOPE"),
                   client.get("/api/library/diff/VIPROS/0010", params={"old": 1, "new": 9}),
                   client.post("/api/library/restore/VIPROS/0010", params={"version": 4})):
        assert (answer.status_code, answer.json()["errorCode"]) == (404, 158)


def test_a_version_number_no_version_can_have_is_refused_with_400(client) -> None:
    _add(client, V1)
    huge = {"version": 2**63}  # past what the database's integers hold

    for answer in (client.get("/api/library/content/VIPROS/0010", params=huge),
                   client.post("/api/library/approve/VIPROS/0010", params=huge),
                   client.post("/api/library/restore/VIPROS/0010", params=huge),
                   client.get("/api/library/diff/VIPROS/0010", params={"old": 1, "new": 2**63})):
        assert (answer.status_code, answer.json()["errorCode"]) == (400, 20001)


def test_a_broken_upload_leaves_no_blob_and_no_version(client, settings) -> None:
    def broken() -> Iterator[bytes]:
        yield b"G0 X0\n" * 1000
        raise ConnectionError("the client went away")

    try:
        client.post("/api/library/programs", content=broken(), headers=RAW,
                    params={"folder": "VIPROS", "name": "0010"})
    except ConnectionError:
        pass  # the test client re-raises the body's failure

    assert [p for p in blobs.blob_dir(settings).rglob("*") if p.is_file()] == []
    assert client.get("/api/library/programs").json() == []
