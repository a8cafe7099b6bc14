"""The mock transport passes the conformance suite (its storage is a local folder)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from tests.worker.transports.contract import *  # noqa: F403
from worker.transports.mock import MockOptions, MockTransport


@pytest.fixture
def transport(tmp_path: Path) -> Iterator[MockTransport]:
    mock = MockTransport(MockOptions(), folder=tmp_path / "machine")
    yield mock
    mock.close()


# -- the state every opener of a machine shares ------------------------------------


def _list_at_once(openers: list[MockTransport]) -> None:
    with ThreadPoolExecutor(len(openers)) as pool:
        list(pool.map(lambda mock: mock.list_dir(""), openers))


def test_operations_are_counted_across_openers_threads_and_processes(tmp_path: Path) -> None:
    folder = tmp_path / "machine"
    slow = MockOptions(latency_ms=300)
    one, two = MockTransport(slow, folder=folder), MockTransport(slow, folder=folder)

    _list_at_once([one, one])  # one opener, two threads
    assert one.peak_active() == 2
    one.reset_peak()
    _list_at_once([one, two])  # two openers in one process
    assert two.peak_active() == 2
    one.reset_peak()
    other = subprocess.Popen([sys.executable, "-c", (
        "import sys; from pathlib import Path; "
        "from worker.transports.mock import MockOptions, MockTransport; "
        "MockTransport(MockOptions(latency_ms=1500), folder=Path(sys.argv[1])).list_dir('')"),
        str(folder)])
    try:
        deadline = time.monotonic() + 10
        while one.peak_active() < 1 and time.monotonic() < deadline:
            time.sleep(0.02)  # the other process's operation has begun
        _list_at_once([one])
    finally:
        assert other.wait(10) == 0
    assert one.peak_active() == 2
    one.close()
    two.close()


def test_a_machine_folder_made_again_starts_its_counters_afresh(tmp_path: Path) -> None:
    folder = tmp_path / "machine"
    first = MockTransport(MockOptions(latency_ms=50), folder=folder)
    _list_at_once([first, first])
    first.close()
    shutil.rmtree(folder)

    again = MockTransport(MockOptions(), folder=folder)
    again.list_dir("")

    assert again.peak_active() == 1
    assert (folder / "counters").exists()
    again.close()
