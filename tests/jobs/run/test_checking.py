"""Checks take one of the machine's slots: a machine busy with other work is not connected
to (a control that takes one client would refuse its job) and not called offline."""

from __future__ import annotations

from jobs import db
from jobs.fleet import checks, registry
from jobs.run import checking, leases


def _spec(settings, machine_id):
    with db.session_scope(settings.resolved_database_url) as session:
        return registry.get(session=session, machine_id=machine_id)


def test_a_machine_held_by_a_job_is_answered_busy_with_its_last_check(settings,
                                                                      add_machines) -> None:
    add_machines({"id": "a", "name": "A", "model": "Mock"})
    quick = settings.model_copy(update={"busy_wait_s": 0.2})
    [first] = checking.check_now(quick, [_spec(settings, "a")])
    url = settings.resolved_database_url
    holder = leases.acquire(url, machine_id="a", max_concurrent=1, group="job:j1")

    [busy] = checking.check_now(quick, [_spec(settings, "a")])

    assert (first["reachable"], first["busy"]) == (True, False)
    assert (busy["reachable"], busy["busy"]) == (True, True)
    assert busy["checked_at"] == first_check_time(settings, "a").isoformat()
    leases.release(url, holder=holder)


def first_check_time(settings, machine_id):
    with db.session_scope(settings.resolved_database_url) as session:
        return checks.last(session, machine_id)["at"]


def test_a_busy_machine_never_checked_says_so_and_nothing_is_kept(settings,
                                                                  add_machines) -> None:
    add_machines({"id": "b", "name": "B", "model": "Mock"})
    quick = settings.model_copy(update={"busy_wait_s": 0.2})
    holder = leases.acquire(settings.resolved_database_url, machine_id="b", max_concurrent=1,
                            group="listen:b")

    [busy] = checking.check_now(quick, [_spec(settings, "b")])

    assert busy["busy"] is True and busy["reachable"] is None
    assert "busy" in busy["error"]
    with db.session_scope(settings.resolved_database_url) as session:
        assert checks.last(session, "b") is None
    leases.release(settings.resolved_database_url, holder=holder)


def test_a_slot_freed_within_the_wait_is_checked(settings, add_machines) -> None:
    import threading

    add_machines({"id": "c", "name": "C", "model": "Mock"})
    url = settings.resolved_database_url
    holder = leases.acquire(url, machine_id="c", max_concurrent=1, group="job:j2")
    threading.Timer(0.3, lambda: leases.release(url, holder=holder)).start()

    [found] = checking.check_now(settings.model_copy(update={"busy_wait_s": 5.0}),
                                 [_spec(settings, "c")])

    assert (found["reachable"], found["busy"]) == (True, False)
