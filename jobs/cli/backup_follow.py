"""How a command follows a backup job: the job's progress and results, then the verdict of
the stored backup it made (its ZIP's name, status, files and bytes, or why none was stored)."""

from __future__ import annotations

import time
from typing import Any

import typer

from jobs.cli.common import api_call, counted, err, fail, out, segment
from jobs.cli.job_follow import follow, started


def follow_backup(job_id: str, wait: bool) -> None:
    """`started` for a backup job: once it ends, also the stored backup it made, whose
    status is the one verdict shown (the job's `failed` is a `partial` backup)."""
    if not wait:
        started(job_id, wait)
        return
    try:
        follow(job_id, state_in_title=False)
    except typer.Exit as exc:
        if exc.exit_code == 1:  # some machines failed; the others are in the backup
            _show_backup_of(job_id)
        raise
    _show_backup_of(job_id)


def _show_backup_of(job_id: str) -> None:
    """The stored backup the job made, once registered (the ZIP is assembled right after
    the last machine; the API answers the moment it is, or that none will be); exit 1 when
    the job says its ZIP could not be written."""
    try:
        _wait_for_backup_of(job_id)
    except KeyboardInterrupt:
        # The ZIP is assembled by dncq, whoever waits for it: a Ctrl-C here ended on a bare
        # ^C, below a table of machines that had all succeeded.
        err.print(f"\nStopped waiting for the backup's ZIP; dncq stores it all the same: dncq "
                  f"backup list shows it, and dncq job {job_id} --watch waits for it again.",
                  highlight=False)
        raise typer.Exit(130) from None


def _wait_for_backup_of(job_id: str) -> None:
    """Say the job's stored backup once registered, or why none will be (exit 1)."""
    deadline = time.monotonic() + BACKUP_WAIT_S
    while (left_s := deadline - time.monotonic()) > 0:
        found = api_call("GET", "/api/backups",
                         params={"job": job_id, "wait_s": min(left_s, WAIT_STEP_S)})
        if found:
            b = found[0]
            out.print(f"Backup {b['id']}: {b['name']}, {_verdict(b)}, "
                      f"{counted(b['files'], 'file')}, {counted(b['size'], 'byte')}.",
                      highlight=False)
            return
        job = api_call("GET", f"/api/jobs/{segment(job_id)}", params={"limit": 0})
        if why := job["options"].get("unstored"):  # a full or read-only backups folder
            raise fail(f"No backup was stored: {why}")
        time.sleep(0.2)  # between two asks (an API that does not wait answers at once)
    out.print("The backup ZIP is not registered yet; see `dncq backup list`.")


def _verdict(backup: dict[str, Any]) -> str:
    """The backup's status and its machines not whole in it: `partial (1014 failed)`."""
    # "ok" is the API's word for MachineBackupStatus.OK: jobs.backup_models would load SQLAlchemy.
    short = [f"{m['machineID']} {m['status']}" for m in backup["machines"] if m["status"] != "ok"]
    if len(short) > NAMED_AT_MOST:
        short[NAMED_AT_MOST:] = [f"{len(short) - NAMED_AT_MOST} more: dncq backup show "
                                 f"{backup['id']}"]
    return f"{backup['status']} ({', '.join(short)})" if short else backup["status"]


NAMED_AT_MOST = 10  # machines the verdict names; a fleet's outage would fill the screen

BACKUP_WAIT_S = 20.0  # how long a backup's follower waits for the ZIP once the machines are done
WAIT_STEP_S = 5.0  # per request
