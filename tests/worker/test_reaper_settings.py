"""The reaper says so when its settings cannot keep the lease period's promise."""

from __future__ import annotations

import logging

import pytest

from jobs.settings import Settings
from worker.app import Reaper


def started(settings: Settings) -> None:
    reaper = Reaper(settings)
    reaper.start()
    reaper.stop()


def test_a_reaper_coming_by_less_often_than_a_sixth_of_the_lease_period_is_warned_of(
        settings: Settings, caplog: pytest.LogCaptureFixture) -> None:
    slow = settings.model_copy(update={"lease_ttl_s": 30.0, "reaper_interval_s": 6.0})
    with caplog.at_level(logging.WARNING, logger="worker.app"):
        started(slow)
    [warning] = [r for r in caplog.records if "DNCQ_REAPER_INTERVAL_S" in r.getMessage()]
    assert "6 s" in warning.getMessage() and "30 s" in warning.getMessage()


def test_the_default_settings_are_not_warned_of(
        settings: Settings, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="worker.app"):
        started(settings)  # 2 s and 30 s
    assert not [r for r in caplog.records if "DNCQ_REAPER_INTERVAL_S" in r.getMessage()]
