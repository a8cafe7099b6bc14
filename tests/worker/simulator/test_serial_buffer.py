"""The simulated control's RS-232 receive buffer in DNC: it loses what a sender pushes past
it, and never what the line carried while its own thread was kept from running (a loaded
host), which a real control's UART would have met with DC3 in time."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from worker.simulator.control import Control, IoChannel, Mode, RunState
from worker.simulator.programs import ProgramStore
from worker.simulator.serial_machine import PtyEnd, SerialMachine

BAUD = 115_200


def tape(lines: int) -> bytes:
    body = b"".join(f"N{n} G1 X{n % 90}.0 Y{n % 37}.0 F500\n".encode()
                    for n in range(10, 10 * lines + 1, 10))
    return b"%\nO0100\n" + body + b"M30\n%"


def wait_for(condition: Callable[[], bool], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "the control did not get there"
        time.sleep(0.01)


@pytest.fixture
def machine(tmp_path: Path) -> Iterator[SerialMachine]:
    """A control in DNC mode on a pty, not started: `start()` is the test's."""
    control = Control(ProgramStore(tmp_path / "cnc"), mode=Mode.DNC, io_channel=IoChannel.RS232,
                      block_rate=300, log_dir=tmp_path / "log")
    serial = SerialMachine(control, PtyEnd(tmp_path / "ttyCNC"), baud=BAUD)
    yield serial
    serial.close()
    control.close()


@pytest.fixture
def sender_end(machine: SerialMachine) -> Iterator[int]:
    """The PC's end of the pty, raw and unpaced: whatever is written arrives at once."""
    fd = os.open(machine.end.link, os.O_RDWR | os.O_NOCTTY)
    yield fd
    os.close(fd)


def executed(machine: SerialMachine) -> bytes:
    log = machine.control._log_dir / "executed.log"  # type: ignore[operator]
    return log.read_bytes() if log.exists() else b""


def test_a_sender_that_ignores_dc3_and_the_lines_pace_overruns_the_buffer(
        machine: SerialMachine, sender_end: int) -> None:
    # About 100 KB against a buffer of 1 KB: the line carries that in 9 s, so only a
    # control kept from looking for that long could forgive it all (a loaded host keeps it
    # from looking for a second at times: 10 KB were all forgiven then).
    data = tape(4000)
    opened = machine._looked_at
    machine.start()
    wait_for(lambda: machine._looked_at > opened)  # it looks every few milliseconds from now on

    written = 0
    while written < len(data):
        written += os.write(sender_end, data[written:])

    wait_for(lambda: machine.overflowed_bytes > 0)
    assert machine.xoff_count > 0
    assert machine.peak_buffer_bytes <= machine.buffer_bytes


def test_what_the_line_carried_while_the_control_did_not_look_is_not_lost(
        machine: SerialMachine, sender_end: int) -> None:
    # About 10 KB: ten times the buffer, and more than a pty hands over in one read (4 KB),
    # as a control thread kept from running for 0.4 s or more finds it.
    data = tape(400)
    piece = int(BAUD / 10 * 0.01)
    for offset in range(0, len(data), piece):  # at the line's pace, no faster
        os.write(sender_end, data[offset:offset + piece])
        time.sleep(0.01)

    machine.start()  # it looks only now, as a thread held up by a loaded host would

    wait_for(lambda: machine.control.state is RunState.DONE)
    assert machine.overflowed_bytes == 0
    lines = data.split(b"\n")[1:-1]
    assert executed(machine).splitlines() == lines


def test_a_control_set_to_a_slower_line_forgives_only_what_that_line_could_carry(
        tmp_path: Path) -> None:
    # The same 2 KB at 115,200 baud's pace, into a control whose line is set to 1,200 baud:
    # far more than its line could have carried while it did not look, so it overruns.
    control = Control(ProgramStore(tmp_path / "cnc"), mode=Mode.DNC, io_channel=IoChannel.RS232,
                      block_rate=300, log_dir=tmp_path / "log")
    slow = SerialMachine(control, PtyEnd(tmp_path / "ttyCNC"), baud=1_200)
    fd = os.open(slow.end.link, os.O_RDWR | os.O_NOCTTY)
    try:
        data = tape(80)
        piece = int(BAUD / 10 * 0.01)
        for offset in range(0, len(data), piece):
            os.write(fd, data[offset:offset + piece])
            time.sleep(0.01)
        slow.start()
        wait_for(lambda: slow.overflowed_bytes > 0)
    finally:
        os.close(fd)
        slow.close()
        control.close()
