"""A machine's request settings and `requests test` through the API and the CLI, and the
request jobs in `dncq jobs --kind request`."""

from __future__ import annotations

from pathlib import Path

import pytest

from jobs import job_views, service
from jobs.db import session_scope
from jobs.fleet import door, fleet_file, registry
from jobs.models import JobKind
from jobs.requests import drop
from jobs.settings import Settings
from tests.jobs.cli.runner import dncq, table_rows
from tests.jobs.requests.conftest import O0010, SEED_REQUEST

FANUC_ON_RS232 = {"id": "2002", "name": "RS232-J", "model": "Fanuc 0i-F", "transport": "serial",
                  "options": {"url": "socket://127.0.0.1:9"}}


def test_a_machine_shows_its_controllers_preset_until_given_its_own(client, add_machines) -> None:
    add_machines(FANUC_ON_RS232)
    shown = client.get("/api/machines/2002/requests").json()
    assert shown["given"] is None
    assert shown["settings"]["enabled"] is False
    assert shown["settings"]["request_program"] == "O8888"
    assert shown["settings"]["switch_window_s"] == 180.0


def test_settings_put_over_the_preset_are_kept_and_shown_with_the_machine(
        client, add_machines) -> None:
    add_machines(FANUC_ON_RS232)
    answer = client.put("/api/machines/2002/requests",
                        json={"enabled": True, "sources": ["library:NC", "library:OLD"],
                              "switch_window_s": 60})
    assert answer.status_code == 200, answer.text
    assert answer.json()["settings"]["sources"] == ["library:NC", "library:OLD"]
    assert answer.json()["settings"]["request_program"] == "O8888"  # the preset's still
    machine = client.get("/api/machines/2002").json()
    assert machine["requests"] == {"enabled": True, "sources": ["library:NC", "library:OLD"],
                                   "switch_window_s": 60}


@pytest.mark.parametrize(("given", "said"), [
    ({"patterns": ["(PRG)"]}, "patterns"),
    ({"switch_window_s": 0}, "switch_window_s"),
    ({"sources": ["ftp://x"]}, "sources"),
    ({"no_such_setting": 1}, "no_such_setting"),
])
def test_bad_settings_are_refused_with_what_is_wrong_and_nothing_is_kept(
        client, add_machines, given, said) -> None:
    add_machines(FANUC_ON_RS232)
    answer = client.put("/api/machines/2002/requests", json=given)
    assert answer.status_code == 422 and said in answer.text
    assert client.get("/api/machines/2002/requests").json()["given"] is None


def test_the_settings_of_an_unknown_machine_are_a_404(client) -> None:
    assert client.get("/api/machines/nope/requests").status_code == 404
    assert client.put("/api/machines/nope/requests", json={"enabled": True}).status_code == 404


def test_a_fleet_file_with_bad_request_settings_is_refused(settings) -> None:
    entry = {**FANUC_ON_RS232, "requests": {"enabled": True, "patterns": ["(unclosed"]}}
    with session_scope(settings.resolved_database_url) as session, \
            pytest.raises(ValueError, match="patterns"):
        fleet_file.import_fleet(session=session,
                                machines=[registry.MachineIn.model_validate(entry)],
                                data_dir=settings.data_dir)


def test_requests_test_shows_what_the_seeds_example_triggers_and_does_nothing(
        client, add_machines) -> None:
    add_machines({**FANUC_ON_RS232, "requests": {"enabled": True}})
    rows = client.post("/api/machines/2002/requests/test",
                       json={"text": SEED_REQUEST.decode()}).json()["rows"]
    assert [(r["command"], r["action"]) for r in rows] == [("DIR", "set_path"), ("PRG", "send")]
    assert (rows[1]["folder"], rows[1]["file"]) == ("VIPROS", "0010")
    assert client.get("/api/jobs", params={"kind": "request"}).json() == []


def test_dncq_requests_test_prints_the_rows_of_a_file(elsewhere, add_machines,
                                                      tmp_path: Path) -> None:
    add_machines({**FANUC_ON_RS232, "requests": {"enabled": True}})
    asked = tmp_path / "O8888.NC"
    asked.write_bytes(SEED_REQUEST)
    result = dncq("requests", "test", "2002", str(asked), width=200)
    assert result.exit_code == 0, result.output
    assert "set_path" in result.output and "send" in result.output and "0010" in result.output


def test_dncq_requests_test_on_a_machine_whose_requests_are_off_says_so_and_how_to_turn_them_on(
        elsewhere, add_machines, tmp_path: Path) -> None:
    # It printed the rows alone, as if the machine's request would run.
    add_machines(FANUC_ON_RS232)  # the preset's `enabled: false`
    asked = tmp_path / "O8888.NC"
    asked.write_bytes(SEED_REQUEST)

    result = dncq("requests", "test", "2002", str(asked), width=200)

    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())
    assert "requests are off on machine 2002 (enabled: false): what it sends triggers " \
        "none of this" in said
    assert "enabled: true" in said and "dncq requests set 2002" in said
    assert "set_path" in result.output  # what it would trigger once on


def test_requests_test_answers_whether_the_machines_requests_are_on(
        client, add_machines) -> None:
    add_machines(FANUC_ON_RS232, {**FANUC_ON_RS232, "id": "2003", "requests": {"enabled": True}})

    answers = {m: client.post(f"/api/machines/{m}/requests/test",
                              json={"text": SEED_REQUEST.decode()}).json()
               for m in ("2002", "2003")}

    assert {m: a["enabled"] for m, a in answers.items()} == {"2002": False, "2003": True}


def test_dncq_requests_set_then_show(elsewhere, add_machines, tmp_path: Path) -> None:
    add_machines(FANUC_ON_RS232)
    given = tmp_path / "requests.yaml"
    given.write_text("enabled: true\nsources: [\"library:NC\"]\n")
    result = dncq("requests", "set", "2002", str(given))
    assert result.exit_code == 0 and "requests on" in result.output, result.output
    shown = dncq("requests", "show", "2002")
    assert "library:NC" in shown.output and "O8888" in shown.output


def test_dncq_jobs_kind_request_lists_what_machines_sent(
        elsewhere, settings: Settings, add_machines, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    [spec] = add_machines({"id": "m1", "name": "M1", "model": "Mock",
                           "requests": {"enabled": True, "drop_folder": "/requests"}})
    with door.open_files(spec, data_dir=settings.data_dir) as files:
        files.make_dir("requests", "/", None)
        files.send_chunks(files.ref("O8888", "/requests", None), iter([SEED_REQUEST]))
    assert drop.scan_machine(settings=settings, spec=spec) == 1

    result = dncq("jobs", "--kind", "request", width=200)  # every column shown whole
    assert result.exit_code == 0, result.output
    [row] = table_rows(result.output)
    assert (row["kind"], row["state"], row["file"]) == ("request", "succeeded", "O8888")
    shown = dncq("job", row["id"], width=200)
    assert "send" in shown.output and "VIPROS/0010" in shown.output and "O0010" in shown.output
    with session_scope(settings.resolved_database_url) as session:
        [job] = service.list_jobs(session=session, kind=JobKind.REQUEST)
        view = job_views.view(session=session, job=job)
    assert view["received"] == SEED_REQUEST.decode() and view["createdBy"].startswith(
        "machine:m1")
