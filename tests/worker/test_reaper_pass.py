"""A reaper pass the database cut short is said in one line and tried again; any other
failure of a pass is logged with its traceback."""

from __future__ import annotations

import logging
import threading
from typing import Any

import pytest
from sqlalchemy import text

from jobs import db
from jobs.run import reaper
from jobs.settings import Settings
from worker.app import Reaper


def passes_of(settings: Settings, monkeypatch: pytest.MonkeyPatch, first_pass: Any) -> None:
    """Run a reaper whose first pass is `first_pass()`, until a second pass has begun."""
    second = threading.Event()
    calls = []

    def reap(**kwargs: Any) -> None:
        calls.append(kwargs)
        if len(calls) == 1:
            first_pass()
        else:
            second.set()

    monkeypatch.setattr(reaper, "reap", reap)
    running = Reaper(settings.model_copy(update={"reaper_interval_s": 0.05}))
    running.start()
    try:
        assert second.wait(30), "no pass after the failed one"
    finally:
        running.stop()


def test_a_pass_whose_database_connection_was_killed_is_one_warning_and_tried_again(
        request: pytest.FixtureRequest, settings: Settings, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    url = request.getfixturevalue("postgres_url")

    def cut_off() -> None:  # as PostgreSQL restarting, or an admin ending the connection
        with db.session_scope(url) as session:
            pid = session.scalar(text("SELECT pg_backend_pid()"))
            with db.session_scope(url) as other:
                other.execute(text("SELECT pg_terminate_backend(:pid)"), {"pid": pid})
            session.execute(text("SELECT 1"))

    with caplog.at_level(logging.WARNING, logger="worker.app"):
        passes_of(settings.model_copy(update={"database_url": url}), monkeypatch, cut_off)

    [said] = [r for r in caplog.records if r.name == "worker.app"]
    assert said.levelno == logging.WARNING and said.exc_info is None
    assert "\n" not in said.getMessage()
    assert "terminating connection" in said.getMessage()
    assert "tried again in 0.05 s" in said.getMessage()


def test_any_other_failure_of_a_pass_is_an_error_with_its_traceback(
        settings: Settings, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    def broken() -> None:
        raise KeyError("a bug")

    with caplog.at_level(logging.WARNING, logger="worker.app"):
        passes_of(settings, monkeypatch, broken)

    [said] = [r for r in caplog.records if r.name == "worker.app"]
    assert said.levelno == logging.ERROR and said.getMessage() == "reaper pass failed"
    assert said.exc_info is not None and isinstance(said.exc_info[1], KeyError)
