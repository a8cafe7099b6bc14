"""What a serial line does beyond the file primitives: punches that reach the control,
punches received from it, and drip-feed runs with XON/XOFF, over real pty pairs."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.worker.transports.contract import get, put
from tests.worker.transports.serial_lines import (  # noqa: F401
    MachineFactory,
    line_to,
    ser2net_url,
    serial_machine,
)
from worker.simulator.control import Mode, RunState
from worker.simulator.serial_machine import SerialMachine
from worker.transports import eia
from worker.transports.drip import LinkLost
from worker.transports.serial_line import SerialTransport

PROGRAM = b"%\nO1234 (FACE)\nG90 G54 G0 X0 Y0\nS1200 M3\nG1 X-10.5 F200\nM30\n%\n"


def blocks(count: int) -> list[bytes]:
    """A real-looking milling program of `count` lines, each numbered."""
    return [f"N{n} G1 X{n % 97}.125 Y-{n % 53}.5 F1200".encode() for n in range(1, count + 1)]


def wait_for(condition: Callable[[], bool], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "the control did not get there"
        time.sleep(0.01)


def executed(machine: SerialMachine) -> list[bytes]:
    log = machine.control._log_dir / "executed.log"  # type: ignore[operator]
    return log.read_bytes().splitlines() if log.exists() else []


# -- programs to and from the control ------------------------------------------------


def test_a_written_program_is_stored_by_the_control_under_its_o_number(
        serial_machine: MachineFactory, line_to: Callable[..., SerialTransport]) -> None:  # noqa: F811
    machine = serial_machine(model="Fanuc 0i-MF")
    line = line_to(str(machine.end.link), baud=115_200, end_of_line="crlf", leader_nulls=10)

    put(line, "face.nc", PROGRAM)

    wait_for(lambda: machine.received == ["O1234"])
    stored = (machine.control.store.root / "O1234").read_bytes()
    assert stored.splitlines()[1:-1] == PROGRAM.splitlines()[1:-1]
    assert get(line, "face.nc") == PROGRAM


def test_a_character_delay_paces_every_character_and_the_program_still_arrives_whole(
        serial_machine: MachineFactory, line_to: Callable[..., SerialTransport]) -> None:  # noqa: F811
    # Old controls need a pause after each character (char_delay_ms): at 115,200 baud the
    # program takes ~6 ms on the line, with 4 ms after each of its characters at least
    # len(PROGRAM) x 4 ms, a lower bound no slow host can break.
    machine = serial_machine(model="Fanuc 0i-MF")
    line = line_to(str(machine.end.link), baud=115_200, char_delay_ms=4.0)
    started = time.monotonic()

    put(line, "face.nc", PROGRAM)

    took_s = time.monotonic() - started
    wait_for(lambda: machine.received == ["O1234"])
    stored = (machine.control.store.root / "O1234").read_bytes()
    assert stored.splitlines()[1:-1] == PROGRAM.splitlines()[1:-1]
    assert took_s >= len(PROGRAM) * 0.004


def test_an_eia_punch_reaches_the_control_as_the_same_program(
        serial_machine: MachineFactory, line_to: Callable[..., SerialTransport]) -> None:  # noqa: F811
    machine = serial_machine(model="Fanuc 0i-MF")
    line = line_to(str(machine.end.link), baud=115_200, code="eia", trailer_nulls=20)

    put(line, "face.nc", PROGRAM)

    wait_for(lambda: machine.received == ["O1234"])
    assert (machine.control.store.root / "O1234").read_bytes() == PROGRAM


def test_a_program_punched_from_the_control_is_received_and_stored_under_its_name(
        serial_machine: MachineFactory, line_to: Callable[..., SerialTransport]) -> None:  # noqa: F811
    machine = serial_machine(model="Fanuc 0i-MF")
    (machine.control.store.root / "O0042").write_bytes(PROGRAM.replace(b"O1234", b"O42"))
    line = line_to(str(machine.end.link), baud=115_200)
    line.connect()

    machine.request_punch("O0042")
    entry = line.receive_punch(timeout_s=10)

    assert entry.name == "O0042"
    assert get(line, "O0042") == PROGRAM.replace(b"O1234", b"O42").strip()
    assert [e.name for e in line.list_dir("")] == ["O0042"]


def test_an_eia_punch_from_the_operator_is_decoded(
        serial_machine: MachineFactory, line_to: Callable[..., SerialTransport]) -> None:  # noqa: F811
    machine = serial_machine()
    line = line_to(str(machine.end.link), baud=115_200, code="eia")
    line.connect()

    machine.end.write(b"\0" * 8 + eia.encode(PROGRAM.strip()) + b"\0" * 8)  # the control punches
    entry = line.receive_punch(timeout_s=10)

    assert entry.name == "O1234"
    assert get(line, "O1234") == PROGRAM.strip()


# -- drip-feed ---------------------------------------------------------------------------


def test_a_drip_fed_program_is_executed_line_by_line_exactly_once_in_order(
        serial_machine: MachineFactory, line_to: Callable[..., SerialTransport]) -> None:  # noqa: F811
    machine = serial_machine(mode=Mode.DNC, block_rate=5000)
    line = line_to(str(machine.end.link), baud=115_200)
    program = blocks(1500)
    seen: list[int] = []

    result = line.drip_feed("BIG.NC", iter(program), total_lines=len(program),
                            on_line=lambda running, sent: seen.append(running),
                            should_stop=lambda: False)

    assert (result.lines_sent, result.last_line, result.stopped) == (1500, 1500, False)
    assert seen == list(range(1, 1501))
    wait_for(lambda: machine.control.state is RunState.DONE)
    assert executed(machine) == program


@pytest.mark.parametrize(("before", "after"), [
    ([b"%"], [b"%"]), ([b"", b"%"], [b"%", b""]), ([b"%  "], [b"%", b"", b"  "])])
def test_a_program_with_its_own_percent_lines_is_drip_fed_whole_and_keeps_its_numbers(
        serial_machine: MachineFactory, line_to: Callable[..., SerialTransport],  # noqa: F811
        before: list[bytes], after: list[bytes]) -> None:
    # As a program file is written: `%`, the blocks, `%`, blank lines around them as an
    # editor leaves them. The link sends its own frame; the file's first `%` sent after it
    # would end the tape before the first block, its last one open a tape never closed.
    machine = serial_machine(mode=Mode.DNC, block_rate=5000)
    line = line_to(str(machine.end.link), baud=115_200)
    program = blocks(200)
    framed = [*before, *program, *after]
    seen: list[int] = []

    result = line.drip_feed("FRAMED.NC", iter(framed), total_lines=len(framed),
                            on_line=lambda running, sent: seen.append(running),
                            should_stop=lambda: False)

    assert (result.lines_sent, result.last_line, result.stopped) == (
        len(framed), len(framed), False)
    assert seen == list(range(1, len(framed) + 1))  # the file's lines, its frame counted
    wait_for(lambda: machine.control.state is RunState.DONE)
    assert executed(machine) == program


def test_xon_xoff_pauses_the_sender_so_the_controls_buffer_never_overflows(
        serial_machine: MachineFactory, line_to: Callable[..., SerialTransport]) -> None:  # noqa: F811
    machine = serial_machine(mode=Mode.DNC, block_rate=150)  # far below the line's ~380/s
    line = line_to(str(machine.end.link), baud=115_200)
    program = blocks(600)

    line.drip_feed("SLOW.NC", iter(program), total_lines=len(program),
                   on_line=lambda *_: None, should_stop=lambda: False)

    wait_for(lambda: machine.control.state is RunState.DONE)
    assert machine.xoff_count > 0  # the control did hold the line
    assert machine.overflowed_bytes == 0
    assert executed(machine) == program


def test_stop_ends_the_run_after_a_whole_line_with_the_end_of_tape(
        serial_machine: MachineFactory, line_to: Callable[..., SerialTransport]) -> None:  # noqa: F811
    machine = serial_machine(mode=Mode.DNC, block_rate=400)
    line = line_to(str(machine.end.link), baud=115_200)
    program = blocks(5000)
    running = [0]

    def note(line_no: int, sent: int) -> None:
        running[0] = line_no

    result = line.drip_feed("LONG.NC", iter(program), total_lines=len(program),
                            on_line=note, should_stop=lambda: running[0] >= 300)

    assert result.stopped and result.lines_sent == result.last_line == 300
    assert result.stop_said.startswith("the end of the tape was sent")  # not "reset"
    wait_for(lambda: machine.control.state is RunState.DONE)
    assert executed(machine) == program[:300]


def test_a_stop_while_the_control_holds_the_line_still_ends_the_tape_after_a_whole_line(
        serial_machine: MachineFactory, line_to: Callable[..., SerialTransport]) -> None:  # noqa: F811
    # A control slower than the line holds it (XOFF) most of the time: a stop nearly always
    # comes during a hold. The tape must still end, so that the control ends the run and
    # the next run's start is not taken as this one's end.
    machine = serial_machine(mode=Mode.DNC, block_rate=100)
    line = line_to(str(machine.end.link), baud=115_200)
    program = blocks(3000)
    stop = threading.Event()

    def note(line_no: int, sent: int) -> None:
        if line_no == 600:  # the operator's stop comes a moment later, not with a line
            threading.Timer(0.05, stop.set).start()

    result = line.drip_feed("HELD.NC", iter(program), total_lines=len(program),
                            on_line=note, should_stop=stop.is_set)

    assert result.stopped and result.stop_said.startswith("the end of the tape was sent")
    assert machine.xoff_count > 0  # the control did hold the line
    wait_for(lambda: machine.control.state is RunState.DONE, timeout_s=60)
    assert executed(machine) == program[:result.last_line]


def test_a_line_held_past_the_send_timeout_is_link_lost_with_its_last_line(
        serial_machine: MachineFactory, line_to: Callable[..., SerialTransport]) -> None:  # noqa: F811
    machine = serial_machine(mode=Mode.DNC, block_rate=0.001)  # feed hold: nothing executes
    line = line_to(str(machine.end.link), baud=115_200, send_timeout_s=1.0)
    sent: list[int] = []

    with pytest.raises(LinkLost) as lost:
        line.drip_feed("HELD.NC", iter(blocks(2000)), total_lines=2000,
                       on_line=lambda running, count: sent.append(running),
                       should_stop=lambda: False)

    assert 0 < lost.value.last_line == sent[-1] < 2000
    assert machine.overflowed_bytes == 0


def test_a_drip_feed_through_ser2net_executes_every_line_once_without_overflow(
        serial_machine: MachineFactory, line_to: Callable[..., SerialTransport],  # noqa: F811
        ser2net_url: Callable[[SerialMachine], str]) -> None:  # noqa: F811
    # A pty has no baud rate: ser2net writes to it whatever it read, at once. On a loaded
    # host it is held up now and then, and sends what it gathered meanwhile in one burst,
    # DC3 or not, as a device server that stalled would through its UART; this control's
    # buffer has room for a stall of about 180 ms at 115,200 baud past its DC3.
    machine = serial_machine(mode=Mode.DNC, block_rate=150, buffer_bytes=4096)
    line = line_to(ser2net_url(machine), baud=115_200)
    program = blocks(450)  # 13 KB, three times the buffer

    line.drip_feed("NET.NC", iter(program), total_lines=len(program),
                   on_line=lambda *_: None, should_stop=lambda: False)

    wait_for(lambda: machine.control.state is RunState.DONE)
    assert machine.xoff_count > 0 and machine.overflowed_bytes == 0
    assert executed(machine) == program


def test_a_device_server_that_drops_the_connection_ends_the_run_with_its_last_line(
        serial_machine: MachineFactory, line_to: Callable[..., SerialTransport],  # noqa: F811
        ser2net_url: Callable[[SerialMachine], str], tmp_path: Path) -> None:  # noqa: F811
    machine = serial_machine(mode=Mode.DNC, block_rate=300)
    line = line_to(ser2net_url(machine), baud=115_200)
    program = blocks(3000)
    sent: list[int] = []

    def note(running: int, count: int) -> None:
        sent.append(running)
        if running == 200:  # the device server dies mid-run
            os.kill(int((tmp_path / "ser2net0.pid").read_text()), signal.SIGKILL)

    with pytest.raises(LinkLost) as lost:
        line.drip_feed("CUT.NC", iter(program), total_lines=len(program), on_line=note,
                       should_stop=lambda: False)

    assert 200 <= lost.value.last_line == sent[-1] < len(program)
    time.sleep(1.0)  # the control works off what reached it
    done = executed(machine)
    assert done == program[:len(done)]  # in order, none twice, none skipped
    assert len(done) <= lost.value.last_line  # nothing ran that the run did not count as sent


def test_the_registry_opens_a_serial_line_with_its_state_folder_in_the_data_dir(
        tmp_path: Path) -> None:
    from worker.transports import open_transport

    line = open_transport("serial", {"url": "socket://127.0.0.1:9"}, machine_id="2001",
                          data_dir=tmp_path)

    assert isinstance(line, SerialTransport)
    assert line.programs == tmp_path / "serial" / "2001" / "programs"
    assert line.list_dir("") == []  # the line itself is opened only to punch or receive
