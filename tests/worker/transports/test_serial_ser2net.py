"""The serial transport passes the conformance suite through ser2net, as through a shop's
serial device server: `socket://` to ser2net, ser2net to a pty, the simulated control on
the pty's other end."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from tests.worker.transports.contract import *  # noqa: F403
from tests.worker.transports.serial_lines import (  # noqa: F401
    MachineFactory,
    ser2net_url,
    serial_machine,
)
from worker.simulator.serial_machine import SerialMachine
from worker.transports.serial_line import SerialOptions, SerialTransport


@pytest.fixture
def transport(serial_machine: MachineFactory,  # noqa: F811
              ser2net_url: Callable[[SerialMachine], str],  # noqa: F811
              tmp_path: Path) -> Iterator[SerialTransport]:
    url = ser2net_url(serial_machine())
    line = SerialTransport(SerialOptions(url=url, baud=4_000_000), folder=tmp_path / "state")
    yield line
    line.close()
