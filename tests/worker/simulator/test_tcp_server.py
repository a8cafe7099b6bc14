"""The simulator's TCP server, frame by frame: every message round-trips, and bad frames,
unknown commands and oversize lengths are answered with errors, never a crash."""

from __future__ import annotations

import socket
import struct
import threading
from collections.abc import Iterator

import pytest

from tests.jobs.helpers import wait_until
from tests.worker.simulator.sim_process import Sim, SimFactory, start_sim  # noqa: F401
from worker.transports import dnc_wire as wire
from worker.transports.dnc_wire import Command, ErrorCode, Frame, HintCode, WireState


class Raw:
    """A bare client socket speaking frames."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.file = self.sock.makefile("rb")

    def send(self, command: int, payload: bytes = b"", request_id: int = 7) -> None:
        self.sock.sendall(wire.HEADER.pack(wire.MAGIC, wire.VERSION, command, 0, request_id,
                                           len(payload)) + payload)

    def frame(self) -> Frame:
        return wire.read_frame(self._exactly)

    def _exactly(self, count: int) -> bytes:
        data = self.file.read(count)
        if len(data) < count:
            raise ConnectionError("closed")
        return data

    def error(self) -> tuple[int, str]:
        frame = self.frame()
        assert frame.command is Command.ERROR, frame
        return wire.read_error(frame.payload)

    def closed(self) -> bool:
        return self.file.read(1) == b""

    def run(self, name: str, lines: list[bytes], *, total: int = 0, whole: bool = False) -> int:
        """Start a DNC run of `lines` (of `total`, 0: not said), all sent at once, and end
        its sending if `whole`; the run's id."""
        self.send(Command.UPDATE_FILE_DNC, wire.file_payload(name, total))
        started = self.frame()
        assert started.command is Command.OK, started
        self.send(Command.SEND_FILE_DNC, wire.lines_payload(1, lines))
        self.frame()
        if whole:
            self.send(Command.END_FILE_DNC)
            self.frame()
        return wire.read_uint(started.payload, 4)

    def close(self) -> None:
        self.file.close()  # the socket's file holds it open until it is closed too
        self.sock.close()


@pytest.fixture
def sim(start_sim: SimFactory) -> Sim:  # noqa: F811
    return start_sim("--block-rate", "2000")


@pytest.fixture
def raw(sim: Sim) -> Iterator[Raw]:
    client = Raw(sim.port)
    yield client
    client.close()


def test_keep_alive_is_echoed(raw: Raw) -> None:
    raw.send(Command.KEEP_ALIVE, request_id=42)
    assert raw.frame() == Frame(Command.KEEP_ALIVE, 42)


def test_upload_list_download_delete_round_trip(raw: Raw) -> None:
    data = b"%\nO0001\nG0 X0\nM30\n%\n"
    raw.send(Command.UPDATE_FILE, wire.file_payload("P1.NC", len(data)))
    assert raw.frame() == Frame(Command.GET_FILE, 7, wire.name_payload("P1.NC"))
    raw.send(Command.SEND_FILE, wire.file_payload("P1.NC", len(data)))
    raw.send(Command.FILE_DATA, data[:5])
    raw.send(Command.FILE_DATA, data[5:])
    listed = raw.frame()
    assert listed.command is Command.SEND_FILE_LIST
    assert [(f.name, f.size) for f in wire.read_list(listed.payload)] == [("P1.NC", len(data))]

    raw.send(Command.GET_FILE, wire.name_payload("P1.NC"))
    assert wire.read_file(raw.frame().payload) == ("P1.NC", len(data))
    assert raw.frame() == Frame(Command.FILE_DATA, 7, data)

    raw.send(Command.UPDATE_FILE, wire.file_payload("P1.NC", 1))
    assert raw.error()[0] == ErrorCode.EXISTS
    raw.send(Command.DELETE_FILE, wire.name_payload("P1.NC"))
    assert wire.read_list(raw.frame().payload) == []
    raw.send(Command.GET_FILE_LIST)
    assert raw.frame() == Frame(Command.SEND_FILE_LIST, 7, b"\x00\x00")


def test_an_aborted_upload_stores_nothing(raw: Raw, sim: Sim) -> None:
    raw.send(Command.UPDATE_FILE, wire.file_payload("HALF.NC", 100))
    raw.frame()
    raw.send(Command.SEND_FILE, wire.file_payload("HALF.NC", 100))
    raw.send(Command.FILE_DATA, b"x" * 50)
    raw.send(Command.ABORT_FILE)
    assert raw.frame().command is Command.OK
    raw.send(Command.GET_FILE, wire.name_payload("HALF.NC"))
    assert raw.error()[0] == ErrorCode.NOT_FOUND
    assert list(sim.root.iterdir()) == []


def test_every_dnc_message_round_trips(raw: Raw, sim: Sim) -> None:
    raw.send(Command.UPDATE_FILE_DNC, wire.file_payload("RUN.NC", 3))
    ok = raw.frame()
    assert ok.command is Command.OK and wire.read_uint(ok.payload, 4) == 1
    raw.send(Command.QUERY_FILE_DNC)
    assert wire.read_ready(raw.frame().payload) == (1, 1000)
    raw.send(Command.SEND_FILE_DNC, wire.lines_payload(1, [b"G0 X1", b"G0 X2"]))
    assert wire.read_ready(raw.frame().payload) == (3, 998)
    raw.send(Command.SEND_FILE_DNC, wire.lines_payload(2, [b"G0 X2", b"M30"]))  # 2 again
    assert wire.read_ready(raw.frame().payload) == (4, 997)
    raw.send(Command.END_FILE_DNC)
    assert raw.frame().command is Command.SEND_MAC_POS
    state = WireState.RUNNING
    while state is not WireState.DONE:
        raw.send(Command.SEND_DATA, b"\x00")
        running, loaded, state = wire.read_position(raw.frame().payload)
    assert (running, loaded) == (3, 3)
    raw.send(Command.RESUME_DNC, wire.uint_payload(1, 4))  # a finished run: nothing to take
    assert wire.read_ready(raw.frame().payload)[1] == 0
    assert sim.executed() == ["G0 X1", "G0 X2", "M30"]


def test_stop_resets_and_end_file_dnc_ends(raw: Raw, sim: Sim) -> None:
    raw.send(Command.UPDATE_FILE_DNC, wire.file_payload("RUN.NC", 0))
    raw.frame()
    raw.send(Command.SEND_FILE_DNC, wire.lines_payload(1, [b"G4 P1"] * 1000))
    raw.frame()
    raw.send(Command.SEND_DATA, b"\x01")
    assert wire.read_position(raw.frame().payload)[2] is WireState.RESET
    raw.send(Command.END_FILE_DNC)
    raw.frame()
    raw.send(Command.RESUME_DNC, wire.uint_payload(1, 4))
    assert raw.error()[0] == ErrorCode.NO_RUN
    assert sim.runs()[-1]["ended"] == "reset"


def test_a_control_in_mem_mode_answers_with_the_hint(start_sim: SimFactory) -> None:  # noqa: F811
    client = Raw(start_sim("--mode", "mem").port)
    client.send(Command.UPDATE_FILE_DNC, wire.file_payload("RUN.NC", 0))
    hint = client.frame()
    assert hint.command is Command.HINT
    assert wire.read_error(hint.payload)[0] == HintCode.NOT_DNC_MODE
    client.close()


@pytest.mark.parametrize(("command", "payload", "code"), [
    (0x99, b"anything", ErrorCode.UNKNOWN_COMMAND),
    (Command.GET_FILE, b"\x00\x09short", ErrorCode.BAD_FRAME),
    (Command.GET_FILE_LIST, b"extra", ErrorCode.BAD_FRAME),
    (Command.GET_FILE, b"\x00\x02\xff\xfe", ErrorCode.BAD_FRAME),  # not UTF-8
    (Command.SEND_DATA, b"\x07", ErrorCode.BAD_FRAME),
    (Command.KEEP_ALIVE, b"extra", ErrorCode.BAD_FRAME),  # its payload is empty
    (Command.QUERY_FILE_DNC, b"", ErrorCode.NO_RUN),
    (Command.SEND_DATA, b"\x00", ErrorCode.NO_RUN),  # no run since the control started
    (Command.END_FILE_DNC, b"", ErrorCode.NO_RUN),
    (Command.SEND_MAC_POS, b"", ErrorCode.OUT_OF_SEQUENCE),
])
def test_a_bad_request_is_answered_with_an_error_and_the_connection_goes_on(
        raw: Raw, command: int, payload: bytes, code: ErrorCode) -> None:
    raw.send(command, payload, request_id=9)
    error = raw.frame()
    assert error.command is Command.ERROR and error.request_id == 9
    assert wire.read_error(error.payload)[0] == code
    raw.send(Command.KEEP_ALIVE)
    assert raw.frame().command is Command.KEEP_ALIVE


def test_a_line_above_4096_bytes_is_a_bad_frame_and_the_run_goes_on(raw: Raw, sim: Sim) -> None:
    raw.send(Command.UPDATE_FILE_DNC, wire.file_payload("RUN.NC", 2))
    raw.frame()
    raw.send(Command.SEND_FILE_DNC, wire.lines_payload(1, [b"G0 X1", b"(" + b"x" * 4096]),
             request_id=9)
    assert raw.error()[0] == ErrorCode.BAD_FRAME
    raw.send(Command.SEND_FILE_DNC, wire.lines_payload(1, [b"G0 X1", b"(" + b"x" * 4095]))
    assert wire.read_ready(raw.frame().payload)[0] == 3  # a line of 4,096 bytes is taken


@pytest.mark.parametrize("command", [Command.KEEP_ALIVE, Command.ABORT_FILE])
def test_an_empty_frame_with_a_payload_amid_an_upload_is_a_bad_frame_and_the_upload_goes_on(
        raw: Raw, sim: Sim, command: Command) -> None:
    data = b"%\nO0001\nM30\n%\n"
    raw.send(Command.UPDATE_FILE, wire.file_payload("O0001", len(data)))
    raw.frame()
    raw.send(Command.SEND_FILE, wire.file_payload("O0001", len(data)))
    raw.send(command, b"extra", request_id=4)
    error = raw.frame()
    assert (error.command, error.request_id) == (Command.ERROR, 4)
    assert wire.read_error(error.payload)[0] == ErrorCode.BAD_FRAME
    raw.send(Command.FILE_DATA, data)
    listed = raw.frame()
    assert [f.name for f in wire.read_list(listed.payload)] == ["O0001"]


def test_a_heartbeat_sent_before_send_file_is_answered_and_the_upload_goes_on(
        raw: Raw, sim: Sim) -> None:
    # A client pings while it waits for a reply: its KEEP_ALIVE may cross GET_FILE.
    data = b"%\nO0001\nM30\n%\n"
    raw.send(Command.UPDATE_FILE, wire.file_payload("O0001", len(data)))
    raw.frame()
    raw.send(Command.KEEP_ALIVE, request_id=4)
    raw.send(Command.SEND_FILE, wire.file_payload("O0001", len(data)))
    raw.send(Command.FILE_DATA, data)
    assert raw.frame() == Frame(Command.KEEP_ALIVE, 4)
    listed = raw.frame()
    assert [f.name for f in wire.read_list(listed.payload)] == ["O0001"]


def test_an_error_from_the_client_is_not_answered(raw: Raw) -> None:
    # dncq answers a frame it cannot take with an ERROR; answering that again, with the
    # request id 0 of a frame whose header was lost, could fail whatever dncq asks next.
    raw.send(Command.ERROR, wire.error_payload(ErrorCode.BAD_FRAME, "payload too short"),
             request_id=0)
    raw.send(Command.KEEP_ALIVE, request_id=5)
    assert raw.frame() == Frame(Command.KEEP_ALIVE, 5)  # the first thing said since


@pytest.mark.parametrize(("header", "code"), [
    (wire.HEADER.pack(wire.MAGIC, 1, Command.GET_FILE, 0, 3, 10**9), ErrorCode.TOO_LONG),
    (b"XX" + bytes(12), ErrorCode.BAD_FRAME),
    (wire.HEADER.pack(wire.MAGIC, 9, Command.GET_FILE, 0, 3, 0), ErrorCode.BAD_VERSION),
])
def test_a_frame_that_loses_the_stream_is_answered_then_only_its_connection_closed(
        raw: Raw, sim: Sim, header: bytes, code: ErrorCode) -> None:
    raw.sock.sendall(header)
    assert raw.error()[0] == code
    assert raw.closed()
    again = Raw(sim.port)  # the control serves the next client
    again.send(Command.GET_FILE_LIST)
    assert again.frame().command is Command.SEND_FILE_LIST
    again.close()


def test_a_second_client_is_refused_busy(raw: Raw, sim: Sim) -> None:
    raw.send(Command.KEEP_ALIVE)
    raw.frame()
    second = Raw(sim.port)
    second.send(Command.GET_FILE_LIST)
    assert second.error()[0] == ErrorCode.BUSY
    assert second.closed()
    second.close()


def test_a_done_run_is_resumed_by_a_new_connection_while_the_old_one_is_half_open(
        raw: Raw, sim: Sim) -> None:
    run_id = raw.run("RUN.NC", [b"M30"], total=1, whole=True)
    wait_until(lambda: sim.runs(), timeout_s=30)  # done, its client still connected

    again = Raw(sim.port)  # the client back after its link dropped, the old one not seen gone
    again.send(Command.RESUME_DNC, wire.uint_payload(run_id, 4))
    resumed = again.frame()
    assert resumed.command is Command.GET_FILE_DNC, resumed
    assert wire.read_ready(resumed.payload) == (2, 0)  # nothing more to take
    assert raw.closed()
    again.send(Command.SEND_DATA, b"\x00")
    assert wire.read_position(again.frame().payload) == (1, 1, WireState.DONE)
    again.close()


def test_a_run_left_by_its_client_is_reset_after_its_grace_while_other_clients_come_and_go(
        start_sim: SimFactory) -> None:  # noqa: F811
    # Only a RESUME_DNC gives the run its client back (docs/dnc-protocol.md): another
    # client, admitted while the run has none, neither stops nor restarts its grace.
    sim = start_sim("--block-rate", "1", "--grace-s", "2", "--heartbeat-s", "0.2")
    client = Raw(sim.port)
    client.run("RUN.NC", [b"G4 P1"] * 100)
    client.close()  # 100 s of lines still to run

    def another_client_came_and_went() -> bool:
        other = Raw(sim.port)
        other.send(Command.KEEP_ALIVE)
        other.frame()  # echoed: admitted, as the run has no client
        other.close()
        return bool(sim.runs())

    wait_until(another_client_came_and_went, timeout_s=20)
    assert sim.runs()[-1]["ended"] == "abandoned"


def test_a_new_run_keeps_its_own_grace_after_a_run_that_ended_without_its_client(
        start_sim: SimFactory) -> None:  # noqa: F811
    # The grace of a run left by its client is that run's: once it ran to its end, a new
    # run started by another client is not reset when the old grace runs out.
    sim = start_sim("--block-rate", "10", "--grace-s", "1", "--heartbeat-s", "5")
    first = Raw(sim.port)
    first.run("RUN.NC", [b"G4 P1"] * 5, total=5, whole=True)
    first.close()  # its grace begins; it runs to its end in 0.5 s
    wait_until(lambda: sim.runs(), timeout_s=30)

    second = Raw(sim.port)
    second.run("NEXT.NC", [b"G4 P1"] * 100)
    threading.Event().wait(3.0)  # past the first run's grace, checked every 2.5 s
    second.send(Command.SEND_DATA, b"\x00")
    assert wire.read_position(second.frame().payload)[2] is WireState.RUNNING
    assert [r["ended"] for r in sim.runs()] == ["done"]
    second.close()


def test_garbage_then_a_new_client_does_not_crash_the_simulator(sim: Sim) -> None:
    for junk in (b"\x00", b"DQ\x01", struct.pack(">I", 0xFFFFFFFF) * 8):
        client = Raw(sim.port)
        client.sock.sendall(junk)
        client.close()
    client = Raw(sim.port)
    client.send(Command.KEEP_ALIVE)
    assert client.frame().command is Command.KEEP_ALIVE
    assert sim.process.poll() is None
    client.close()
