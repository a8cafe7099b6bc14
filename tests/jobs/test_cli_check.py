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
