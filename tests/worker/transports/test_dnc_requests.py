"""Machine-initiated requests over the seed protocol: QUERY_PUNCH brings what the operator
punched, QUERY_READ says READ was pressed, READ_IN sends the answer; against the simulator's
TCP server in this process, so a test can press the control's keys."""

from __future__ import annotations

import socket
import struct
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from tests.jobs.helpers import wait_until
from tests.worker.simulator.test_tcp_server import Raw
from worker.simulator.control import Control
from worker.simulator.programs import ProgramStore
from worker.simulator.tcp_server import DncServer
from worker.transports import dnc_wire as wire
from worker.transports.base import (
    BadPath,
    Permanent,
    Transient,
)
from worker.transports.dnc import DncOptions, DncTransport
from worker.transports.dnc_link import ControlError
from worker.transports.dnc_wire import Command, ErrorCode, Frame, HintCode
from worker.transports.optional import RequestLink

REQUEST = b"%\nO8888\nN0010 (DIR=/VIPROS)\nN0020 (PRG=0010)\n%"
ANSWER = b"%\nO0010 (FROM DNCQ)\nG0 X0 Y0\nM30\n%"


@dataclass
class Cnc:
    control: Control
    server: DncServer
    link: Callable[..., DncTransport]

    @property
    def root(self) -> Path:
        return self.control.store.root


@pytest.fixture
def cnc(tmp_path: Path) -> Iterator[Cnc]:
    control = Control(ProgramStore(tmp_path / "root", model="Fanuc 0i-F"))
    server = DncServer(control, heartbeat_s=0.5)
    server.start()
    opened: list[DncTransport] = []

    def link(**options: Any) -> DncTransport:
        settings = {"host": "127.0.0.1", "port": server.port, "timeout_s": 10.0,
                    "heartbeat_interval_s": 0.5, "poll_interval_s": 0.01} | options
        opened.append(DncTransport(DncOptions.model_validate(settings)))
        return opened[-1]

    yield Cnc(control, server, link)
    for made in opened:
        made.close()
    server.close()
    control.close()


def hang_up(client: Raw, *, reset: bool = False) -> None:
    """Close a raw client's connection for real (its file holds the socket open too)."""
    if reset:  # a reset at once, whatever is still unsent to it
        client.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    client.file.close()
    client.close()


def admitted(port: int) -> Raw:
    """A raw client once the control takes one (the one before it was let go)."""
    found: list[Raw] = []

    def try_once() -> bool:
        client = Raw(port)
        client.send(Command.KEEP_ALIVE)
        if client.frame().command is Command.KEEP_ALIVE:
            found.append(client)
            return True
        client.close()  # BUSY: the control still holds the other client
        return False

    wait_until(try_once)
    return found[0]


def test_a_dnc_link_is_a_request_link() -> None:
    assert DncTransport.capabilities.requests
    assert issubclass(DncTransport, RequestLink)


# -- programs the operator punches -------------------------------------------------------


def test_receive_program_returns_the_punched_request_and_empties_the_outbox(cnc: Cnc) -> None:
    cnc.server.punch_text(REQUEST)
    dnc = cnc.link()

    assert dnc.receive_program(timeout_s=10) == REQUEST
    dnc.list_dir("")  # answered after the control is done with the punch
    assert cnc.control.outbox_length == 0


def test_receive_program_is_none_when_nothing_is_punched_in_time(cnc: Cnc) -> None:
    assert cnc.link().receive_program(timeout_s=0.2) is None


def test_punched_programs_come_oldest_first(cnc: Cnc) -> None:
    (cnc.root / "O0042").write_bytes(ANSWER)
    cnc.server.request_punch("O0042")
    cnc.server.punch_text(REQUEST)
    dnc = cnc.link()

    assert [dnc.receive_program(timeout_s=10), dnc.receive_program(timeout_s=10)] == [
        ANSWER, REQUEST]


def test_an_enormous_punch_is_refused_and_the_next_program_comes_through(cnc: Cnc) -> None:
    cnc.server.punch_text(b"%\nO9999\n" + b"G1 X1.0 Y2.0 F100\n" * 20_000 + b"%")
    cnc.server.punch_text(REQUEST)
    dnc = cnc.link(max_receive_bytes=1000)

    with pytest.raises(Permanent, match="max_receive_bytes"):
        dnc.receive_program(timeout_s=10)
    assert dnc.receive_program(timeout_s=10) == REQUEST


def test_a_punch_the_control_stops_sending_midway_is_a_transient_failure() -> None:
    listener = socket.create_server(("127.0.0.1", 0))
    held: list[socket.socket] = []

    def control_that_stalls() -> None:
        conn, _ = listener.accept()
        held.append(conn)
        header = wire.HEADER.unpack(conn.recv(wire.HEADER.size))
        request_id = header[4]
        conn.sendall(wire.encode(Command.SEND_FILE, request_id, wire.file_payload("O8888", 100))
                     + wire.encode(Command.FILE_DATA, request_id, b"%\nO8888\n"))
        # ... and nothing more: no data, no answer to pings

    threading.Thread(target=control_that_stalls, daemon=True).start()
    dnc = DncTransport(DncOptions(host="127.0.0.1", port=listener.getsockname()[1],
                                  timeout_s=5, heartbeat_interval_s=0.2, ping_checks=2))
    try:
        with pytest.raises(Transient):
            dnc.receive_program(timeout_s=10)
    finally:
        dnc.close()
        listener.close()
        for conn in held:
            conn.close()


def test_a_punch_is_kept_when_the_connection_is_lost_midway(cnc: Cnc) -> None:
    big = b"%\nO7777\n" + b"G1 X1.0 Y2.0 F100\n" * 1_000_000 + b"%"  # beyond socket buffers
    cnc.control.punch("O7777", big)
    raw = Raw(cnc.server.port)
    raw.send(Command.QUERY_PUNCH)
    assert wire.read_file(raw.frame().payload) == ("O7777", len(big))
    hang_up(raw, reset=True)  # with most of the program unsent

    again = admitted(cnc.server.port)
    assert cnc.control.outbox_length == 1
    again.send(Command.QUERY_PUNCH)
    assert wire.read_file(again.frame().payload) == ("O7777", len(big))
    received = 0
    while received < len(big):
        received += len(again.frame().payload)
    again.send(Command.KEEP_ALIVE)
    again.frame()  # the control has gone past the program
    assert cnc.control.outbox_length == 0
    again.close()


# -- READ and the answer read in -----------------------------------------------------------


def test_wait_ready_to_read_is_false_until_the_operator_presses_read(cnc: Cnc) -> None:
    dnc = cnc.link()

    assert dnc.wait_ready_to_read(timeout_s=0.2) is False
    cnc.control.press_read()
    assert dnc.wait_ready_to_read(timeout_s=10) is True


def test_query_read_answers_hint_wait_before_read_and_ok_after(cnc: Cnc) -> None:
    raw = Raw(cnc.server.port)
    raw.send(Command.QUERY_READ)
    hint = raw.frame()
    assert hint.command is Command.HINT
    assert wire.read_error(hint.payload)[0] == HintCode.WAIT

    cnc.control.press_read()
    raw.send(Command.QUERY_READ)
    assert raw.frame() == Frame(Command.OK, 7)
    raw.close()


def test_the_link_serves_other_calls_while_it_waits_for_read(cnc: Cnc) -> None:
    dnc = cnc.link()
    waited: list[bool] = []
    waiter = threading.Thread(target=lambda: waited.append(
        dnc.wait_ready_to_read(timeout_s=30)))
    waiter.start()

    listed = dnc.list_dir("")  # the wait holds the link for one poll at a time only
    still_waiting = waiter.is_alive()
    cnc.control.press_read()
    waiter.join(30)

    assert listed == [] and still_waiting and waited == [True]


def test_send_to_read_replaces_the_controls_program_and_ends_the_read(cnc: Cnc) -> None:
    (cnc.root / "O0010").write_bytes(b"%\nO0010 (OLD)\nM30\n%\n")
    cnc.control.press_read()
    dnc = cnc.link()

    dnc.send_to_read("O0010", ANSWER)

    assert (cnc.root / "O0010").read_bytes() == ANSWER
    assert not cnc.control.ready_to_read
    assert dnc.wait_ready_to_read(timeout_s=0.1) is False


def test_read_in_when_the_control_is_not_ready_is_refused_and_the_link_goes_on(
        cnc: Cnc) -> None:
    dnc = cnc.link()

    with pytest.raises(ControlError) as refused:
        dnc.send_to_read("O0010", ANSWER)

    assert refused.value.code == ErrorCode.OUT_OF_SEQUENCE
    assert dnc.list_dir("") == []


def test_read_in_of_a_name_the_control_cannot_store_is_bad_path(cnc: Cnc) -> None:
    cnc.control.press_read()
    dnc = cnc.link()

    with pytest.raises(BadPath):
        dnc.send_to_read("ANSWER.NC", ANSWER)

    assert cnc.control.ready_to_read and dnc.list_dir("") == []


def test_a_connection_dropped_mid_read_in_stores_nothing(cnc: Cnc) -> None:
    (cnc.root / "O0010").write_bytes(b"%\nO0010 (OLD)\nM30\n%\n")
    cnc.control.press_read()
    raw = Raw(cnc.server.port)
    raw.send(Command.READ_IN, wire.file_payload("O0010", 100))
    assert raw.frame() == Frame(Command.GET_FILE, 7, wire.name_payload("O0010"))
    raw.send(Command.SEND_FILE, wire.file_payload("O0010", 100))
    raw.send(Command.FILE_DATA, b"x" * 50)
    hang_up(raw)

    admitted(cnc.server.port).close()  # the control has let the dropped client go

    assert [p.name for p in cnc.root.iterdir()] == ["O0010"]
    assert (cnc.root / "O0010").read_bytes() == b"%\nO0010 (OLD)\nM30\n%\n"
    assert cnc.control.ready_to_read
