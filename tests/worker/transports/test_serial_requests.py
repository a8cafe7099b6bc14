"""Machine-initiated requests over RS-232: the operator punches a request program, presses
READ (DC1) and reads dncq's answer in; over a pty pair and a raw TCP port to the simulator."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from tests.jobs.helpers import wait_until
from tests.worker.transports.serial_lines import (  # noqa: F401
    MachineFactory,
    line_to,
    serial_machine,
    url_of,
)
from worker.simulator.serial_machine import SerialMachine, TcpRawEnd
from worker.transports import eia
from worker.transports.base import (
    Permanent,
    PunchedInstead,
    TimedOut,
)
from worker.transports.optional import RequestLink
from worker.transports.serial_line import SerialTransport

REQUEST = b"%\nO8888\nN0010 (DIR=/VIPROS)\nN0020 (PRG=0010)\n%"
ANSWER = b"%\nO0010 (FROM DNCQ)\nG0 X0 Y0\nM30\n%"
LineFactory = Callable[..., SerialTransport]


def stored(machine: SerialMachine, name: str) -> bytes | None:
    path = machine.control.store.root / name
    return path.read_bytes() if path.exists() else None


def test_a_serial_line_is_a_request_link() -> None:
    assert SerialTransport.capabilities.requests
    assert issubclass(SerialTransport, RequestLink)


def test_receive_program_returns_the_punched_request_and_keeps_no_copy(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine(model="Fanuc 0i-MF")
    line = line_to(url_of(machine), baud=115_200)
    line.connect()

    machine.punch_text(REQUEST)

    assert line.receive_program(timeout_s=10) == REQUEST
    assert line.list_dir("") == []


def test_receive_program_over_a_raw_tcp_port_returns_the_request(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine(tcp_raw=True)
    line = line_to(url_of(machine), baud=115_200)
    line.connect()
    wait_until(lambda: isinstance(machine.end, TcpRawEnd) and machine.end.connected)

    machine.punch_text(REQUEST)

    assert line.receive_program(timeout_s=10) == REQUEST


def test_receive_program_is_none_when_nothing_is_punched_in_time(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine()
    line = line_to(url_of(machine), baud=115_200)

    assert line.receive_program(timeout_s=0.2) is None


def test_noise_before_the_start_of_the_tape_is_not_a_program_begun(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine()
    line = line_to(url_of(machine), baud=115_200)
    line.connect()

    machine.end.write(b"\0\0 stray\r\n")

    assert line.receive_program(timeout_s=0.3) is None


def test_a_punch_cut_before_its_end_mark_is_timed_out(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine()
    line = line_to(url_of(machine), baud=115_200, receive_timeout_s=0.3)
    line.connect()

    machine.end.write(REQUEST[:-5])  # the tape tears before its end

    with pytest.raises(TimedOut):
        line.receive_program(timeout_s=10)


def test_an_enormous_punch_is_refused_and_the_next_program_comes_through(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine()
    line = line_to(url_of(machine), baud=4_000_000, max_receive_bytes=1000)
    line.connect()
    enormous = b"%\nO9999\n" + b"G1 X1.0 Y2.0 F100\n" * 2000 + b"%"

    machine.punch_text(enormous)
    machine.punch_text(REQUEST)  # right behind it on the tape

    with pytest.raises(Permanent, match="max_receive_bytes"):
        line.receive_program(timeout_s=10)
    assert line.receive_program(timeout_s=10) == REQUEST


def test_a_stray_end_character_does_not_put_the_programs_after_it_out_of_step(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine()
    line = line_to(url_of(machine), baud=115_200, receive_timeout_s=5)
    line.connect()
    cut = b"%\nO0104 (FEED 50%)\nG0 X4\nM30\n%"  # ISO ends the tape at the comment's %

    punched = []
    for program in (cut, REQUEST, ANSWER):
        machine.end.write(b"\0" * 20 + program + b"\0" * 20)
        punched.append(line.receive_program(timeout_s=10))

    assert punched == [b"%\nO0104 (FEED 50%", REQUEST, ANSWER]


def test_an_eia_tape_after_a_lone_end_of_record_comes_through_whole(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine()
    line = line_to(url_of(machine), baud=115_200, code="eia", receive_timeout_s=5)
    line.connect()
    program = b"%\nO0010\nG0 X0 Y0\nM30\n%"

    machine.end.write(b"\0" * 20 + bytes([eia.EIA_EOR]) + b"\0" * 20)  # a torn tape's start
    machine.end.write(b"\0" * 20 + eia.encode(program) + b"\0" * 20)

    assert line.receive_program(timeout_s=10) == eia.decode(eia.encode(program))


def test_receive_punch_still_stores_what_the_operator_punched(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine()
    line = line_to(url_of(machine), baud=115_200, max_receive_bytes=10)
    line.connect()

    machine.punch_text(REQUEST)  # longer than max_receive_bytes: that is for requests

    assert line.receive_punch(timeout_s=10).name == "O8888"
    assert b"".join(line.read("O8888")) == REQUEST


def test_wait_ready_to_read_is_false_until_the_operator_presses_read(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine()
    line = line_to(url_of(machine), baud=115_200)
    line.connect()

    assert line.wait_ready_to_read(timeout_s=0.3) is False
    machine.control.press_read()
    assert line.wait_ready_to_read(timeout_s=10) is True


def test_wait_ready_to_read_ignores_what_else_the_control_sends(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine()
    line = line_to(url_of(machine), baud=115_200)
    line.connect()

    machine.end.write(b"\x13 NOT READY \x12\x14")  # DC3, text, DC2 and DC4: no DC1

    assert line.wait_ready_to_read(timeout_s=0.3) is False


@pytest.mark.parametrize("framing", [True, False])
def test_a_program_punched_instead_of_read_ends_the_wait_and_is_received_next(
        serial_machine: MachineFactory, line_to: LineFactory,  # noqa: F811
        framing: bool) -> None:
    machine = serial_machine()
    line = line_to(url_of(machine), baud=115_200, framing=framing, punch_end_silence_s=0.3)
    line.connect()

    machine.punch_text(REQUEST)  # the operator sends another request rather than READ

    with pytest.raises(PunchedInstead):
        line.wait_ready_to_read(timeout_s=10)
    got = line.receive_program(timeout_s=10)
    assert got is not None and got.strip(b"\0") == REQUEST


def test_a_read_pressed_right_after_the_request_ends_is_not_lost(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine()
    line = line_to(url_of(machine), baud=115_200)
    line.connect()

    machine.end.write(REQUEST + b"\0\0\x11")  # the end mark, trailer and DC1 in one go

    assert line.receive_program(timeout_s=10) == REQUEST
    assert line.wait_ready_to_read(timeout_s=10) is True


@pytest.mark.parametrize(("delay_s", "timeout_s", "ready"), [(0.05, 5.0, True),
                                                            (5.0, 0.05, False)])
def test_without_a_ready_signal_the_control_is_taken_as_ready_after_the_delay(
        serial_machine: MachineFactory, line_to: LineFactory,  # noqa: F811
        delay_s: float, timeout_s: float, ready: bool) -> None:
    machine = serial_machine()
    line = line_to(url_of(machine), ready_signal="none", ready_delay_s=delay_s)

    assert line.wait_ready_to_read(timeout_s=timeout_s) is ready


def test_send_to_read_replaces_the_controls_program_and_keeps_no_copy(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine(model="Fanuc 0i-MF")
    (machine.control.store.root / "O0010").write_bytes(b"%\nO0010 (OLD)\nM30\n%\n")
    line = line_to(url_of(machine), baud=115_200)
    line.connect()
    machine.control.press_read()
    assert line.wait_ready_to_read(timeout_s=10)

    line.send_to_read("O0010", ANSWER)

    wait_until(lambda: machine.received == ["O0010"])
    assert stored(machine, "O0010") == ANSWER + b"\n"
    assert not machine.control.ready_to_read  # read in: the READ is used up
    assert line.list_dir("") == []


def test_an_eia_answer_is_read_in_as_the_same_program(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine(model="Fanuc 0i-MF")
    line = line_to(url_of(machine), baud=115_200, code="eia")
    machine.control.press_read()
    assert line.wait_ready_to_read(timeout_s=10)

    line.send_to_read("O0010", ANSWER)

    wait_until(lambda: machine.received == ["O0010"])
    assert stored(machine, "O0010") == ANSWER + b"\n"


def test_a_program_sent_without_read_pressed_does_not_replace_the_controls(
        serial_machine: MachineFactory, line_to: LineFactory) -> None:  # noqa: F811
    machine = serial_machine(model="Fanuc 0i-MF")
    (machine.control.store.root / "O0010").write_bytes(b"%\nO0010 (OLD)\nM30\n%\n")
    line = line_to(url_of(machine), baud=115_200)

    line.send_to_read("O0010", ANSWER)

    wait_until(lambda: machine.last_error is not None)
    assert "O0010" in machine.last_error  # type: ignore[operator]
    assert stored(machine, "O0010") == b"%\nO0010 (OLD)\nM30\n%\n"
