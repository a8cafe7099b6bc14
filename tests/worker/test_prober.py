"""The prober: workers check the machines due a check, skip the busy and disabled ones, and
keep what they found for the fleet page and the metrics."""

from __future__ import annotations

import threading
from datetime import timedelta

import pytest
from sqlalchemy import update

from jobs import db
from jobs.fleet import checks
from jobs.models import MachineCheck, utcnow
from jobs.run import leases
from tests.jobs.helpers import wait_until
from worker.prober import Prober, probe_due


@pytest.fixture
def settings(settings):
    """Machines checked every 5 minutes, as by default."""
    return settings.model_copy(update={"machine_check_interval_s": 300.0})


def _last(settings):
    with db.session_scope(settings.resolved_database_url) as session:
        return checks.latest(session)


def test_machines_never_checked_are_checked_and_kept(settings, add_machines):
    add_machines({"id": "a", "name": "A", "model": "Mock"},
                 {"id": "b", "name": "B", "model": "Mock", "options": {"offline": True}})

    checked = probe_due(settings)

    last = _last(settings)
    assert checked == 2
    assert last["a"]["reachable"] is True and last["a"]["error"] is None
    assert last["b"]["reachable"] is False and "offline" in last["b"]["error"]


def test_a_machine_checked_within_the_period_is_not_checked_again(settings, add_machines):
    add_machines({"id": "a", "name": "A", "model": "Mock"},
                 {"id": "b", "name": "B", "model": "Mock"})
    probe_due(settings)
    with db.session_scope(settings.resolved_database_url) as session:
        session.execute(update(MachineCheck).where(MachineCheck.machine_id == "b").values(
            checked_at=utcnow() - timedelta(seconds=settings.machine_check_interval_s + 1)))

    assert probe_due(settings) == 1  # only b, whose check grew old
    assert probe_due(settings) == 0


def test_two_workers_sweeping_at_once_check_each_machine_once(settings, add_machines):
    ids = [f"m{n}" for n in range(40)]
    add_machines(*({"id": m, "name": m, "model": "Mock", "options": {"latency_ms": 20}}
                   for m in ids))
    start = threading.Barrier(2)
    counts: list[int] = []

    def sweep() -> None:
        start.wait()  # both find every machine due, as two workers started together do
        counts.append(probe_due(settings))

    sweeps = [threading.Thread(target=sweep) for _ in range(2)]
    for t in sweeps:
        t.start()
    for t in sweeps:
        t.join(60)

    assert sum(counts) == len(ids)  # each machine checked by one of them, once
    assert set(_last(settings)) == set(ids)


def test_a_busy_machine_is_left_to_its_job_and_a_disabled_one_alone(settings, add_machines):
    add_machines({"id": "busy", "name": "Busy", "model": "Mock"},
                 {"id": "off", "name": "Off", "model": "Mock", "enabled": False})
    url = settings.resolved_database_url
    holder = leases.acquire(url, machine_id="busy", max_concurrent=1, group="job:j1")

    assert probe_due(settings) == 0
    assert _last(settings) == {}
    leases.release(url, holder=holder)
    assert probe_due(settings) == 1
    assert set(_last(settings)) == {"busy"}


def test_no_period_means_no_probing(settings, add_machines):
    add_machines({"id": "a", "name": "A", "model": "Mock"})

    assert Prober(settings.model_copy(update={"machine_check_interval_s": 0})).tick() is False
    assert _last(settings) == {}


def test_a_worker_checks_the_machines_by_itself(settings, add_machines, start_worker,
                                                redis_server) -> None:
    add_machines({"id": "a", "name": "A", "model": "Mock"})
    every_second = settings.model_copy(update={"machine_check_interval_s": 1.0,
                                               "broker_url": redis_server.url,
                                               "reaper_interval_s": 0.2})
    start_worker("w1", every_second).wait_for_log("ready")

    wait_until(lambda: "a" in _last(settings), timeout_s=15)
    first = _last(settings)["a"]["at"]
    wait_until(lambda: _last(settings)["a"]["at"] > first, timeout_s=15)  # and again
