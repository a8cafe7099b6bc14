"""One rule for every command that starts a job: it follows the job to its end unless
--no-wait, and then says how to follow it."""

from __future__ import annotations

import re
from collections.abc import Callable

import pytest

from tests.jobs.cli.runner import dncq
from tests.jobs.helpers import on_machine

PROGRAM = "G0 X0\nM30\n"
RESULTS = re.compile(r"\d+ succeeded, \d+ skipped, \d+ failed, \d+ cancelled, 0 not finished")


def job_id_in(output: str) -> str:
    return re.findall(r"[Jj]ob ([0-9a-f]{16})", output)[0]


def backup_id_in(output: str) -> str:
    return re.findall(r"Backup ([0-9a-f]{16}):", output)[0]


def send(settings) -> list[str]:
    return ["send", "P.nc", "--to", "m0"]


def delete(settings) -> list[str]:
    on_machine(settings, "m0", "P.nc").write_text(PROGRAM)
    return ["delete", "P.nc", "--to", "m0"]


def backup_run(settings) -> list[str]:
    return ["backup", "run", "--to", "m0"]


def backup_restore(settings) -> list[str]:
    on_machine(settings, "m0", "B.nc").write_text(PROGRAM)
    made = dncq("backup", "run", "--to", "m0", "--wait")
    return ["backup", "restore", backup_id_in(made.output), "--machine", "m0", "--to", "m2"]


def schedule_run_now(settings) -> list[str]:
    assert dncq("schedule", "add", "nightly", "--cron", "0 2 * * *", "--to", "m0").exit_code == 0
    return ["schedule", "run-now", "nightly"]


def retry(settings) -> list[str]:
    blocker = on_machine(settings, "m1", "P.nc")
    blocker.write_text("old")
    failed = dncq("send", "P.nc", "--to", "m1", "--wait")
    blocker.unlink()
    return ["retry", job_id_in(failed.output)]


def restore_replaced(settings) -> list[str]:
    on_machine(settings, "m0", "P.nc").write_text("old")
    replaced = dncq("send", "P.nc", "--to", "m0", "--replace", "--wait")
    return ["restore-replaced", job_id_in(replaced.output)]


STARTERS: list[Callable[..., list[str]]] = [send, delete, backup_run, backup_restore,
                                            schedule_run_now, retry, restore_replaced]


@pytest.fixture
def in_folder(live_with_worker, tmp_path) -> None:
    (tmp_path / "P.nc").write_text(PROGRAM)


@pytest.mark.parametrize("command", STARTERS, ids=lambda c: c.__name__)
def test_a_command_that_starts_a_job_follows_it_to_its_end_by_default(
        in_folder, queue_settings, command):
    result = dncq(*command(queue_settings))

    assert result.exit_code == 0, result.output
    assert RESULTS.search(result.output), result.output


@pytest.mark.parametrize("command", STARTERS, ids=lambda c: c.__name__)
def test_a_command_that_starts_a_job_returns_once_it_is_queued_with_no_wait(
        in_folder, queue_settings, command):
    result = dncq(*command(queue_settings), "--no-wait")

    assert result.exit_code == 0, result.output
    assert f"Follow it with: dncq job {job_id_in(result.output)} --watch" in result.output
    assert not RESULTS.search(result.output)


def test_a_job_followed_piped_prints_its_results_alone(in_folder, queue_settings):
    # The bar, redrawn in place on a terminal, left its last frame and a blank line.
    result = dncq("send", "P.nc", "--to", "m0", "--wait")

    job_id = job_id_in(result.output)
    assert result.exit_code == 0, result.output
    assert result.output.splitlines()[:2] == [f"Job {job_id}: 1 target.",
                                              f"job {job_id} (send): succeeded"], result.output
