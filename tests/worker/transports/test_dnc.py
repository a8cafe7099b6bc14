"""The `dnc` transport passes the conformance suite against the simulator (its own process)."""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Callable, Iterator

import pytest

from tests.worker.simulator.sim_process import SimFactory, start_sim  # noqa: F401
from tests.worker.transports.contract import *  # noqa: F403
from tests.worker.transports.contract import put
from worker.transports import dnc_wire as wire
from worker.transports import kind
from worker.transports.base import BadPath, Dropped, Permanent, TimedOut, Unsupported
from worker.transports.dnc import DncOptions, DncTransport
from worker.transports.drip import DripFeeder


@pytest.fixture
def transport(start_sim: SimFactory) -> Iterator[DncTransport]:  # noqa: F811
    dnc = start_sim().transport()
    yield dnc
    dnc.close()


def test_the_registry_opens_it_by_name() -> None:
    assert kind("dnc").cls is DncTransport


def test_it_is_a_drip_feeder_without_folders(transport: DncTransport) -> None:
    assert isinstance(transport, DripFeeder) and transport.capabilities.drip_feed
    with pytest.raises(Unsupported):
        transport.make_dir("SUB")


def test_one_connection_serves_many_calls(transport: DncTransport) -> None:
    for number in range(5):
        put(transport, f"P{number}.nc", b"G0\n")
        transport.list_dir("")
    assert len(transport.list_dir("")) == 5


def test_a_read_taken_up_on_another_thread_leaves_the_machine_free(
        transport: DncTransport) -> None:
    # As the API streams a download: the first chunk on the request's thread, the rest
    # read ahead on another. The next caller (a third thread) must get the link.
    data = b"G0 X1.\n" * 30_000
    put(transport, "BIG.nc", data)
    chunks = transport.read("BIG.nc")
    first = next(chunks)
    rest: list[bytes] = []
    ahead = threading.Thread(target=lambda: rest.extend(chunks), daemon=True)
    ahead.start()
    ahead.join(30)
    listed: list[str] = []
    after = threading.Thread(target=lambda: listed.extend(
        e.name for e in transport.list_dir("")), daemon=True)
    after.start()
    after.join(30)

    assert not ahead.is_alive() and first + b"".join(rest) == data
    assert not after.is_alive() and listed == ["BIG.nc"]


def test_a_name_the_model_does_not_take_is_bad_path(start_sim: SimFactory) -> None:  # noqa: F811
    fanuc = start_sim("--model", "Fanuc 0i-F").transport()
    put(fanuc, "O1234", b"%\nO1234\nM30\n%\n")
    with pytest.raises(BadPath):
        put(fanuc, "PART.nc", b"G0\n")
    assert [e.name for e in fanuc.list_dir("")] == ["O1234"]
    fanuc.close()


@pytest.fixture
def bad_control() -> Iterator[tuple[int, list[bytes]]]:
    """A listener that answers every connection with the next of `replies` (raw bytes)."""
    listener = socket.create_server(("127.0.0.1", 0))
    replies: list[bytes] = []

    def serve() -> None:
        while True:
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            conn.recv(65536)
            conn.sendall(replies.pop(0) if replies else b"")
            conn.close()

    threading.Thread(target=serve, daemon=True).start()
    yield listener.getsockname()[1], replies
    listener.close()


@pytest.mark.parametrize("reply", [
    wire.HEADER.pack(wire.MAGIC, 1, wire.Command.SEND_FILE_LIST, 0, 1, 10**9),  # oversize
    b"garbage that is no frame at all",
    wire.HEADER.pack(wire.MAGIC, 1, 0x77, 0, 1, 0),  # unknown command
])
def test_a_control_that_answers_nonsense_is_a_dropped_link_not_a_crash(
        bad_control: tuple[int, list[bytes]], reply: bytes) -> None:
    port, replies = bad_control
    replies.append(reply)
    dnc = DncTransport(DncOptions(host="127.0.0.1", port=port, timeout_s=5,
                                  heartbeat_interval_s=0.5))
    with pytest.raises(Dropped):
        dnc.list_dir("")
    dnc.close()


@contextlib.contextmanager
def scripted_control(script: Callable[[socket.socket, Callable[[], wire.Frame]], None],
                     *, timeout_s: float = 5, heartbeat_interval_s: float = 60
                     ) -> Iterator[DncTransport]:
    """A transport to a control on loopback that plays `script` on its one connection (the
    connection, and a reader of the next frame from it); the script has ended on leaving."""
    listener = socket.create_server(("127.0.0.1", 0))

    def control() -> None:
        conn, _ = listener.accept()
        with conn:
            stream = conn.makefile("rb")
            script(conn, lambda: wire.read_frame(stream.read))

    serving = threading.Thread(target=control, daemon=True)
    serving.start()
    dnc = DncTransport(DncOptions(host="127.0.0.1", port=listener.getsockname()[1],
                                  timeout_s=timeout_s,
                                  heartbeat_interval_s=heartbeat_interval_s))
    try:
        yield dnc
        serving.join(5)
    finally:
        dnc.close()
        listener.close()


def test_a_command_of_a_later_revision_is_answered_unknown_and_the_link_goes_on() -> None:
    # Version 1 may gain commands: a side that does not know one answers UNKNOWN_COMMAND
    # and goes on (docs/dnc-protocol.md). Dropping the link for it met it again on resume.
    answered: list[wire.Frame] = []

    def control(conn: socket.socket, frame: Callable[[], wire.Frame]) -> None:
        request = frame()
        conn.sendall(wire.HEADER.pack(wire.MAGIC, 1, 0x40, 0, 7, 2) + b"hi")  # a new one
        conn.sendall(wire.encode(wire.Command.SEND_FILE_LIST, request.request_id,
                                 wire.list_payloads([wire.ListedFile("P1.nc", 3, 0)])[0]))
        answered.append(frame())

    with scripted_control(control) as dnc:
        assert [e.name for e in dnc.list_dir("")] == ["P1.nc"]

    [told] = answered
    assert (told.command, told.request_id) == (wire.Command.ERROR, 7)
    assert wire.read_error(told.payload)[0] == wire.ErrorCode.UNKNOWN_COMMAND


def test_a_short_get_file_dnc_is_answered_bad_frame_and_the_link_goes_on() -> None:
    # A payload that does not decode is BAD_FRAME; the frame was read whole, so neither
    # side stops serving over it (docs/dnc-protocol.md).
    told: list[wire.Frame] = []

    def control(conn: socket.socket, frame: Callable[[], wire.Frame]) -> None:
        start = frame()  # UPDATE_FILE_DNC
        conn.sendall(wire.encode(wire.Command.OK, start.request_id, wire.uint_payload(7, 4)))
        query = frame()  # QUERY_FILE_DNC
        conn.sendall(wire.encode(wire.Command.GET_FILE_DNC, query.request_id, b"\0\0\0\1"))
        told.append(frame())
        listing = frame()  # on the same connection
        conn.sendall(wire.encode(wire.Command.SEND_FILE_LIST, listing.request_id,
                                 wire.list_payloads([wire.ListedFile("P1.nc", 3, 0)])[0]))
        told.append(query)

    with scripted_control(control) as dnc:
        with pytest.raises(Permanent, match="bad GET_FILE_DNC"):
            dnc.drip_feed("P1.nc", [b"G0 X1"], total_lines=1, on_line=lambda *_: None,
                          should_stop=lambda: False)
        assert [e.name for e in dnc.list_dir("")] == ["P1.nc"]

    answer, query = told
    assert (answer.command, answer.request_id) == (wire.Command.ERROR, query.request_id)
    assert wire.read_error(answer.payload)[0] == wire.ErrorCode.BAD_FRAME


def test_a_control_ping_with_a_payload_is_answered_bad_frame_not_keep_alive() -> None:
    # KEEP_ALIVE's payload is empty: one with bytes is BAD_FRAME (docs/dnc-protocol.md),
    # as the control answers a client's. It answers no request, so the listing goes on.
    told: list[wire.Frame] = []

    def control(conn: socket.socket, frame: Callable[[], wire.Frame]) -> None:
        request = frame()  # GET_FILE_LIST
        conn.sendall(wire.encode(wire.Command.KEEP_ALIVE, 0, b"ping"))
        told.append(frame())
        conn.sendall(wire.encode(wire.Command.SEND_FILE_LIST, request.request_id,
                                 wire.list_payloads([wire.ListedFile("P1.nc", 3, 0)])[0]))

    with scripted_control(control) as dnc:
        assert [e.name for e in dnc.list_dir("")] == ["P1.nc"]

    [answer] = told
    assert (answer.command, answer.request_id) == (wire.Command.ERROR, 0)
    assert wire.read_error(answer.payload)[0] == wire.ErrorCode.BAD_FRAME


def test_an_answer_to_a_ping_check_with_a_payload_is_answered_bad_frame() -> None:
    # dncq's ping check (a KEEP_ALIVE sent while it waits) is answered by an empty
    # KEEP_ALIVE; one with bytes is a bad frame (docs/dnc-protocol.md). The control still
    # answered, so the listing it waits for goes on.
    told: list[wire.Frame] = []

    def control(conn: socket.socket, frame: Callable[[], wire.Frame]) -> None:
        request = frame()  # GET_FILE_LIST
        probe = frame()  # the ping check after a heartbeat interval of silence
        conn.sendall(wire.encode(wire.Command.KEEP_ALIVE, probe.request_id, b"pong"))
        told.extend([probe, frame()])
        conn.sendall(wire.encode(wire.Command.SEND_FILE_LIST, request.request_id,
                                 wire.list_payloads([wire.ListedFile("P1.nc", 3, 0)])[0]))

    with scripted_control(control, heartbeat_interval_s=0.2) as dnc:
        assert [e.name for e in dnc.list_dir("")] == ["P1.nc"]

    probe, answer = told
    assert probe.command is wire.Command.KEEP_ALIVE
    assert (answer.command, answer.request_id) == (wire.Command.ERROR, probe.request_id)
    assert wire.read_error(answer.payload)[0] == wire.ErrorCode.BAD_FRAME


def test_an_answer_to_a_ping_check_of_another_kind_is_out_of_step() -> None:
    # A KEEP_ALIVE is answered by a KEEP_ALIVE: a control that answers it with anything
    # else has lost track of what it answers, as for any reply of the wrong kind.
    def control(conn: socket.socket, frame: Callable[[], wire.Frame]) -> None:
        frame()  # GET_FILE_LIST
        probe = frame()
        conn.sendall(wire.encode(wire.Command.OK, probe.request_id))
        conn.recv(1)  # until the client leaves

    with scripted_control(control, heartbeat_interval_s=0.2) as dnc:
        with pytest.raises(Dropped, match="answered a KEEP_ALIVE with OK"):
            dnc.list_dir("")


def test_a_link_check_answered_with_a_payload_reports_no_heartbeat() -> None:
    # The machine's link check (dncq machines check) says the control answered wrongly,
    # and the control is told BAD_FRAME, as for any frame whose payload does not decode.
    told: list[wire.Frame] = []

    def control(conn: socket.socket, frame: Callable[[], wire.Frame]) -> None:
        ping = frame()
        conn.sendall(wire.encode(wire.Command.KEEP_ALIVE, ping.request_id, b"pong"))
        told.append(frame())

    with scripted_control(control) as dnc:
        report = dnc.link_report()

    assert not report.heartbeat and "bad KEEP_ALIVE" in (report.error or "")
    [answer] = told
    assert (answer.command, wire.read_error(answer.payload)[0]) == (
        wire.Command.ERROR, wire.ErrorCode.BAD_FRAME)


def test_a_download_the_control_sends_past_its_size_is_dropped_not_returned_longer() -> None:
    # FILE_DATA frames come until the bytes received equal SEND_FILE's size (the seed,
    # S34): more than that is no file of that size, and not handed on as one.
    def control(conn: socket.socket, frame: Callable[[], wire.Frame]) -> None:
        request = frame()  # GET_FILE
        conn.sendall(wire.encode(wire.Command.SEND_FILE, request.request_id,
                                 wire.file_payload("P1.nc", 3))
                     + wire.encode(wire.Command.FILE_DATA, request.request_id, b"G0 X1"))

    with scripted_control(control) as dnc:
        with pytest.raises(Dropped, match="5 bytes of P1.nc, not 3"):
            b"".join(dnc.read("P1.nc"))


def test_a_silent_control_is_timed_out_at_timeout_s_not_a_heartbeat_later() -> None:
    # timeout_s bounds each wait for an answer (docs/fleet.md), also when the heartbeat
    # interval (60 s here) is longer: a read never waits a whole interval past it.
    def control(conn: socket.socket, frame: Callable[[], wire.Frame]) -> None:
        frame()  # GET_FILE_LIST, never answered
        conn.recv(1)  # silent until the client gives up

    failed: list[Exception] = []

    def list_dir(dnc: DncTransport) -> None:
        try:
            dnc.list_dir("")
        except Exception as exc:  # noqa: BLE001
            failed.append(exc)

    with scripted_control(control, timeout_s=0.2) as dnc:
        waiting = threading.Thread(target=list_dir, args=(dnc,), daemon=True)
        waiting.start()
        waiting.join(20)

        assert not waiting.is_alive()
        [error] = failed
        assert isinstance(error, TimedOut) and "timeout_s" in str(error)
