"""Machine leases on both databases dncq runs on: slots, groups, expiry, release."""

from __future__ import annotations

import threading
import uuid
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import delete, select, update

from jobs import db
from jobs.models import MachineLease, utcnow
from jobs.run import leases
from jobs.settings import Settings
from tests.jobs.helpers import wait_until


@pytest.fixture(params=["sqlite", "postgresql"])
def url(request: pytest.FixtureRequest, settings: Settings) -> str:
    if request.param == "sqlite":
        return settings.resolved_database_url
    return str(request.getfixturevalue("postgres_url"))


def fresh(name: str) -> str:
    """A machine id no other test of the shared server uses.

    The whole uuid: the deadlock test alone makes 9,000 ids on one server, and 8 hex
    digits (32 bits) gave two of them the same id about once in a hundred runs.
    """
    return f"{name}-{uuid.uuid4().hex}"


def take_many(url: str, wants: list[leases.Want], ttl_s: float = 30.0) -> list[str | None]:
    with db.session_scope(url) as session:
        return leases.take_many(session, wants, ttl_s=ttl_s)


def held(url: str, machine_id: str) -> list[tuple[int, str, str]]:
    """The machine's leases: slot, group and expiry of each."""
    with db.session_scope(url) as session:
        return [(lease.slot, lease.group, lease.expires_at.isoformat()) for lease in
                session.scalars(select(MachineLease).where(MachineLease.machine_id == machine_id)
                                .order_by(MachineLease.slot))]


def held_slots(url: str, machine_id: str) -> list[int]:
    with db.session_scope(url) as session:
        return sorted(session.scalars(select(MachineLease.slot)
                                      .where(MachineLease.machine_id == machine_id)))


def test_a_machine_gives_no_more_slots_than_its_limit_and_answers_in_order(url: str) -> None:
    one, two = fresh("one"), fresh("two")
    wants = [leases.Want(two, 2, "job:a"), leases.Want(one, 1, "job:a"),
             leases.Want(two, 2, "job:b"), leases.Want(one, 1, "job:b"),
             leases.Want(two, 2, "job:c")]

    got = take_many(url, wants)

    assert [h is not None for h in got] == [True, True, True, False, False]
    assert len(set(h for h in got if h)) == 3  # every holder token is its own
    assert held_slots(url, one) == [0]
    assert held_slots(url, two) == [0, 1]


def test_a_group_holds_one_slot_of_a_machine_however_often_it_asks(url: str) -> None:
    machine = fresh("m")

    first = take_many(url, [leases.Want(machine, 3, "job:a")])[0]
    again = take_many(url, [leases.Want(machine, 3, "job:a")])[0]

    assert first is not None and again is None
    assert held_slots(url, machine) == [0]


def test_a_released_slot_and_an_expired_one_can_be_taken_again(url: str) -> None:
    released, expired = fresh("released"), fresh("expired")
    holders = take_many(url, [leases.Want(released, 1, "job:a"),
                              leases.Want(expired, 1, "job:a")])
    assert all(holders)
    leases.release(url, holder=str(holders[0]))
    with db.session_scope(url) as session:  # the other holder died: its lease ran out
        session.execute(update(MachineLease).where(MachineLease.holder == holders[1])
                        .values(expires_at=utcnow() - timedelta(seconds=1)))

    again = take_many(url, [leases.Want(released, 1, "job:b"),
                            leases.Want(expired, 1, "job:b")])

    assert all(again) and set(again).isdisjoint(holders)
    assert not leases.renew(url, holder=str(holders[1]))  # the dead holder's lease is gone
    assert leases.renew(url, holder=str(again[1]))


def test_a_slot_held_and_alive_is_not_taken(url: str) -> None:
    machine = fresh("m")
    holder = leases.acquire(url, machine_id=machine, max_concurrent=1, group="api:x")

    other = leases.acquire(url, machine_id=machine, max_concurrent=1, group="api:y")

    assert holder is not None and other is None


def test_two_workers_taking_the_same_machines_in_opposite_orders_do_not_deadlock(
        postgres_url: str) -> None:
    # Each takes the fleet's slots in one statement, in its own request order; rows taken
    # in those orders meet in the middle, each waiting for the other's (deadlock detected).
    errors: list[Exception] = []
    missed: list[str] = []

    def take(start: threading.Barrier, order: list[str], job: str) -> None:
        try:
            with db.session_scope(postgres_url) as session:
                start.wait()
                taken = leases.take_many(session, [leases.Want(m, 2, job) for m in order])
            missed.extend(f"{job} {m}" for m, holder in zip(order, taken, strict=True)
                          if holder is None)
        except Exception as exc:  # said below, with the others
            errors.append(exc)

    for _ in range(ROUNDS):
        machines = [fresh("dl") for _ in range(300)]
        start = threading.Barrier(2)
        threads = [threading.Thread(target=take, args=(start, machines, "job:a")),
                   threading.Thread(target=take, args=(start, machines[::-1], "job:b"))]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()

    assert errors == []
    # Two slots each: both get every machine. A miss is shown with what the machine holds.
    assert missed == [], [(want, held(postgres_url, want.split()[1]))
                          for want in missed[:5]]


ROUNDS = 30


def test_what_a_lease_covers_is_renewed_only_when_the_lease_was(url: str, tmp_path: Path) -> None:
    # A job's targets are kept alive through the lease's on_renew: if the database refused
    # the renewal, the lease may run out, and the targets must then be left to run out too.
    [holder] = take_many(url, [leases.Want(fresh("m"), 1, "job:a")], ttl_s=0.6)
    unreachable = f"sqlite:///{tmp_path / 'no-such-folder' / 'dncq.db'}"
    kept: list[str] = []
    with leases.Heartbeat(url, holder=str(holder), ttl_s=0.6,
                          on_renew=lambda: kept.append("reachable")), \
            leases.Heartbeat(unreachable, holder="lost", ttl_s=0.6,
                             on_renew=lambda: kept.append("unreachable")):
        wait_until(lambda: kept.count("reachable") >= 3, timeout_s=10)
    assert "unreachable" not in kept


def expiry(url: str, holder: str) -> float:
    """Seconds from now until the holder's lease runs out."""
    with db.session_scope(url) as session:
        expires_at = session.scalar(select(MachineLease.expires_at)
                                    .where(MachineLease.holder == holder))
    assert expires_at is not None
    return (expires_at - utcnow()).total_seconds()


def test_a_lease_holds_five_sixths_of_its_ttl_so_a_dead_holder_is_done_within_one(
        url: str) -> None:
    [holder] = take_many(url, [leases.Want(fresh("m"), 1, "job:a")], ttl_s=60.0)
    assert holder is not None
    # Dead now: the lease runs out 50 s on, leaving the reaper 10 s within the 60 s period.
    assert 45.0 < expiry(url, holder) <= 50.0  # not the whole 60 s, whatever the host's pace


def test_a_live_holder_renews_every_sixth_of_its_ttl_all_its_leases_at_once(url: str) -> None:
    ttl_s = 3.0  # a renewal a beat late on a busy host still comes in time
    machines = [fresh("m") for _ in range(3)]
    holders = take_many(url, [leases.Want(m, 1, "job:a") for m in machines], ttl_s=ttl_s)
    assert all(holders)
    renewed: list[str] = []
    beats = [leases.Heartbeat(url, holder=str(h), ttl_s=ttl_s,
                              on_renew=lambda h=h: renewed.append(str(h))) for h in holders]
    for beat in beats:
        beat.__enter__()
    try:
        deadline = utcnow() + timedelta(seconds=2 * ttl_s)  # without renewals, all gone
        while utcnow() < deadline:
            assert all(expiry(url, str(h)) > 0 for h in holders)  # never ran out
            threading.Event().wait(0.05)
    finally:
        for beat in beats:
            beat.__exit__(None, None, None)
    assert leases.renew_many(url, [str(h) for h in holders], ttl_s=ttl_s) == 3
    assert len(renewed) >= 3 * 6  # every sixth of the TTL (12 each at best), each of the three


def test_a_lease_lost_before_its_renewal_is_logged(url: str, caplog: pytest.LogCaptureFixture
                                                   ) -> None:
    holder = leases.acquire(url, machine_id=fresh("m"), max_concurrent=1, group="job:a",
                            ttl_s=0.6)
    assert holder is not None
    with leases.Heartbeat(url, holder=holder, ttl_s=0.6):
        with db.session_scope(url) as session:  # what a taker does with an expired lease
            session.execute(delete(MachineLease).where(MachineLease.holder == holder))
        wait_until(lambda: "expired before they were renewed" in caplog.text, timeout_s=5)

    assert "1 machine leases of this process expired" in caplog.text
