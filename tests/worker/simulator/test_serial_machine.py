"""`dncq sim-cnc` on RS-232 (a pty it links, a raw TCP port) and its operator panel, on the
RS-232 side and on the TCP side."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

from tests.worker.simulator.sim_process import SimFactory, start_sim  # noqa: F401
from worker.transports.serial_line import SerialOptions, SerialTransport

PROGRAM = b"%\nO0100 (BORE)\nG0 X0 Y0\nM30\n%"
REQUEST = b"%\nO8888\nN0010 (DIR=/VIPROS)\nN0020 (PRG=0010)\n%"


def wait_for(condition: Callable[[], bool], timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "the simulator did not get there"
        time.sleep(0.02)


def status(panel: Path) -> dict[str, object]:
    path = panel / "status.json"
    return json.loads(path.read_text()) if path.exists() else {}


def test_the_raw_tcp_port_reads_in_a_program_and_the_panel_punches_it_back(
        start_sim: SimFactory, tmp_path: Path) -> None:  # noqa: F811
    panel = tmp_path / "panel"
    panel.mkdir()
    sim = start_sim("--model", "Fanuc", "--mode", "edit", "--tcp-raw", "0", "--panel", str(panel))
    assert sim.process.stdout is not None
    port = int(sim.process.stdout.readline().split()[3])  # "listening tcp-raw HOST PORT"
    line = SerialTransport(SerialOptions(url=f"socket://127.0.0.1:{port}", baud=115_200),
                           folder=tmp_path / "state")
    try:
        line.write("bore.nc", iter([PROGRAM]))
        wait_for(lambda: status(panel).get("received") == ["O0100"])

        (panel / "punch").write_text("O0100")  # the operator presses PUNCH
        entry = line.receive_punch(timeout_s=10)
    finally:
        line.close()

    assert entry.name == "O0100"
    assert b"".join(line.read("O0100")) == PROGRAM


def test_serial_links_a_pty_the_transport_opens_by_that_path(
        start_sim: SimFactory, tmp_path: Path) -> None:  # noqa: F811
    link = tmp_path / "ttyCNC"
    sim = start_sim("--model", "Fanuc", "--mode", "edit", "--serial", str(link))
    assert sim.process.stdout is not None
    assert sim.process.stdout.readline().startswith("listening serial /dev/pts/")
    line = SerialTransport(SerialOptions(url=str(link), baud=115_200), folder=tmp_path / "state")
    try:
        line.write("bore.nc", iter([PROGRAM]))
    finally:
        line.close()

    wait_for(lambda: (sim.root / "O0100").exists())
    assert (sim.root / "O0100").read_bytes() == PROGRAM + b"\n"


def test_the_panel_types_a_request_toward_the_tcp_side_and_presses_read(
        start_sim: SimFactory, tmp_path: Path) -> None:  # noqa: F811
    panel = tmp_path / "panel"
    sim = start_sim("--model", "Fanuc", "--panel", str(panel))
    dnc = sim.transport()
    try:
        wait_for(lambda: status(panel).get("outbox") == 0)
        (panel / "type").write_bytes(REQUEST)  # the operator types and punches a request
        wait_for(lambda: status(panel).get("outbox") == 1)
        received = dnc.receive_program(timeout_s=10)

        (panel / "read").write_text("")  # the operator presses READ
        wait_for(lambda: status(panel).get("ready_to_read") is True)
        ready = dnc.wait_ready_to_read(timeout_s=10)
        dnc.send_to_read("O0100", PROGRAM)
    finally:
        dnc.close()

    assert received == REQUEST and ready
    assert (sim.root / "O0100").read_bytes() == PROGRAM
    wait_for(lambda: status(panel).get("ready_to_read") is False)
    assert status(panel)["outbox"] == 0


def test_read_on_the_panel_sends_dc1_and_the_answer_replaces_its_namesake(
        start_sim: SimFactory, tmp_path: Path) -> None:  # noqa: F811
    panel = tmp_path / "panel"
    sim = start_sim("--model", "Fanuc", "--mode", "edit", "--tcp-raw", "0", "--panel", str(panel))
    assert sim.process.stdout is not None
    port = int(sim.process.stdout.readline().split()[3])
    line = SerialTransport(SerialOptions(url=f"socket://127.0.0.1:{port}", baud=115_200),
                           folder=tmp_path / "state")
    answer = PROGRAM.replace(b"(BORE)", b"(ANSWER)")
    try:
        line.write("bore.nc", iter([PROGRAM]))  # the line is up: the control has it stored
        wait_for(lambda: status(panel).get("received") == ["O0100"])

        (panel / "read").write_text("60")
        ready = line.wait_ready_to_read(timeout_s=10)
        line.send_to_read("O0100", answer)
        wait_for(lambda: status(panel).get("received") == ["O0100", "O0100"])
    finally:
        line.close()

    assert ready
    assert (sim.root / "O0100").read_bytes() == answer + b"\n"
    assert status(panel)["ready_to_read"] is False
