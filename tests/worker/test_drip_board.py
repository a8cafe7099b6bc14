"""The drip-feed board: the runs of a worker told to the database together, each run's own
record still saying whether its own feed goes on."""

from __future__ import annotations

from typing import Any

import pytest

from jobs import db
from jobs.dnc import feeding, programs, runs
from jobs.models import Run, RunState
from worker import drip_board


@pytest.fixture
def two_runs(queue_settings, add_machines) -> list[tuple[str, feeding.Ticket]]:
    """Two runs, each of a job of its own, begun as a runner begins them (nothing runs
    them: the queue has no worker)."""
    add_machines({"id": "a", "name": "A", "model": "Mock"},
                 {"id": "b", "name": "B", "model": "Mock"})
    program = programs.store(queue_settings, iter([b"O1\nG0 X0\nM30\n"]))
    url = queue_settings.resolved_database_url
    begun = []
    for machine_id in ("a", "b"):
        with db.session_scope(url) as session:
            job = runs.submit(session=session, settings=queue_settings,
                              machine_ids=[machine_id], program=program, file_name="P.NC")
            job_id = job.id
        begun.append((job_id, feeding.begin(url=url, job_id=job_id, machine_id=machine_id,
                                                attempt=1)))
    return begun


def record(settings: Any, ticket: feeding.Ticket) -> Run:
    with db.session_scope(settings.resolved_database_url) as session:
        run = session.get(Run, ticket.run_id)
        assert run is not None
        session.expunge(run)
        return run


def test_one_flush_writes_the_line_of_every_run_that_moved(queue_settings, two_runs) -> None:
    board = drip_board.Board(queue_settings.resolved_database_url)
    (_, first), (_, second) = two_runs
    entries = [board.join(first.run_id), board.join(second.run_id)]
    entries[0].moved(2, 3)
    entries[1].moved(1, 2)

    board.flush()

    assert (record(queue_settings, first).last_line, record(queue_settings, first).lines_sent) \
        == (2, 3)
    assert record(queue_settings, second).last_line == 1
    for entry in entries:
        board.leave(entry)


def test_a_stop_reaches_only_its_own_run(queue_settings, two_runs) -> None:
    board = drip_board.Board(queue_settings.resolved_database_url)
    (first_job, first), (_, second) = two_runs
    entries = [board.join(first.run_id), board.join(second.run_id)]
    with db.session_scope(queue_settings.resolved_database_url) as session:
        runs.request_stop(session=session, settings=queue_settings, job_id=first_job,
                          stopped_by="alice")

    board.flush()

    assert [e.stop for e in entries] == [True, False]
    for entry in entries:
        board.leave(entry)


def test_a_feed_not_heard_from_lets_its_record_go_stale_and_an_ended_run_stays_ended(
        queue_settings, two_runs, monkeypatch) -> None:
    """The reaper keeps a run's lease while its record is fresh: a feed stuck on its link
    must not be kept fresh by the board, and a late flush never rewrites a run's end."""
    monkeypatch.setattr(drip_board, "ALIVE_EVERY_S", 0.0)
    url = queue_settings.resolved_database_url
    board = drip_board.Board(url)
    (_, going), (_, stuck) = two_runs
    going_entry, stuck_entry = board.join(going.run_id), board.join(stuck.run_id)
    board.flush()  # both written once
    stuck_since = record(queue_settings, stuck).updated_at
    going_since = record(queue_settings, going).updated_at

    going_entry.alive()  # only this feed asks whether to stop
    board.flush()

    assert record(queue_settings, going).updated_at > going_since
    assert record(queue_settings, stuck).updated_at == stuck_since

    feeding.end(url=url, run_id=going.run_id, state=RunState.SUCCEEDED, last_line=3,
                lines_sent=3, message="ran to line 3")
    going_entry.moved(1, 1)  # a flush that comes after the end
    board.flush()

    ended = record(queue_settings, going)
    assert (ended.state, ended.last_line) == (RunState.SUCCEEDED, 3)
    assert going_entry.stop  # and its feed is told to stop
    board.leave(going_entry)
    board.leave(stuck_entry)


def test_the_flushing_thread_ends_with_the_last_run_and_starts_again_with_the_next(
        queue_settings, two_runs) -> None:
    from tests.jobs.helpers import wait_until

    board = drip_board.Board(queue_settings.resolved_database_url)
    (_, first), (_, second) = two_runs
    entry = board.join(first.run_id)
    entry.moved(2, 2)
    wait_until(lambda: record(queue_settings, first).last_line == 2, timeout_s=10)
    board.leave(entry)
    wait_until(lambda: board._thread is None, timeout_s=10)

    later = board.join(second.run_id)
    later.moved(1, 1)

    wait_until(lambda: record(queue_settings, second).last_line == 1, timeout_s=10)
    board.leave(later)
