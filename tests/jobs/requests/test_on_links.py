"""Requests an operator sends from the control, end to end over its link.

The control is the simulator of the DNC links: on a pseudo-terminal for RS-232 (its
operator punches the request, then presses READ) and over the seed's TCP protocol. The
listener is a worker's (`worker.listener`), on a real database; what the control stores
is read from the simulated control's own program memory.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from sqlalchemy import func, select

from jobs.db import session_scope
from jobs.inbox import service as inbox
from jobs.library import blobs
from jobs.models import Job, JobState, MachineLease
from jobs.run import leases
from tests.jobs.helpers import wait_until
from tests.jobs.requests.conftest import O0010, SEED_REQUEST, request_jobs, wait_for_jobs
from tests.worker.transports.serial_lines import serial_machine  # noqa: F401
from worker.listener import Listeners
from worker.simulator.control import Control, IoChannel, Mode
from worker.simulator.programs import ProgramStore
from worker.simulator.tcp_server import DncServer


def stored(control: Control, name: str) -> bytes | None:
    try:
        with control.store.open(name) as source:
            return source.read()
    except Exception:
        return None


def listened(settings: Any, machine_id: str) -> bool:
    with session_scope(settings.resolved_database_url) as session:
        return session.query(MachineLease).filter(
            MachineLease.machine_id == machine_id,
            MachineLease.group == leases.listen_group(machine_id)).count() == 1


def same_program(got: bytes | None, text: str) -> bool:
    """The program as the control holds it: its lines, framing and line ends aside."""
    def lines(data: str) -> list[str]:
        return [x.strip() for x in data.splitlines() if x.strip() and x.strip() != "%"]
    return got is not None and lines(got.decode()) == lines(text)


def press_read_when_asked(settings: Any, control: Control, *, count: int = 1) -> threading.Thread:
    """The operator: once the request is being answered, switches to receive, `count` times."""
    def operator() -> None:
        for _ in range(count):
            wait_until(lambda: request_jobs(settings, finished=False), timeout_s=30)
            time.sleep(0.3)
            control.press_read()
            wait_until(lambda: not control.ready_to_read, timeout_s=30)
    thread = threading.Thread(target=operator, daemon=True)
    thread.start()
    return thread


@pytest.fixture
def rs232(settings, add_machines, serial_machine, listening):  # noqa: F811
    """A Fanuc on an RS-232 pty whose operator may send requests; dncq listening on it."""
    line = serial_machine(mode=Mode.EDIT, model="Fanuc 0i-F")

    def start(**requests: Any) -> Any:
        add_machines({"id": "2002", "name": "RS232-J", "model": "Fanuc 0i-F",
                      "transport": "serial",
                      "options": {"url": str(line.end.link), "baud": 115200},
                      "requests": {"enabled": True, **requests}})
        listening.tick()
        wait_until(lambda: listening.hearing("2002"))
        return line
    return start


@pytest.fixture
def tcp_control(settings, add_machines, listening, tmp_path) -> Iterator[Any]:
    """A Fanuc on the seed's TCP protocol whose operator may send requests; dncq listening."""
    control = Control(ProgramStore(tmp_path / "cnc-dnc", model="Fanuc 0i-F"), mode=Mode.EDIT,
                      io_channel=IoChannel.NETWORK)
    server = DncServer(control, host="127.0.0.1", port=0)
    server.start()

    def start(**requests: Any) -> DncServer:
        add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                      "options": {"host": "127.0.0.1", "port": server.port,
                                  "poll_interval_s": 0.05},
                      "requests": {"enabled": True, **requests}})
        listening.tick()
        wait_until(lambda: listening.hearing("2001"))
        return server

    yield start
    listening.stop()
    server.close()
    control.close()


def test_the_seeds_request_over_rs232_gets_the_program_from_the_folder_asked_for(
        settings, rs232, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    line = rs232()
    operator = press_read_when_asked(settings, line.control)
    line.punch_text(SEED_REQUEST)

    [job] = wait_for_jobs(settings, 1)
    operator.join(10)
    assert job["state"] == "succeeded" and job["fileName"] == "O8888"
    [target] = job["targets"]
    assert (target["action"], target["folder"], target["fileName"]) == ("send", "VIPROS", "0010")
    assert target["answer"] == "O0010" and target["statusMsg"] == "sent library VIPROS/0010"
    assert same_program(stored(line.control, "O0010"), O0010)


def test_the_seeds_request_over_the_dnc_link_gets_the_program(
        settings, tcp_control, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    server = tcp_control()
    operator = press_read_when_asked(settings, server.control)
    server.punch_text(SEED_REQUEST)

    [job] = wait_for_jobs(settings, 1)
    operator.join(10)
    assert job["state"] == "succeeded", job
    assert same_program(stored(server.control, "O0010"), O0010)


def test_a_missing_program_is_answered_with_an_error_program_the_operator_can_read(
        settings, rs232) -> None:
    line = rs232()
    operator = press_read_when_asked(settings, line.control)
    line.punch_text(SEED_REQUEST)

    [job] = wait_for_jobs(settings, 1)
    operator.join(10)
    assert job["state"] == "failed" and job["targets"][0]["errorCode"] == 158
    error = stored(line.control, "O8890")
    assert error is not None and b"(NOT FOUND: VIPROS/0010)" in error


def test_a_listing_request_answers_the_folders_programs_as_a_program(
        settings, rs232, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    add_program("VIPROS", "0020", "%\nO0020\nM30\n%\n")
    line = rs232()
    operator = press_read_when_asked(settings, line.control)
    line.punch_text(b"%\nO8888\nN10 (DIR=/VIPROS)\nN20 (LST=)\n%\n")

    [job] = wait_for_jobs(settings, 1)
    operator.join(10)
    assert job["state"] == "succeeded", job
    listing = stored(line.control, "O8889")
    assert listing is not None
    assert b"0010" in listing and b"0020" in listing and listing.lstrip(b"%\n").startswith(b"O8889")


def test_an_operator_who_never_switches_to_receive_ends_the_request_failed(
        settings, rs232, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    line = rs232(switch_window_s=1.5)
    line.punch_text(SEED_REQUEST)

    [job] = wait_for_jobs(settings, 1)
    [target] = job["targets"]
    assert job["state"] == "failed" and target["errorCode"] == 20005
    assert "not switched to receive within 1.5 s" in target["statusMsg"]
    assert stored(line.control, "O0010") is None


def test_a_program_punched_while_the_answer_waits_for_read_is_received_not_lost(
        settings, rs232, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    line = rs232()
    line.punch_text(SEED_REQUEST)
    wait_until(lambda: request_jobs(settings, finished=False), timeout_s=30)
    time.sleep(0.3)  # the answer waits for READ

    line.punch_text(b"%\nO1234 (EDITED WHILE DNCQ WAITED)\nG0 X5.\nM30\n%\n")

    request, received = wait_for_jobs(settings, 2)
    [target] = request["targets"]
    assert request["state"] == "failed" and target["errorCode"] == 20005
    assert "punched a program instead of reading the answer in" in target["statusMsg"]
    assert stored(line.control, "O0010") is None
    assert received["state"] == "succeeded" and received["targets"][0]["action"] == "receive"
    with session_scope(settings.resolved_database_url) as session:
        [item] = inbox.list_items(session=session, machine_id="2002")
        assert item.program_number == "O1234"


def test_a_request_refused_for_its_size_is_answered_with_why_nothing_was_done(
        settings, rs232, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    line = rs232()
    operator = press_read_when_asked(settings, line.control)
    line.punch_text(b"%\nO8888\n" + b"(DIR=/VIPROS)" * 200 + b"\n(PRG=0010)\n%\n")

    [job] = wait_for_jobs(settings, 1)
    operator.join(10)
    [target] = job["targets"]
    assert job["state"] == "failed" and target["errorCode"] == 20001
    assert stored(line.control, "O0010") is None
    error = stored(line.control, "O8890")
    assert error is not None and b"(REFUSED: THE REQUEST HAS 201 COMMANDS; AT MOST 200" in error


def test_several_programs_in_one_request_are_each_sent_in_order(
        settings, rs232, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    add_program("VIPROS", "0020", "%\nO0020 (FLANGE)\nM30\n%\n")
    line = rs232()
    operator = press_read_when_asked(settings, line.control, count=2)
    line.punch_text(b"%\nO8888\n(DIR=/VIPROS)(PRG=0010)(PRG=0020)\n%\n")

    [job] = wait_for_jobs(settings, 1)
    operator.join(20)
    assert [t["fileName"] for t in job["targets"]] == ["0010", "0020"]
    assert job["state"] == "succeeded", job
    assert same_program(stored(line.control, "O0010"), O0010)
    assert stored(line.control, "O0020") is not None


def test_a_program_punched_from_the_machine_lands_in_the_inbox_not_the_library(
        settings, rs232, add_program) -> None:
    add_program("RECEIVED", "1234", "%\nO1234 (OLD)\nG0 X0\nM30\n%\n")
    line = rs232()
    line.punch_text(b"%\nO1234 (EDITED AT THE MACHINE)\nG0 X5.\nM30\n%\n")

    [job] = wait_for_jobs(settings, 1)
    assert job["targets"][0]["action"] == "receive" and job["state"] == "succeeded"
    with session_scope(settings.resolved_database_url) as session:
        [item] = inbox.list_items(session=session, machine_id="2002")
        assert (item.name, item.program_number, item.state.value) == ("1234", "O1234",
                                                                       "pending")
        diff = inbox.diff(session=session, settings=settings, item_id=item.id)
    assert "-G0 X0" in diff and "+G0 X5." in diff


def test_the_listener_gives_the_machine_to_a_job_and_listens_again_after(
        settings, rs232, listening) -> None:
    rs232()
    with leases.hold(settings.resolved_database_url, machine_id="2002", max_concurrent=1,
                     wait_s=10):
        assert not listened(settings, "2002")  # a request waiting took the machine
    wait_until(lambda: (listening.tick(), listened(settings, "2002"))[1])


def test_reading_an_rs232_machines_programs_leaves_its_listener_on_the_line(
        settings, rs232, listening, client) -> None:
    """What dncq lists and reads of an RS-232 machine is its own copies: the line is not
    closed for it, so a program punched meanwhile still reaches the inbox."""
    line = rs232()
    copies = settings.data_dir / "serial" / "2002" / "programs"
    (copies / "O0100").write_bytes(b"%\nO0100\nG0 X1.\nM30\n%\n")
    listener = listening._running["2002"]
    asked = {"machineID": "2002", "dirAtCNC": "//CNC_MEM/"}

    answers = [client.get("/api/cnc/readProgramList", params=asked),
               client.get("/api/cnc/receiveFile", params={**asked, "fileName": "O0100"}),
               client.get("/api/cnc/receiveFileStream", params={**asked, "fileName": "O0100"}),
               client.get("/api/cnc/searchFile", params={**asked, "fileName": "O0100"}),
               client.get("/api/cnc/readAllPrograms", params=asked),
               client.get("/machines/2002/api/files/sdcard"),
               client.get("/api/cnc/readCurrentProgram", params=asked)]  # none: 20003

    assert [r.status_code for r in answers] == [200] * 7
    assert answers[0].json()["programs"] == ["100"]  # as Fanuc lists O0100
    assert answers[2].content == b"%\nO0100\nG0 X1.\nM30\n%\n"
    assert [f["name"] for f in answers[5].json()["files"]] == ["100"]
    assert listener.is_alive() and not listener.giving_way() and listening.hearing("2002")
    line.punch_text(b"%\nO1234 (EDITED AT THE MACHINE)\nG0 X5.\nM30\n%\n")
    [job] = wait_for_jobs(settings, 1)
    assert job["targets"][0]["action"] == "receive" and job["state"] == "succeeded"
    assert listening._running["2002"] is listener  # the same listener heard it


def test_garbage_from_the_line_is_kept_as_a_failed_reception_and_answered_nothing(
        settings, rs232) -> None:
    line = rs232()
    line.punch_text(b"%\n\x01\x02\x7f\xff\x00garbage\x00\x00binary\n%\n")

    [job] = wait_for_jobs(settings, 1)
    assert job["state"] == "failed"
    with session_scope(settings.resolved_database_url) as session:
        [item] = inbox.list_items(session=session, machine_id="2002")
        assert item.state.value == "failed"
        assert session.query(Job).filter(Job.state == JobState.RUNNING).count() == 0


def test_a_punch_sent_the_moment_the_listener_hears_is_not_lost_to_a_slow_opening(
        settings, rs232, monkeypatch) -> None:
    # Opening a serial port discards what waited in its input; a port slow to open (a busy
    # host) must not let the listener say it hears before the port is open.
    from worker.transports import serial_port

    opening = serial_port.Line.__init__

    def slow_open(self: Any, *args: Any, **kwargs: Any) -> None:
        time.sleep(0.5)
        opening(self, *args, **kwargs)

    monkeypatch.setattr(serial_port.Line, "__init__", slow_open)
    line = rs232()
    line.punch_text(b"%\n\x01\x02garbage\x00binary\n%\n")

    [job] = wait_for_jobs(settings, 1, timeout_s=10)
    assert job["state"] == "failed"  # heard, and kept as a failed reception


def test_two_workers_never_listen_on_one_machine_at_once(settings, rs232) -> None:
    rs232()
    other_worker = Listeners(settings)
    try:
        assert other_worker.tick() == 0 and not other_worker.hearing("2002")
    finally:
        other_worker.stop()


def test_listeners_stopped_start_no_listener_and_keep_no_lease(
        settings, add_machines, serial_machine) -> None:  # noqa: F811
    """The worker's stop and its reaper's tick run on two threads: a tick that comes after
    the stop must not start a listener (nor keep the machine's slot) that nothing stops."""
    line = serial_machine(mode=Mode.EDIT, model="Fanuc 0i-F")
    add_machines({"id": "2002", "name": "RS232-J", "model": "Fanuc 0i-F", "transport": "serial",
                  "options": {"url": str(line.end.link), "baud": 115200},
                  "requests": {"enabled": True}})
    stopped = Listeners(settings)
    stopped.stop()

    assert stopped.tick() == 0 and not stopped.hearing("2002")
    with session_scope(settings.resolved_database_url) as session:
        assert session.scalar(select(func.count()).where(
            MachineLease.machine_id == "2002")) == 0
    running = Listeners(settings)  # the machine is free: a worker not stopped listens
    try:
        assert running.tick() == 1
    finally:
        running.stop()


def test_an_enormous_punch_is_kept_as_a_failed_reception_and_the_next_request_is_answered(
        settings, add_machines, serial_machine, listening, add_program) -> None:  # noqa: F811
    add_program("VIPROS", "0010", O0010)
    line = serial_machine(mode=Mode.EDIT, model="Fanuc 0i-F")
    add_machines({"id": "2002", "name": "RS232-J", "model": "Fanuc 0i-F", "transport": "serial",
                  "options": {"url": str(line.end.link), "baud": 115200,
                              "max_receive_bytes": 4096},
                  "requests": {"enabled": True}})
    listening.tick()
    wait_until(lambda: listening.hearing("2002"))
    line.punch_text(b"%\nO8888\n" + b"(PRG=0010)\n" * 2000 + b"%\n")

    [failed] = wait_for_jobs(settings, 1)
    assert failed["state"] == "failed" and "4096" in failed["targets"][0]["errorMsg"] + \
        (failed["targets"][0]["statusMsg"] or "")
    assert stored(line.control, "O0010") is None  # nothing of it was run

    operator = press_read_when_asked(settings, line.control)
    line.punch_text(SEED_REQUEST)
    jobs = wait_for_jobs(settings, 2)
    operator.join(10)
    assert jobs[1]["state"] == "succeeded"
    assert same_program(stored(line.control, "O0010"), O0010)


def test_a_listened_machine_is_kept_online_by_its_listener_and_offline_when_the_link_goes(
        settings, tcp_control) -> None:
    from jobs import db
    from jobs.fleet import checks

    def last() -> dict[str, Any] | None:
        with db.session_scope(settings.resolved_database_url) as session:
            return checks.last(session, "2001")

    server = tcp_control()
    wait_until(lambda: last() is not None)
    assert (last()["reachable"], last()["by"]) == (True, "listener")  # type: ignore[index]

    server.close()  # the control's link goes away

    wait_until(lambda: last()["reachable"] is False, timeout_s=30)  # type: ignore[index]
    assert last()["error"]  # type: ignore[index]


def test_a_single_machine_request_gets_a_listened_machine_however_quickly_it_listens_again(
        settings, tcp_control, listening) -> None:
    from jobs import db
    from jobs.fleet import registry
    from jobs.run import checking

    tcp_control()
    stop = threading.Event()

    def listen_again_at_once() -> None:  # a reaper far quicker than any
        while not stop.wait(0.02):
            listening.tick()

    eager = threading.Thread(target=listen_again_at_once, daemon=True)
    eager.start()
    with db.session_scope(settings.resolved_database_url) as session:
        spec = registry.get(session=session, machine_id="2001")
    try:
        found = [checking.check_now(settings.model_copy(update={"busy_wait_s": 15.0}), [spec])[0]
                 for _ in range(3)]
    finally:
        stop.set()
        eager.join(5)

    assert [(f["busy"], f["reachable"]) for f in found] == [(False, True)] * 3


def test_octoprints_listing_of_a_listened_control_gets_the_machine_from_its_listener(
        settings, tcp_control, listening, client) -> None:
    server = tcp_control()
    with server.control.store.receive("O0100") as out:
        out.write(b"%\nO0100\nM30\n%\n")

    for _ in range(2):  # the second after the listener took the machine back
        wait_until(lambda: (listening.tick(), listened(settings, "2001"))[1])
        response = client.get("/machines/2001/api/gcodefiles/sdcard")
        assert response.status_code == 200, response.json()
        assert [f["name"] for f in response.json()["files"]] == ["100"]


def test_a_link_lost_while_the_answer_waits_ends_the_request_failed_saying_so(
        settings, tcp_control, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    server = tcp_control()
    server.punch_text(SEED_REQUEST)
    wait_until(lambda: request_jobs(settings, finished=False), timeout_s=30)

    server.close()  # the control's link goes away before its operator presses READ

    [job] = wait_for_jobs(settings, 1, timeout_s=10)
    [target] = job["targets"]
    assert job["state"] == "failed" and target["errorCode"] == 20006, job
    assert "ask again from the control" in target["statusMsg"]
    assert "lost before it answered" not in target["statusMsg"]


def test_a_punch_cut_short_is_kept_in_the_inbox_with_what_came_of_it(
        settings, add_machines, serial_machine, listening) -> None:  # noqa: F811
    line = serial_machine(mode=Mode.EDIT, model="Fanuc 0i-F")
    add_machines({"id": "2002", "name": "RS232-J", "model": "Fanuc 0i-F", "transport": "serial",
                  "options": {"url": str(line.end.link), "baud": 115200,
                              "receive_timeout_s": 1.0},
                  "requests": {"enabled": True}})
    listening.tick()
    wait_until(lambda: listening.hearing("2002"))

    line.end.write(b"%\nO1234 (EDITED AT THE MACHINE)\nG0 X5.\n")  # the cable is pulled

    [job] = wait_for_jobs(settings, 1)
    assert job["state"] == "failed"
    with session_scope(settings.resolved_database_url) as session:
        [item] = inbox.list_items(session=session, machine_id="2002")
        session.expunge(item)
    assert item.state.value == "failed" and "before its end" in item.reason
    assert blobs.read_all(settings, item.sha256) == b"%\nO1234 (EDITED AT THE MACHINE)\nG0 X5.\n"
