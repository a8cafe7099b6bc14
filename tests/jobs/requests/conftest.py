"""Fixtures of the request tests: the library's programs, listeners, and the jobs they record."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest

from jobs import service
from jobs.db import session_scope
from jobs.library import blobs
from jobs.library import service as library
from jobs.models import JobKind
from jobs.settings import Settings
from tests.jobs.helpers import wait_until
from worker.listener import Listeners

O0010 = ("%\nO0010 (VIPROS BRACKET)\nG21 G90 G40 G80\nT01 M06\nG54 G0 X0 Y0 S2500 M03\n"
         "G43 Z5. H01\nN100 G1 Z-2. F200\nN110 X40. F600\nN120 Y30.\nN130 X0\nN140 Y0\n"
         "G0 Z50.\nM30\n%\n")
SEED_REQUEST = b"%\nO8888\nN0010 (DIR=/VIPROS)\nN0020 (PRG=0010)\n%\n"


@pytest.fixture
def add_program(settings: Settings) -> Callable[..., None]:
    """Factory: put an approved program into the library."""

    def add(folder: str, name: str, text: str, *, approve: bool = True) -> None:
        blob = blobs.put(settings, [text.encode()])
        with session_scope(settings.resolved_database_url) as session:
            library.add(session=session, folder=folder, name=name, blob=blob, approve=approve)

    return add


@pytest.fixture
def listening(settings: Settings) -> Iterator[Listeners]:
    """The listeners of a worker of the test's dncq; `tick()` starts them, as its reaper does."""
    fast = settings.model_copy(update={"lease_ttl_s": 6.0})
    listeners = Listeners(fast)
    yield listeners
    listeners.stop()


def request_jobs(settings: Settings, *, finished: bool = True) -> list[dict[str, Any]]:
    """The request jobs recorded, oldest first, each with its targets."""
    with session_scope(settings.resolved_database_url) as session:
        jobs = service.list_jobs(session=session, kind=JobKind.REQUEST)
        views = [service.view(session=session, job=j, page=service.TargetPage())
                 for j in reversed(jobs)]
    return [v for v in views if not finished or v["state"] not in ("queued", "running")]


def wait_for_jobs(settings: Settings, count: int, timeout_s: float = 30.0
                  ) -> list[dict[str, Any]]:
    """Wait until `count` request jobs have finished; them, oldest first."""
    wait_until(lambda: len(request_jobs(settings)) >= count, timeout_s=timeout_s)
    return request_jobs(settings)
