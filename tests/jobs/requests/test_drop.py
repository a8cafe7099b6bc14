"""Requests by file drop: the control writes a request program into a folder of its
machine, a scan finds it, answers with a file beside it and removes the request.

The machines are mock ones (files in the data folder) and FTP ones against the real
servers of the FTP transport's tests (pyftpdlib, vsftpd and ProFTPD where installed); the
scan is `jobs.requests.drop`, called as the worker's reaper tick calls it, and once
through a real `worker.app.Reaper`.
"""

from __future__ import annotations

import os
import re
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from jobs.db import session_scope
from jobs.inbox import service as inbox
from jobs.library import service as library
from jobs.requests import drop
from jobs.run import leases
from tests.jobs.helpers import wait_until
from tests.jobs.requests.conftest import DROP_FOLDER, O0010, SEED_REQUEST, request_jobs
from tests.servers import free_port
from tests.worker.transports.ftp_daemons import DAEMON_KINDS, server_of
from tests.worker.transports.ftp_server import KINDS, FtpServer

SEED_EXAMPLE = b"O8888\nN0010 (DIR=/VIPROS)\nN0020 (PRG=0010)\n%\n"  # as the issue writes it


@pytest.fixture(params=KINDS + DAEMON_KINDS)
def ftp_server(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[FtpServer]:
    """Each FTP server the ftp transport is tested against (a missing one skips, saying so)."""
    with server_of(request.param, tmp_path / "ftp") as server:
        yield server


def test_the_seeds_request_dropped_on_an_ftp_machine_is_answered_with_the_program_file(
        settings, drop_machine, add_program, ftp_server) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine("f1", transport="ftp", model="Fanuc 0i-F",
                           options=ftp_server.options)
    machine.drop("O8888", SEED_EXAMPLE)

    assert machine.scan() == 1

    assert machine.names() == ["O0010"]  # the request is gone, the answer is there
    assert machine.read("O0010") == O0010.encode()
    [job] = request_jobs(settings)
    assert (job["state"], job["fileName"], job["kind"]) == ("succeeded", "O8888", "request")
    [target] = job["targets"]
    assert (target["action"], target["folder"], target["fileName"]) == ("send", "VIPROS", "0010")
    assert (target["machineID"], target["origin"], target["answer"]) == ("f1", "drop:O8888",
                                                                          "O0010")


def test_answers_are_written_to_the_answer_folder_when_one_is_set(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine(answer_folder="/answers", folders=("/answers",))
    machine.drop("O8888", SEED_REQUEST)

    machine.scan()

    assert machine.names() == []
    assert machine.names("/answers") == ["O0010"]
    assert machine.read("O0010", "/answers") == O0010.encode()


def test_a_program_dropped_with_the_bytes_of_an_answer_kept_elsewhere_is_received(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine(answer_folder="/answers", folders=("/answers",))
    machine.drop("O8888", SEED_REQUEST)
    machine.scan()
    machine.drop("O0010", O0010.encode())  # the control sends the program back unchanged

    assert machine.scan() == 1

    assert machine.names() == []
    with session_scope(settings.resolved_database_url) as session:
        [item] = inbox.list_items(session=session)
        assert item.name == "0010"


def test_a_dropped_request_for_a_missing_program_is_answered_with_the_error_program_file(
        settings, drop_machine) -> None:
    machine = drop_machine()
    machine.drop("O8888", SEED_REQUEST)

    machine.scan()

    assert machine.names() == ["O8890"]
    assert b"(NOT FOUND: VIPROS/0010)" in machine.read("O8890")
    [job] = request_jobs(settings)
    assert job["state"] == "failed" and job["targets"][0]["errorCode"] == 158
    assert job["targets"][0]["answer"] == "O8890"


def test_two_error_answers_of_one_look_are_one_error_program_holding_both(
        settings, drop_machine) -> None:
    # The second replaced the first before the control had taken it.
    machine = drop_machine()
    machine.drop("A", b"%\nO8888\n(DIR=/VIPROS)\n(PRG=0010)\n%\n")
    machine.drop("B", b"%\nO8888\n(DIR=/VIPROS)\n(PRG=0020)\n%\n")

    assert machine.scan() == 2

    assert machine.names() == ["O8890"]
    assert sorted(re.findall(rb"\((NOT FOUND: [^)]*)\)", machine.read("O8890"))) == [
        b"NOT FOUND: VIPROS/0010", b"NOT FOUND: VIPROS/0020"]
    assert machine.scan() == 0  # the control's to take, as any answer


def test_a_second_scan_leaves_dncqs_own_answer_for_the_control(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", SEED_REQUEST)
    machine.scan()

    assert machine.scan() == 0

    assert machine.names() == ["O0010"]
    assert len(request_jobs(settings)) == 1
    with session_scope(settings.resolved_database_url) as session:
        assert inbox.list_items(session=session) == []


def test_an_answer_the_control_changed_is_taken_as_a_program_it_sent(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", SEED_REQUEST)
    machine.scan()
    edited = O0010.replace("N130 X0", "N130 X1.").encode()
    machine.drop("O0010", edited, replace=True)

    assert machine.scan() == 1

    assert machine.names() == []
    with session_scope(settings.resolved_database_url) as session:
        [item] = inbox.list_items(session=session)
        assert (item.name, item.state.value, item.size) == ("0010", "pending", len(edited))


def test_an_answer_never_replaces_a_program_the_control_dropped_and_dncq_has_not_taken(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "9000", "%\nO9000 (LIBRARY)\nM30\n%\n")
    machine = drop_machine()
    edited = b"%\nO9000 (EDITED AT THE MACHINE)\nG0 X1.\nM30\n%\n"
    machine.drop("O9000", edited)  # listed after O8888: the answer's name is taken
    machine.drop("O8888", SEED_REQUEST.replace(b"0010", b"9000"))

    assert machine.scan() == 2

    with session_scope(settings.resolved_database_url) as session:
        [item] = inbox.list_items(session=session)
        assert (item.name, item.size) == ("9000", len(edited))
    asked = request_jobs(settings)[0]
    assert asked["state"] == "failed" and asked["targets"][0]["errorCode"] == 142
    assert "a file dncq did not write" in asked["targets"][0]["statusMsg"]

    machine.drop("O8888", SEED_REQUEST.replace(b"0010", b"9000"))  # the operator asks again
    machine.scan()
    assert machine.read("O9000") == b"%\nO9000 (LIBRARY)\nM30\n%\n"


def test_a_dropped_program_that_is_no_request_goes_to_the_inbox_and_leaves_the_folder(
        settings, drop_machine) -> None:
    machine = drop_machine()
    part = b"%\nO1234 (MY PART)\nG0 X0\nM30\n%\n"
    machine.drop("O1234", part)

    assert machine.scan() == 1

    assert machine.names() == []
    with session_scope(settings.resolved_database_url) as session:
        [item] = inbox.list_items(session=session, machine_id="m1")
        assert (item.name, item.comment, item.folder, item.state.value) == (
            "1234", "MY PART", "RECEIVED", "pending")
        assert library.list_programs(session=session, folder="RECEIVED") == []
    [job] = request_jobs(settings)
    assert job["targets"][0]["action"] == "receive" and job["state"] == "succeeded"


def test_a_busy_machine_is_skipped_and_its_request_handled_on_the_next_scan(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", SEED_REQUEST)

    with leases.hold(settings.resolved_database_url, machine_id="m1", max_concurrent=1,
                     wait_s=5):
        assert machine.scan() == 0
        assert machine.names() == ["O8888"]
        assert request_jobs(settings, finished=False) == []

    assert machine.scan() == 1
    assert machine.names() == ["O0010"]


def test_two_looks_at_once_into_one_drop_folder_take_its_request_once(
        settings, drop_machine, add_program, monkeypatch) -> None:
    # Two slots: an operation may run beside a look, but a second look beside it could read
    # the file the first is removing, and take it for a new one once the first marked it.
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine(max_concurrent=2)
    machine.drop("O8888", SEED_REQUEST)
    handling, first_in, go_on = drop.handling.handle, threading.Event(), threading.Event()

    def held_first(**kwargs):
        if not first_in.is_set():
            first_in.set()
            go_on.wait(30)
        return handling(**kwargs)

    monkeypatch.setattr(drop.handling, "handle", held_first)
    with ThreadPoolExecutor(1) as pool:
        first = pool.submit(machine.scan)
        assert first_in.wait(30)
        try:
            second = machine.scan()  # while the first look handles the file
        finally:
            go_on.set()
        assert (first.result(timeout=60), second) == (1, 0)

    assert len(request_jobs(settings)) == 1
    assert machine.names() == ["O0010"]


def test_the_scan_answers_every_machine_when_another_cannot_be_reached(
        settings, drop_machine, add_program, add_machines) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    add_machines({"id": "f9", "name": "Unreachable", "model": "Fanuc 0i-F", "transport": "ftp",
                  "options": {"host": "127.0.0.1", "port": free_port(), "user": "cnc",
                              "password": "x", "timeout_s": 2},
                  "requests": {"enabled": True, "drop_folder": DROP_FOLDER}})
    machine.drop("O8888", SEED_REQUEST)

    assert drop.scan(settings=settings) == 1

    assert machine.names() == ["O0010"]


def test_machines_without_a_drop_folder_or_with_requests_off_are_not_looked_into(
        settings, drop_machine, add_machines) -> None:
    drop_machine("m1")
    drop_machine("m2", enabled=False)
    add_machines({"id": "m3", "name": "No drop", "model": "Mock", "transport": "mock",
                  "requests": {"enabled": True}})

    assert [spec.id for spec in drop.candidates(settings)] == ["m1"]


def test_the_workers_reaper_tick_answers_a_dropped_request(
        settings, drop_machine, add_program) -> None:
    from worker.app import Reaper

    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", SEED_REQUEST)
    reaper = Reaper(settings.model_copy(update={
        "reaper_interval_s": 0.05, "request_scan_interval_s": 0.1, "listen": False}))
    reaper.start()
    try:
        wait_until(lambda: machine.names() == ["O0010"], timeout_s=30)
    finally:
        reaper.stop()
        reaper._thread.join(10)
    [job] = request_jobs(settings)
    assert job["state"] == "succeeded" and job["targets"][0]["origin"] == "drop:O8888"


def test_a_file_written_a_moment_ago_is_left_for_the_next_look(
        settings, drop_machine, add_program, monkeypatch) -> None:
    monkeypatch.setattr(drop, "SETTLE_S", 2.0)
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", SEED_REQUEST)  # the control may still be writing it

    assert machine.scan() == 0 and machine.names() == ["O8888"]

    written = settings.data_dir / "mock" / machine.id / "files" / "requests" / "O8888"
    os.utime(written, (time.time() - 5, time.time() - 5))  # five seconds later
    assert machine.scan() == 1 and machine.names() == ["O0010"]


def test_a_dropped_file_whose_name_dncq_cannot_take_is_told_once_and_the_others_are_handled(
        settings, drop_machine, add_program) -> None:
    # Its name was refused outside the scan's handling: every look failed there, with a
    # traceback, and the files after it in the listing were never taken.
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    folder = settings.data_dir / "mock" / "m1" / "files" / DROP_FOLDER.strip("/")
    (folder / "bad\\name").write_bytes(b"%\nO0777\nM30\n%\n")
    machine.drop("zz1", SEED_REQUEST)  # listed after the bad one

    assert machine.scan() == 1
    assert machine.scan() == 0  # the bad one is passed by again, and told no more

    assert machine.names() == ["O0010", "bad\\name"]  # answered; the bad one left alone
    failed = [job for job in request_jobs(settings) if job["state"] == "failed"]
    assert len(failed) == 1
    said = failed[0]["targets"][0]
    assert "'bad\\\\name' in the drop folder cannot be taken" in said["statusMsg"], said


@pytest.mark.parametrize(("preset", "request_name", "asked", "answer"), [
    ("siemens_iso", "DNCREQ.MPF", b"%_N_DNCREQ_MPF\n;LST=\nM30\n", "DNCLIST.MPF"),
    ("siemens_iso", "DNCREQ.MPF", b"%_N_DNCREQ_MPF\n;PRG=PART1\nM30\n", "PART1.MPF"),
    ("heidenhain_iso", "9999.I", b"%9999 G71 *\nN10 ;LST= *\nN20 M30 *\nN99999999 %9999 G71 *\n",
     "9998"),
])
def test_answers_dropped_for_on_a_siemens_or_heidenhain_are_written_under_their_programs_names(
        settings, drop_machine, add_program, preset, request_name, asked, answer) -> None:
    add_program("NC", "PART1.MPF", "%_N_PART1_MPF\nG0 X0\nM30\n")
    machine = drop_machine(preset=preset, sources=["library:NC"])
    machine.drop(request_name, asked)

    assert machine.scan() == 1

    [job] = request_jobs(settings)
    assert job["state"] == "succeeded", job
    assert machine.names() == [answer]
    assert job["targets"][0]["answer"] == answer


def dropped_at(settings, machine, name: str, data: bytes, mtime: float) -> None:
    """The control drops `name`, the file keeping the modification time `mtime` (a copy that
    keeps its time, as Windows' Explorer or `cp -p` makes it)."""
    machine.drop(name, data)
    written = settings.data_dir / "mock" / machine.id / "files" / DROP_FOLDER.strip("/") / name
    os.utime(written, (mtime, mtime))


def test_the_same_request_dropped_again_after_it_was_handled_runs_again(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    add_program("VIPROS", "0020", "%\nO0020 (FLANGE)\nM30\n%\n")
    machine = drop_machine()
    rename = b"%\nO8888\n(DIR=/VIPROS)\n(FIL=0010)\n(REN=0030)\n%\n"
    copied_at = time.time() - 3600
    dropped_at(settings, machine, "O8888", rename, copied_at)
    assert machine.scan() == 1

    dropped_at(settings, machine, "O8888", rename, copied_at)  # the same file once more
    assert machine.scan() == 1

    first, second = request_jobs(settings)
    assert first["id"] != second["id"]
    assert first["state"] == "succeeded"
    # Run again: 0010 is gone, and the operator reads why.
    assert second["state"] == "failed" and second["targets"][0]["errorCode"] == 158
    assert machine.names() == ["O8890"]


def test_a_dropped_request_that_could_not_be_removed_is_not_handled_again_at_the_next_look(
        settings, drop_machine, add_program) -> None:
    from worker.transports.mock_options import MockOptions
    from worker.transports.mock_state import MachineState

    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", b"%\nO8888\n(DIR=/VIPROS)\n(DEL=0010)\n%\n")
    protected = MachineState(settings.data_dir / "mock" / machine.id, MockOptions())
    protected.lock_range(8888, 8888, True)  # the control refuses to have O8888 deleted

    assert drop.scan(settings=settings) == 0  # deleted 0010, then could not remove O8888
    assert drop.scan(settings=settings) == 0
    protected.lock_range(8888, 8888, False)
    assert drop.scan(settings=settings) == 1

    [job] = request_jobs(settings)
    assert job["state"] == "succeeded"  # no second delete: NOT FOUND: VIPROS/0010
    assert machine.names() == ["O8890"]
    assert b"(DELETED: VIPROS/0010)" in machine.read("O8890")
