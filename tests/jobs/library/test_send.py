"""A send job of a library version: it reaches the machines and says which version it sent."""

from __future__ import annotations

from tests.jobs.helpers import ended_run, wait_done

V1 = b"%\nO0010\nG0 X0\nM30\n%\n"
V2 = b"%\nO0010\nG0 X0\nG1 X10 F200\nM30\n%\n"
RAW = {"content-type": "application/octet-stream"}


def _add(client, data: bytes, **params) -> None:
    client.post("/api/library/programs", content=data, headers=RAW,
                params={"folder": "VIPROS", "name": "0010", **params}).raise_for_status()


def _machines(add_machines) -> None:
    add_machines(*[{"id": f"m{i}", "name": f"M{i}", "model": "Mock", "tags": ["lathes"]}
                   for i in range(2)])


def _on(settings, machine: str, name: str = "0010") -> bytes:
    return (settings.data_dir / "mock" / machine / "files" / name).read_bytes()


def test_a_send_of_the_approved_version_reaches_the_machines_and_names_it(
        queue_client, add_machines, queue_settings) -> None:
    _machines(add_machines)
    _add(queue_client, V1, approve="true")
    _add(queue_client, V2)  # pending: not what goes out by default

    answer = queue_client.post("/api/jobs", json={
        "kind": "send", "library": "VIPROS/0010", "machines": {"tags": ["lathes"]}})
    assert answer.status_code == 202, answer.text
    job = wait_done(queue_client, answer.json()["id"])

    assert job["state"] == "succeeded"
    assert job["library"] == {"path": "VIPROS/0010", "version": 1,
                              "sha256": job["library"]["sha256"], "state": "approved"}
    assert [_on(queue_settings, m) for m in ("m0", "m1")] == [V1, V1]


def test_a_pending_version_goes_out_when_asked_for_by_number(
        queue_client, add_machines, queue_settings) -> None:
    _machines(add_machines)
    _add(queue_client, V1)
    _add(queue_client, V2)

    answer = queue_client.post("/api/jobs", json={
        "kind": "send", "library": "VIPROS/0010", "library_version": 2, "fileName": "P.NC",
        "machines": {"ids": ["m0"]}})
    job = wait_done(queue_client, answer.json()["id"])

    assert (job["state"], job["library"]["version"]) == ("succeeded", 2)
    assert _on(queue_settings, "m0", "P.NC") == V2


def test_a_send_of_a_program_with_no_approved_version_is_refused(
        queue_client, add_machines) -> None:
    _machines(add_machines)
    _add(queue_client, V1)

    for library in ("VIPROS/0010", "VIPROS/NOPE", "../x/0010"):
        answer = queue_client.post("/api/jobs", json={
            "kind": "send", "library": library, "machines": {"ids": ["m0"]}})
        assert answer.status_code in (400, 404)
        assert answer.json()["errorCode"] in (20001, 158)
    assert queue_client.get("/api/jobs").json() == []


def test_a_program_shows_its_analysis_and_its_sends_apart_from_its_runs(
        queue_client, add_machines, queue_settings) -> None:
    from datetime import UTC, datetime

    from jobs import db
    from jobs.models import RunState

    _machines(add_machines)
    _add(queue_client, V2, approve="true")
    job = queue_client.post("/api/jobs", json={"kind": "send", "library": "VIPROS/0010",
                                               "machines": {"ids": ["m0"]}}).json()
    wait_done(queue_client, job["id"])
    now = datetime.now(UTC)
    with db.session_scope(queue_settings.resolved_database_url) as session:
        session.add(ended_run("r1", "m1", "0010", RunState.SUCCEEDED, now, lines=6))

    shown = queue_client.get("/api/library/programs/VIPROS/0010").json()

    assert shown["analysis"]["programNumber"] == "O0010"
    assert shown["analysis"]["cycleTimeS"] == 3.0  # 10 mm at F200
    assert shown["sends"] == {"m0": 1}  # a send is not a run
    assert shown["runs"]["m1"]["success"] == 1 and shown["runs"]["m1"]["last"]["success"]
    assert "m0" not in shown["runs"]
