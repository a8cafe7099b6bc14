"""The serial transport passes the conformance suite over RFC 2217 (telnet with the line's
settings sent along), as to a serial device server that speaks it: `rfc2217://` to ser2net,
ser2net to a pty, the simulated control on the pty's other end."""

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
              ser2net_url: Callable[..., str],  # noqa: F811
              tmp_path: Path) -> Iterator[SerialTransport]:
    url = ser2net_url(serial_machine(), rfc2217=True)
    line = SerialTransport(SerialOptions(url=url, baud=4_000_000), folder=tmp_path / "state")
    yield line
    line.close()


def test_a_program_punched_over_rfc2217_arrives_whole(
        serial_machine: MachineFactory, ser2net_url: Callable[..., str],  # noqa: F811
        tmp_path: Path) -> None:
    machine: SerialMachine = serial_machine()
    line = SerialTransport(SerialOptions(url=ser2net_url(machine, rfc2217=True), baud=115200),
                           folder=tmp_path / "state")
    try:
        line.connect()
        machine.punch_text(b"%\nO0042 (OVER RFC 2217)\nG0 X1.\nM30\n%\n")
        entry = line.receive_punch(timeout_s=10)
        assert entry.name == "O0042"
        assert b"G0 X1." in b"".join(line.read("O0042"))
    finally:
        line.close()
