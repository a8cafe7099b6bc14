"""`dncq machines check`: which machines answer, how fast, and what they can do."""

from __future__ import annotations

from tests.jobs.cli_runner import dncq


def test_check_reports_reachable_and_offline_machines(env, add_machines):
    add_machines({"id": "ok1", "name": "Up", "model": "Fanuc 0i-F"},
                 {"id": "off1", "name": "Down", "model": "Mock", "options": {"offline": True}})
    result = dncq("machines", "check", "--all")
    assert result.exit_code == 1  # one machine did not answer
    lines = {line.split("│")[1].strip(): line for line in result.output.splitlines()
             if line.startswith("│") and line.split("│")[1].strip()}
    assert "yes" in lines["ok1"] and "no" in lines["off1"]


def test_check_of_one_machine_that_answers_exits_0(env, add_machines):
    add_machines({"id": "ok1", "name": "Up", "model": "Mock"})
    result = dncq("machines", "check", "ok1")
    assert result.exit_code == 0 and "yes" in result.output


def test_check_names_the_model_as_registered_and_the_row_that_governs_it(settings, add_machines):
    from jobs import db, machines

    add_machines({"id": "f18", "name": "Old", "model": "Fanuc 18i"},
                 {"id": "f0i", "name": "New", "model": "Fanuc 0i-F"})
    with db.session_scope(settings.resolved_database_url) as session:
        specs = [machines.get(session=session, machine_id=m) for m in ("f18", "f0i")]
    found = [machines.check(spec, data_dir=settings.data_dir)["model"] for spec in specs]
    assert found == ["Fanuc 18i (Fanuc (other models))", "Fanuc 0i-F"]
