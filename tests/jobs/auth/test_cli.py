"""`dncq users`, `dncq keys` and `dncq audit` against a live API, with the admin key."""

from __future__ import annotations

import csv
import io
import os
import subprocess
import sys

from jobs.settings import get_settings
from tests.jobs.cli.runner import dncq, table_rows


def test_users_are_added_listed_changed_and_removed(elsewhere, add_machines) -> None:
    add_machines(*({"id": m, "name": m, "model": "Mock"} for m in ("1010", "1011")))
    added = dncq("users", "add", "alice", "--role", "operator", "--machines", "1010,1011",
                 "--password-stdin", answer="a long password\n")
    listed = dncq("users", "list")
    changed = dncq("users", "set", "alice", "--role", "programmer", "--machines", "all",
                   "--disable")
    removed = dncq("users", "rm", "alice")

    assert added.exit_code == 0, added.output
    assert "User alice: operator, machines 1010, 1011." in added.output
    assert "alice" in listed.output and "operator" in listed.output
    assert "User alice: programmer, machines all, disabled." in changed.output
    assert removed.exit_code == 0 and "alice" not in dncq("users", "list").output


def test_ls_still_lists_users_and_keys_as_list_does(elsewhere) -> None:
    dncq("users", "add", "carol", "--role", "viewer", "--password-stdin",
         answer="a long password\n")

    assert dncq("users", "ls").output == dncq("users", "list").output
    assert "carol" in dncq("users", "ls").output
    assert dncq("keys", "ls").output == dncq("keys", "list").output


def test_a_password_is_asked_twice_and_never_printed(elsewhere) -> None:
    added = dncq("users", "add", "bob", "--role", "viewer",
                 answer="typed secret 1\ntyped secret 1\n")

    assert added.exit_code == 0, added.output
    assert "typed secret 1" not in added.output


def test_a_password_typed_differently_the_second_time_is_asked_again(elsewhere) -> None:
    added = dncq("users", "add", "bob", "--role", "viewer",
                 answer="typed secret 1\ntyped secret 2\ntyped secret 3\ntyped secret 3\n")

    assert added.exit_code == 0, added.output
    assert "do not match" in added.output


def test_a_key_is_printed_once_and_listed_by_its_first_characters(elsewhere) -> None:
    made = dncq("keys", "add", "robot", "--role", "viewer")
    key = made.stdout.strip().splitlines()[-1]
    listed = dncq("keys", "list")

    assert made.exit_code == 0, made.output
    assert key.startswith("dncq_")
    assert key[:12] in listed.output and key not in listed.output


def test_the_cli_with_a_named_key_acts_with_its_role(elsewhere, monkeypatch) -> None:
    key = dncq("keys", "add", "robot", "--role", "viewer").stdout.strip().splitlines()[-1]
    monkeypatch.setenv("DNCQ_API_KEY", key)
    get_settings.cache_clear()

    reads = dncq("machines", "list")
    refused = dncq("users", "list")

    assert reads.exit_code == 0, reads.output
    assert refused.exit_code == 1
    assert "this needs the admin role; you (key:robot) are a viewer" in refused.output


def test_a_revoked_key_is_refused(elsewhere, monkeypatch) -> None:
    key = dncq("keys", "add", "robot", "--role", "viewer").stdout.strip().splitlines()[-1]
    assert dncq("keys", "revoke", "robot").exit_code == 0
    monkeypatch.setenv("DNCQ_API_KEY", key)
    get_settings.cache_clear()

    refused = dncq("machines", "list")

    assert refused.exit_code == 1 and "20403" in refused.output


def test_audit_lists_filters_and_exports_what_was_done(elsewhere) -> None:
    dncq("keys", "add", "robot", "--role", "viewer")
    dncq("users", "add", "carol", "--role", "viewer", "--password-stdin",
         answer="a long password\n")

    shown = dncq("audit")
    keys_only = dncq("audit", "--action", "keys", "--who", "admin-key")
    exported = dncq("audit", "--csv")

    assert shown.exit_code == 0, shown.output
    assert "users.add" in shown.output and "keys.add" in shown.output
    assert "127.0.0.1" in shown.output
    assert "keys.add" in keys_only.output and "users.add" not in keys_only.output
    rows = list(csv.DictReader(io.StringIO(exported.stdout)))
    assert [r["action"] for r in rows] == ["users.add", "keys.add"]
    assert "a long password" not in exported.stdout


def test_audit_csv_exports_every_event_the_table_the_last_100(elsewhere, settings) -> None:
    from jobs import db
    from jobs.auth.models import AuditEvent

    with db.session_scope(settings.resolved_database_url) as session:
        session.add_all(AuditEvent(who="admin-key", kind="admin-key", role="admin",
                                   method="PUT", path=f"/api/machines/m{i}", status=200,
                                   action="machines.put", target=f"m{i}") for i in range(150))

    exported = dncq("audit", "--csv")
    some = dncq("audit", "--csv", "--limit", "20")
    shown = dncq("audit", width=200)

    assert len(list(csv.DictReader(io.StringIO(exported.stdout)))) == 150
    assert len(list(csv.DictReader(io.StringIO(some.stdout)))) == 20
    assert len(table_rows(shown.output)) == 100


def test_audit_prune_removes_old_events_keeps_recent_ones_and_records_itself(env,
                                                                             settings) -> None:
    from datetime import timedelta

    from sqlalchemy import update

    from jobs import db
    from jobs.auth.models import AuditEvent
    from jobs.models import utcnow

    url = settings.resolved_database_url
    db.upgrade(url)
    with db.session_scope(url) as session:
        for days_ago, action in ((500, "machines.put"), (10, "keys.add")):
            session.add(AuditEvent(who="admin-key", kind="admin-key", role="admin",
                                   method="PUT", path="/api/x", status=200, action=action))
            session.flush()
            session.execute(update(AuditEvent).where(AuditEvent.action == action)
                            .values(at=utcnow() - timedelta(days=days_ago)))

    pruned = dncq("audit", "prune", "--older-than-days", "400")

    assert pruned.exit_code == 0, pruned.output
    assert "Pruned 1 audit events older than 400 days" in pruned.output
    with db.session_scope(url) as session:
        left = {e.action: e for e in session.query(AuditEvent)}
    assert set(left) == {"keys.add", "audit.prune"}
    assert left["audit.prune"].who.startswith("local:")
    assert left["audit.prune"].detail["removed"] == 1


def test_a_password_piped_without_password_stdin_is_refused_naming_it(tmp_path) -> None:
    # A process of its own, without a terminal: the test runner's prompt asks none.
    added = subprocess.run(
        [sys.executable, "-m", "jobs.cli", "users", "add", "bob", "--role", "viewer"],
        input="a long password\n", capture_output=True, text=True, start_new_session=True,
        env={**os.environ, "DNCQ_URL": "http://127.0.0.1:9", "DNCQ_DATA_DIR": str(tmp_path)},
        timeout=60)

    assert added.returncode == 2
    assert added.stderr == ("error: no terminal to type the password in: give it on stdin "
                            "with --password-stdin\n")


def test_an_admin_key_with_a_machine_list_is_refused_saying_why(elsewhere) -> None:
    made = dncq("keys", "add", "robot", "--role", "admin", "--machines", "1010")

    assert made.exit_code == 1
    assert "an admin may change every machine: give it no machine list" in made.output
    assert "robot" not in dncq("keys", "list").output


def test_a_machine_list_naming_an_unknown_machine_is_refused_naming_it(
        elsewhere, add_machines) -> None:
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})

    made = dncq("keys", "add", "robot", "--role", "operator", "--machines", "1010,1O11")
    added = dncq("users", "add", "alice", "--role", "operator", "--machines", "1O11",
                 "--password-stdin", answer="a long password\n")

    assert (made.exit_code, added.exit_code) == (1, 1)
    assert ("no machine has the id 1O11 (dncq machines list and the dashboard's fleet show "
            "the ids)") in " ".join(made.output.split())
    two = dncq("keys", "add", "robot", "--role", "operator", "--machines", "1O11,10\n12")
    assert "no machine has the ids 1O11, '10\\n12'" in " ".join(two.output.split())
    assert "no machine has the id 1O11" in added.output
    assert "robot" not in dncq("keys", "list").output
    assert "alice" not in dncq("users", "list").output


def test_a_key_or_schedule_naming_a_look_alike_of_a_machine_is_refused_naming_that_machine(
        elsewhere, add_machines) -> None:
    add_machines({"id": "1001", "name": "Lathe", "model": "Mock"})

    key = dncq("keys", "add", "robot", "--role", "operator", "--machines", "1O01")
    schedule = dncq("schedule", "add", "nightly", "--cron", "0 2 * * *", "--to", "1O01")

    assert (key.exit_code, schedule.exit_code) == (1, 1)
    assert "no machine has the id 1O01 (did you mean 1001?)" in " ".join(key.output.split())
    assert "no machine 1O01 (did you mean 1001?)" in " ".join(schedule.output.split())
    assert "robot" not in dncq("keys", "list").output
    assert "nightly" not in dncq("schedule", "list").output


def test_making_a_user_with_a_machine_list_an_admin_is_refused_naming_how(
        elsewhere, add_machines) -> None:
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})
    dncq("users", "add", "alice", "--role", "operator", "--machines", "1010",
         "--password-stdin", answer="a long password\n")

    refused = dncq("users", "set", "alice", "--role", "admin")
    promoted = dncq("users", "set", "alice", "--role", "admin", "--machines", "all")

    assert refused.exit_code == 1
    assert ("user alice has a machine list, which an admin takes none of (it would limit "
            "nothing): clear it in the same change, with --machines all (in the API, "
            '"machines": null)') in " ".join(refused.output.split())
    assert "User alice: admin, machines all, enabled." in promoted.output


def test_an_empty_machine_list_is_refused_naming_how_to_allow_every_machine(
        elsewhere, add_machines) -> None:
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})
    dncq("users", "add", "bob", "--role", "operator", "--machines", "1010",
         "--password-stdin", answer="a long password\n")

    made = dncq("keys", "add", "robot", "--role", "operator", "--machines", "")
    added = dncq("users", "add", "alice", "--role", "operator", "--machines", " , ",
                 "--password-stdin", answer="a long password\n")
    changed = dncq("users", "set", "bob", "--machines", "")

    assert (made.exit_code, added.exit_code, changed.exit_code) == (1, 1, 1)
    for refused in (made, added, changed):
        assert ("a machine list names no machine (it would allow none): name its machines, or "
                'give --machines all for every machine (in the API, "machines": null)'
                ) in " ".join(refused.output.split())
    assert "robot" not in dncq("keys", "list").output
    assert "alice" not in dncq("users", "list").output
    assert table_rows(dncq("users", "list").output)[0]["machines"] == "1010"
