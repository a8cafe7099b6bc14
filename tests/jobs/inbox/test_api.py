"""The inbox's HTTP API: list, show, content, diff, approve, reject, prune, and its errors."""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import update

from jobs import db
from jobs.inbox import service as inbox
from jobs.inbox.models import InboxItem
from jobs.models import utcnow
from jobs.settings import Settings

APPROVED = b"%\nO0010 (BRACKET)\nG0 X0\nM30\n%\n"
PUNCHED = b"%\nO0010 (BRACKET)\nG0 X0\nG1 X10 F200\nM30\n%\n"
RAW = {"content-type": "application/octet-stream"}


def _receive(settings: Settings, data: bytes = PUNCHED, machine_id: str = "m1") -> int:
    with db.session_scope(settings.resolved_database_url) as session:
        return inbox.receive(session=session, settings=settings, machine_id=machine_id,
                             data=data, name=None, folder="VIPROS").id


def _failed(settings: Settings) -> int:
    with db.session_scope(settings.resolved_database_url) as session:
        return inbox.receive_failed(session=session, settings=settings, machine_id="m1",
                                    data=b"O0010\nG0 X", reason="no end mark").id


def _approve_in_library(client, data: bytes = APPROVED) -> None:
    answer = client.post("/api/library/programs", content=data, headers=RAW,
                         params={"folder": "VIPROS", "name": "O0010", "approve": "true"})
    assert answer.status_code == 201


def test_list_filters_by_machine_and_state(client, settings) -> None:
    first = _receive(settings, machine_id="m1")
    second = _receive(settings, machine_id="m2")
    failed = _failed(settings)

    assert [i["id"] for i in client.get("/api/inbox").json()] == [failed, second, first]
    assert [i["id"] for i in client.get("/api/inbox", params={"machine": "m1"}).json()] == [
        failed, first]
    assert [i["id"] for i in client.get("/api/inbox", params={"state": "failed"}).json()] == [
        failed]
    assert client.get("/api/inbox", params={"state": "lost"}).status_code == 400


def test_show_content_and_diff_against_the_approved_copy(client, settings) -> None:
    _approve_in_library(client)
    item_id = _receive(settings)

    shown = client.get(f"/api/inbox/{item_id}").json()
    assert {k: shown[k] for k in ("machineID", "name", "path", "programNumber", "comment",
                                  "state", "size", "libraryVersion")} == {
        "machineID": "m1", "name": "O0010", "path": "VIPROS/O0010", "programNumber": "O0010",
        "comment": "BRACKET", "state": "pending", "size": len(PUNCHED), "libraryVersion": None}
    assert shown["approved"]["version"] == 1
    content = client.get(f"/api/inbox/{item_id}/content")
    assert (content.content, content.headers["content-type"]) == (
        PUNCHED, "application/octet-stream")
    diff = client.get(f"/api/inbox/{item_id}/diff")
    assert diff.status_code == 200 and "+G1 X10 F200\n" in diff.text
    assert diff.text.startswith("--- VIPROS/O0010 v1 (approved)\n")


def test_approve_answers_the_new_version_and_the_program_keeps_the_previous(
        client, settings) -> None:
    _approve_in_library(client)
    item_id = _receive(settings)

    answer = client.post(f"/api/inbox/{item_id}/approve", params={"by": "anna"},
                         json={"note": "from the shop floor"})

    assert answer.status_code == 200
    body = answer.json()
    assert (body["version"]["version"], body["version"]["state"], body["version"]["note"],
            body["version"]["decidedBy"]) == (2, "approved", "from the shop floor", "anna")
    assert (body["item"]["state"], body["item"]["libraryVersion"]) == ("approved", 2)
    history = client.get("/api/library/history/VIPROS/O0010").json()
    assert [(v["version"], v["state"]) for v in history] == [(2, "approved"), (1, "approved")]
    content = client.get("/api/library/content/VIPROS/O0010")
    assert content.content == PUNCHED


def test_approve_without_a_body_and_as_another_program(client, settings) -> None:
    first, second = _receive(settings), _receive(settings, b"O0020\nM30\n")

    plain = client.post(f"/api/inbox/{first}/approve")
    moved = client.post(f"/api/inbox/{second}/approve",
                        json={"folder": "LATHE", "name": "0020"})

    assert plain.json()["program"]["path"] == "VIPROS/O0010"
    assert moved.json()["program"]["path"] == "LATHE/0020"


def test_a_received_program_leaves_the_approved_one_alone_until_approved(
        client, settings) -> None:
    _approve_in_library(client)
    _receive(settings)

    assert client.get("/api/library/content/VIPROS/O0010").content == APPROVED
    assert len(client.get("/api/library/history/VIPROS/O0010").json()) == 1


def test_reject_keeps_it_and_prune_removes_it_after_the_configured_days(
        client, settings) -> None:
    item_id = _receive(settings)

    rejected = client.post(f"/api/inbox/{item_id}/reject", json={"reason": "wrong part"})
    assert (rejected.json()["item"]["state"], rejected.json()["item"]["reason"]) == (
        "rejected", "wrong part")
    assert client.post("/api/inbox/prune").json()["pruned"] == 0
    with db.session_scope(settings.resolved_database_url) as session:
        session.execute(update(InboxItem).values(
            decided_at=utcnow() - timedelta(days=settings.inbox_rejected_keep_days + 1)))
    assert client.post("/api/inbox/prune").json()["pruned"] == 1
    assert client.get(f"/api/inbox/{item_id}").status_code == 404


def test_a_missing_item_is_404_with_the_contract_body(client) -> None:
    for answer in (client.get("/api/inbox/424242"), client.get("/api/inbox/424242/diff"),
                   client.post("/api/inbox/424242/approve")):
        assert answer.status_code == 404
        assert answer.json()["errorCode"] == 158
        assert "no inbox item 424242" in answer.json()["statusMsg"]


def test_approving_twice_or_a_failed_reception_is_409_saying_why(client, settings) -> None:
    item_id, failed = _receive(settings), _failed(settings)
    assert client.post(f"/api/inbox/{item_id}/approve").status_code == 200

    again = client.post(f"/api/inbox/{item_id}/approve")
    refused = client.post(f"/api/inbox/{failed}/approve")
    rejected = client.post(f"/api/inbox/{failed}/reject")

    # 20409, where it said 20001 Bad parameter of a request that was right when it was read
    assert (again.status_code, again.json()["errorCode"]) == (409, 20409)
    assert again.json()["errorMsg"] == "Already decided."
    assert "approved already, as VIPROS/O0010 v1" in again.json()["statusMsg"]
    assert refused.status_code == rejected.status_code == 409
    assert refused.json()["errorCode"] == rejected.json()["errorCode"] == 20001
    assert "failed reception (no end mark)" in refused.json()["statusMsg"]


def test_a_bad_folder_or_name_to_approve_as_is_400(client, settings) -> None:
    item_id = _receive(settings)

    answer = client.post(f"/api/inbox/{item_id}/approve", json={"folder": "../up"})

    assert (answer.status_code, answer.json()["errorCode"]) == (400, 20001)
    assert client.get(f"/api/inbox/{item_id}").json()["state"] == "pending"


def test_the_inbox_needs_the_api_key(client) -> None:
    assert client.get("/api/inbox", headers={"X-Api-Key": ""}).status_code == 401
