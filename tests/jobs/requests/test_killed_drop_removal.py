"""A process looking into a drop folder killed with SIGKILL at each step of handing a dropped
request over to its job: the request makes one job, whatever the step, and the same file
dropped again afterwards (a copy that kept its modification time) makes a second one. A
dropped program that is not a request, killed as it goes into the inbox, is in the inbox
once after the next look.

The look runs in a process of its own, as a worker's reaper runs it, and that process kills
itself with SIGKILL as it enters the step: only such a fault injection stops it exactly
between the file's removal from the machine and the mark on its job, a moment a few
microseconds long.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from sqlalchemy import func, select

from jobs.db import session_scope
from jobs.inbox import service as inbox
from jobs.inbox.models import InboxState
from jobs.models import Job
from jobs.run import leases
from jobs.settings import Settings
from tests.jobs.requests.conftest import DROP_FOLDER, O0010, SEED_REQUEST, DropMachine
from tests.workers import worker_env

pytestmark = pytest.mark.slow

LOOK_KILLED_AT = """
import importlib, os, signal, sys
from jobs.requests import drop
from jobs.settings import Settings

module, _, name = sys.argv[1].partition(":")

def killed(*args, **kwargs):
    os.kill(os.getpid(), signal.SIGKILL)

setattr(importlib.import_module(module), name, killed)
drop.scan(settings=Settings())
"""

STEPS = [
    "jobs.requests.handling:handle",  # nothing recorded yet
    "jobs.requests.record:finish",  # the job recorded, its answer written, not finished
    "jobs.requests.dropped:removing",  # the job finished, the file not yet removed
    "jobs.requests.dropped:removed",  # the file removed, its job not yet marked so
]


def look_killed_at(settings: Settings, step: str, log_path: Path) -> None:
    """One look in a process of its own that is killed as it enters `step`."""
    with open(log_path, "wb") as log:
        done = subprocess.run([sys.executable, "-c", LOOK_KILLED_AT, step],
                              env=worker_env(settings), stdout=log, stderr=subprocess.STDOUT,
                              timeout=120, check=False)
    assert done.returncode == -signal.SIGKILL, log_path.read_text()


def look_once_free(settings: Settings, machine: DropMachine) -> int:
    """A look once the lease the killed process held has expired."""
    with leases.hold(settings.resolved_database_url, machine_id=machine.id, max_concurrent=1,
                     wait_s=60, ttl_s=settings.lease_ttl_s):
        pass
    return machine.scan()


def dropped_copy(settings: Settings, machine: DropMachine, mtime: float) -> None:
    """The control drops the request, a copy keeping the modification time `mtime` (as
    Windows' Explorer or `cp -p` copies a file)."""
    machine.drop("O8888", SEED_REQUEST)
    written = settings.data_dir / "mock" / machine.id / "files" / DROP_FOLDER.strip("/") / "O8888"
    os.utime(written, (mtime, mtime))


def jobs_recorded(settings: Settings) -> int:
    with session_scope(settings.resolved_database_url) as session:
        return session.scalar(select(func.count()).select_from(Job)) or 0


@pytest.mark.parametrize("step", STEPS)
def test_a_dropped_request_makes_one_job_whatever_step_its_look_was_killed_at(
        settings: Settings, drop_machine, add_program, tmp_path: Path, step: str) -> None:
    s = settings.model_copy(update={"lease_ttl_s": 1.0})  # the killed look's lease ends soon
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    copied_at = time.time() - 3600
    dropped_copy(s, machine, copied_at)

    look_killed_at(s, step, tmp_path / "look.log")
    look_once_free(s, machine)
    assert "O8888" not in machine.names()
    assert jobs_recorded(s) == 1

    dropped_copy(s, machine, copied_at)  # the same file once more: a request of its own
    assert machine.scan() == 1
    assert "O8888" not in machine.names()
    assert jobs_recorded(s) == 2
    assert machine.read("O0010") == O0010.encode()  # answered


KEPT = {  # what the control drops: the step it is killed at, and the item it becomes
    "a program": (b"%\nO7777\nG0 X0\nM30\n%\n", "jobs.inbox.service:receive",
                  InboxState.PENDING),
    "what dncq cannot take": (b"%\n\x01\x02garbage\x00binary\n%\n",
                              "jobs.inbox.service:receive_failed", InboxState.FAILED),
}


@pytest.mark.parametrize("dropped", list(KEPT))
def test_a_dropped_program_killed_on_its_way_into_the_inbox_is_kept_by_the_next_look(
        settings: Settings, drop_machine, tmp_path: Path, dropped: str) -> None:
    data, step, state = KEPT[dropped]
    s = settings.model_copy(update={"lease_ttl_s": 1.0})
    machine = drop_machine()
    machine.drop("O7777", data)
    written = s.data_dir / "mock" / machine.id / "files" / DROP_FOLDER.strip("/") / "O7777"
    settled = time.time() - 60  # the killed look's own process waits for a file to settle
    os.utime(written, (settled, settled))

    look_killed_at(s, step, tmp_path / "look.log")
    assert jobs_recorded(s) == 0  # nothing half recorded: the file is still the program
    look_once_free(s, machine)

    assert "O7777" not in machine.names()
    with session_scope(s.resolved_database_url) as session:
        items = inbox.list_items(session=session, machine_id=machine.id)
        assert [(item.state, item.size) for item in items] == [(state, len(data))]
    [job] = jobs_recorded_in(s)
    assert job.state.value == ("succeeded" if state is InboxState.PENDING else "failed")


def jobs_recorded_in(settings: Settings) -> list[Job]:
    with session_scope(settings.resolved_database_url) as session:
        jobs = list(session.scalars(select(Job)))
        session.expunge_all()
        return jobs
