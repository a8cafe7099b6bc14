"""Fixtures of the request tests: the library's programs, listeners, drop folders, and the
jobs they record."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest

from jobs import job_views, service
from jobs.db import session_scope
from jobs.fleet import door, registry
from jobs.fleet.registry import MachineSpec
from jobs.library import blobs
from jobs.library import service as library
from jobs.models import JobKind
from jobs.requests import drop
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
        views = [job_views.view(session=session, job=j, page=job_views.TargetPage())
                 for j in reversed(jobs)]
    return [v for v in views if not finished or v["state"] not in ("queued", "running")]


def wait_for_jobs(settings: Settings, count: int, timeout_s: float = 30.0
                  ) -> list[dict[str, Any]]:
    """Wait until `count` request jobs have finished; them, oldest first."""
    wait_until(lambda: len(request_jobs(settings)) >= count, timeout_s=timeout_s)
    return request_jobs(settings)


DROP_FOLDER = "/requests"


@dataclass
class DropMachine:
    """A machine reached through a folder whose control drops requests into `DROP_FOLDER`."""

    settings: Settings
    id: str

    @property
    def spec(self) -> MachineSpec:
        with session_scope(self.settings.resolved_database_url) as session:
            return registry.get(session=session, machine_id=self.id)

    def drop(self, name: str, data: bytes, folder: str = DROP_FOLDER, *,
             replace: bool = False) -> None:
        """The control writes `name` into the folder (over a file of that name: `replace`)."""
        with door.open_files(self.spec, data_dir=self.settings.data_dir) as files:
            ref = files.ref(name, folder, None)
            if replace:
                files.delete(ref, force=True)
            files.send_chunks(ref, iter([data]))

    def names(self, folder: str = DROP_FOLDER) -> list[str]:
        """The files in the folder, sorted."""
        with door.open_files(self.spec, data_dir=self.settings.data_dir) as files:
            return sorted(files.list_program_dir(folder, None)["programs"])

    def read(self, name: str, folder: str = DROP_FOLDER) -> bytes:
        with door.open_files(self.spec, data_dir=self.settings.data_dir) as files:
            return files.read_bytes(files.ref(name, folder, None), max_bytes=1 << 24)

    def scan(self) -> int:
        """One look into the drop folder, as the reaper's tick does it."""
        return drop.scan_machine(settings=self.settings, spec=self.spec)


@pytest.fixture
def drop_machine(settings: Settings, add_machines: Callable[..., Any]
                 ) -> Callable[..., DropMachine]:
    """Factory: a machine (a mock one unless told) with requests dropped into a folder;
    `requests` are its request settings over the drop folder's."""

    def make(machine_id: str = "m1", *, transport: str = "mock", model: str = "Mock",
             options: dict[str, Any] | None = None, folders: tuple[str, ...] = (),
             max_concurrent: int = 1, **requests: Any) -> DropMachine:
        add_machines({"id": machine_id, "name": f"Drop {machine_id}", "model": model,
                      "transport": transport, "options": options or {},
                      "max_concurrent": max_concurrent,
                      "requests": {"enabled": True, "drop_folder": DROP_FOLDER, **requests}})
        machine = DropMachine(settings, machine_id)
        with door.open_files(machine.spec, data_dir=settings.data_dir) as files:
            for folder in (DROP_FOLDER, *folders):  # a parent before its children
                parent, _, name = folder.rstrip("/").rpartition("/")
                files.make_dir(name, parent or "/", None)
        return machine

    return make


@pytest.fixture(autouse=True)
def files_settle_at_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """A dropped file is taken at the next look, not `SETTLE_S` after it was written (one
    test of the settle time sets it back)."""
    monkeypatch.setattr(drop, "SETTLE_S", 0.0)
