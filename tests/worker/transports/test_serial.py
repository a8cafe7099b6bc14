"""The serial transport passes the conformance suite over a pty pair to the simulated control."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.worker.transports.contract import *  # noqa: F403
from tests.worker.transports.serial_lines import MachineFactory, serial_machine  # noqa: F401
from worker.transports.serial_line import SerialOptions, SerialTransport

FAST_BAUD = 4_000_000  # a pty takes any speed; the suite moves megabytes


@pytest.fixture
def transport(serial_machine: MachineFactory, tmp_path: Path) -> Iterator[SerialTransport]:  # noqa: F811
    machine = serial_machine()
    line = SerialTransport(SerialOptions(url=str(machine.end.link), baud=FAST_BAUD),
                           folder=tmp_path / "state")
    yield line
    line.close()
