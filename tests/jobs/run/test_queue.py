"""The producer that sends tasks: one per broker, configured before any thread gets it."""

from __future__ import annotations

import threading
from pathlib import Path

from jobs.run.queue import producer
from jobs.settings import Settings

THREADS = 16
ROUNDS = 20  # each with a data folder of its own: a producer made while threads ask for it


def _ask(settings: Settings, start: threading.Barrier, got: list[tuple[int, str]]) -> None:
    start.wait()
    app = producer(settings)
    got.append((id(app), str(app.conf.broker_url)))


def test_threads_asking_at_once_all_get_one_producer_configured_for_the_data_folder(
        tmp_path: Path) -> None:
    for round_number in range(ROUNDS):
        data = tmp_path / f"data{round_number}"
        data.mkdir()
        settings = Settings(data_dir=data)
        start = threading.Barrier(THREADS)
        got: list[tuple[int, str]] = []

        threads = [threading.Thread(target=_ask, args=(settings, start, got))
                   for _ in range(THREADS)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()

        assert len(set(got)) == 1
        assert got[0][1].startswith("filesystem://")


def test_health_answers_through_a_redis_restart_and_counts_the_workers_again(
        queue_client, restarted_redis):
    from tests.jobs.helpers import wait_until

    assert queue_client.get("/api/health").json()["workers"] >= 1  # a pooled connection now
    restarted_redis.kill()
    restarted_redis.start()
    answers = []

    def counted_again() -> bool:
        response = queue_client.get("/api/health")
        answers.append(response.status_code)
        workers = response.json().get("workers") if response.status_code == 200 else None
        return isinstance(workers, int) and workers >= 1

    wait_until(counted_again, timeout_s=30)  # the worker itself reconnects meanwhile
    assert set(answers) == {200}  # never a server error on the connection Redis dropped
