"""Group commit: many threads' requests served together, each caller gets its own answer."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from jobs import db
from jobs.models import MachineLease
from jobs.run import leases
from jobs.run.group_commit import GroupCommit
from jobs.settings import Settings


def test_requests_that_arrive_together_share_a_transaction_and_get_their_own_result(
        settings: Settings) -> None:
    url = settings.resolved_database_url
    batches: list[list[str]] = []
    first_inside = threading.Event()
    let_go = threading.Event()

    def serve(session: Session, machines: Sequence[str]) -> list[str | None]:
        batches.append(list(machines))
        if len(batches) == 1:  # hold the first batch so that the others queue up behind it
            first_inside.set()
            assert let_go.wait(10)
        return [leases.take(session, machine_id=m, max_concurrent=1, group="g")
                for m in machines]

    commits: GroupCommit[str, str | None] = GroupCommit("test-commits", serve)
    with ThreadPoolExecutor(20) as pool:
        first = pool.submit(commits.call, url, "m0")
        assert first_inside.wait(10)
        # Each queues behind the held batch from a thread of its own, and is let go only
        # once all have queued: a loaded host may keep a thread from running for a second.
        queued = [pool.submit(commits.submit, url, f"m{i}") for i in range(1, 20)]
        rest = [q.result(10) for q in queued]
        let_go.set()
        holders = [first.result(10)] + [f.result(10) for f in rest]

    assert len(batches) == 2  # the 19 that waited went in one transaction after the held one
    assert sorted(m for b in batches for m in b) == sorted(f"m{i}" for i in range(20))
    with db.session_scope(url) as session:
        stored = dict(session.execute(select(MachineLease.machine_id, MachineLease.holder))
                      .all())
    assert stored == {f"m{i}": holders[i] for i in range(20)}  # each caller got its own slot


def test_a_failing_request_fails_only_its_caller(settings: Settings) -> None:
    url = settings.resolved_database_url
    gate = threading.Event()

    def serve(session: Session, machines: Sequence[str]) -> list[str | None]:
        gate.wait(10)
        if "bad" in machines:
            raise ValueError("bad request")
        return [leases.take(session, machine_id=m, max_concurrent=1, group="g")
                for m in machines]

    commits: GroupCommit[str, str | None] = GroupCommit("test-commits", serve)
    with ThreadPoolExecutor(8) as pool:
        futures = {m: pool.submit(commits.call, url, m) for m in ("a", "b", "bad", "c", "d")}
        gate.set()
        with pytest.raises(ValueError, match="bad request"):
            futures["bad"].result(10)
        good = {m: f.result(10) for m, f in futures.items() if m != "bad"}

    assert all(good.values())
    with db.session_scope(url) as session:
        # The failed shared transaction was rolled back and each good request redone once.
        assert session.scalar(select(func.count()).select_from(MachineLease)) == 4


def test_submitted_requests_are_committed_by_the_time_drain_returns(settings: Settings) -> None:
    url = settings.resolved_database_url
    gate = threading.Event()

    def serve(session: Session, machines: Sequence[str]) -> list[str | None]:
        gate.wait(10)
        return [leases.take(session, machine_id=m, max_concurrent=1, group="g")
                for m in machines]

    commits: GroupCommit[str, str | None] = GroupCommit("test-commits", serve)
    futures = [commits.submit(url, f"m{i}") for i in range(5)]  # the caller goes on at once
    assert not any(f.done() for f in futures)
    assert not commits.drain(0.2)  # held at the gate: not served yet

    gate.set()
    assert commits.drain(10)

    assert all(f.done() for f in futures)
    with db.session_scope(url) as session:
        stored = dict(session.execute(select(MachineLease.machine_id, MachineLease.holder))
                      .all())
    assert stored == {f"m{i}": futures[i].result() for i in range(5)}
