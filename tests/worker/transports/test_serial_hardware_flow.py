"""RTS/CTS: the line dncq opens is set for hardware flow control, on a local port and, over
RFC 2217, on the serial device server's port.

Whether the far end then holds the flow is the UART's: a pseudo-terminal has no modem lines,
so no test here can drop CTS. What dncq decides, the line's setting, is read back from the
kernel (termios of the pty dncq opened, or of the pty ser2net opened for it).
"""

from __future__ import annotations

import os
import termios
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.worker.transports.serial_lines import (  # noqa: F401
    MachineFactory,
    line_to,
    ser2net_url,
    serial_machine,
    url_of,
)
from worker.simulator.serial_machine import PtyEnd


def flags_of(device: str) -> tuple[bool, bool]:
    """(RTS/CTS, XON/XOFF by the kernel) as the tty is set now."""
    fd = os.open(device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        iflag, _, cflag, *_ = termios.tcgetattr(fd)
    finally:
        os.close(fd)
    return bool(cflag & termios.CRTSCTS), bool(iflag & (termios.IXON | termios.IXOFF))


@pytest.mark.parametrize(("flow", "expected"), [
    ("rtscts", (True, False)),
    ("xonxoff", (False, False)),  # dncq does XON/XOFF itself: it must see the machine's DC3
    ("none", (False, False)),
])
def test_a_local_port_is_set_for_the_flow_control_asked(
        serial_machine: MachineFactory, line_to: Callable[..., object],  # noqa: F811
        flow: str, expected: tuple[bool, bool]) -> None:
    machine = serial_machine()
    assert isinstance(machine.end, PtyEnd)
    line = line_to(url_of(machine), flow_control=flow, baud=115200)
    line.connect()  # type: ignore[attr-defined]
    assert flags_of(machine.end.device) == expected


def test_rts_cts_reaches_the_device_servers_port_over_rfc2217(
        serial_machine: MachineFactory, ser2net_url: Callable[..., str],  # noqa: F811
        line_to: Callable[..., object]) -> None:  # noqa: F811
    machine = serial_machine()
    assert isinstance(machine.end, PtyEnd)
    url = ser2net_url(machine, rfc2217=True)
    line = line_to(url, flow_control="rtscts", baud=115200)
    line.connect()  # type: ignore[attr-defined]
    deadline = time.monotonic() + 10  # ser2net applies what the telnet options say
    while flags_of(machine.end.device)[0] is not True and time.monotonic() < deadline:
        time.sleep(0.05)
    assert flags_of(machine.end.device)[0] is True


def test_a_program_sent_over_a_line_set_for_rts_cts_arrives_whole(
        serial_machine: MachineFactory, line_to: Callable[..., object],  # noqa: F811
        tmp_path: Path) -> None:
    machine = serial_machine()
    line = line_to(url_of(machine), flow_control="rtscts", baud=115200)
    program = b"%\nO0077 (RTS CTS)\nG0 X1.\nG1 Y2. F100.\nM30\n%\n"
    line.write("O0077", [program])  # type: ignore[attr-defined]
    stored = machine.control.store.root / "O0077"
    deadline = time.monotonic() + 10
    while not stored.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert b"G1 Y2. F100." in stored.read_bytes()
