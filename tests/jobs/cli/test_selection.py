"""Typos in `--to` and `--tag` are caught before anything is queued, and named; a typo in a
list's `--machine` is refused naming the machine meant, not listed as nothing."""

from __future__ import annotations

import pytest
from sqlalchemy import func, select

from jobs import db
from jobs.backup_models import Backup
from jobs.models import Job
from tests.jobs.cli.runner import PROGRAM, dncq
from tests.jobs.helpers import on_machine


def count(settings, table) -> int:
    with db.session_scope(settings.resolved_database_url) as session:
        return int(session.scalar(select(func.count()).select_from(table)) or 0)


def test_send_to_an_unknown_id_names_it_and_queues_nothing(live_with_worker, queue_settings,
                                                           program):
    result = dncq("send", str(program), "--to", "m0,m9", "--wait")

    assert result.exit_code == 1
    assert "no machine m9" in result.output and "--anyway" in result.output
    assert count(queue_settings, Job) == 0
    assert not on_machine(queue_settings, "m0", "P.nc").exists()


def test_send_to_an_unknown_tag_names_the_tag_and_the_one_meant(live_with_worker,
                                                                queue_settings, program):
    result = dncq("send", str(program), "--tag", "lathe")

    assert result.exit_code == 1
    assert "no machine tagged lathe (did you mean lathes?)" in result.output
    assert count(queue_settings, Job) == 0


def test_backup_run_of_an_unknown_machine_stores_no_backup(live_with_worker, queue_settings):
    result = dncq("backup", "run", "--to", "1099")

    assert result.exit_code == 1
    assert "no machine 1099" in result.output
    assert (count(queue_settings, Job), count(queue_settings, Backup)) == (0, 0)


def test_send_anyway_goes_to_the_machines_that_are_there(live_with_worker, queue_settings,
                                                         program):
    result = dncq("send", str(program), "--to", "m0,m9", "--anyway", "--wait")

    assert result.exit_code == 1, result.output  # the unknown one fails as its own target
    assert on_machine(queue_settings, "m0", "P.nc").read_text() == PROGRAM
    assert "10003" in result.output


def test_dry_run_shows_the_unknown_ids_and_tags(live_with_worker, queue_settings, program):
    result = dncq("send", str(program), "--to", "m0,m9", "--tag", "lathe", "--dry-run")

    assert result.exit_code == 0, result.output
    assert "Not there: no machine m9; no machine tagged lathe" in result.output
    assert count(queue_settings, Job) == 0


def test_backup_dry_run_names_an_unknown_machine_and_stores_nothing(live_with_worker,
                                                                    queue_settings):
    result = dncq("backup", "run", "--to", "m0,1099", "--dry-run")

    assert result.exit_code == 0, result.output
    assert "Not there: no machine 1099" in result.output
    assert (count(queue_settings, Job), count(queue_settings, Backup)) == (0, 0)


@pytest.mark.parametrize("args", [("jobs",), ("runs",), ("inbox", "list"),
                                  ("library", "assignments")], ids=" ".join)
def test_a_list_of_a_mistyped_machine_is_refused_naming_the_machine_meant(
        elsewhere, add_machines, args):
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})

    result = dncq(*args, "--machine", "1O10")  # a letter O for the 0

    assert result.exit_code == 1, result.output
    assert "Invalid MachineID (1O10) (did you mean 1010?)" in " ".join(result.output.split())
