"""Drip-feed runs end to end: API → queue → worker → `dnc` link → the simulated control.

The control is `dncq sim-cnc` in a process of its own; its logs say which lines it
executed, so a test sees what the machine did, not what dncq believes it did.
"""

from __future__ import annotations

import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tests.jobs.helpers import wait_done, wait_until
from tests.worker.simulator.sim_process import Sim, SimFactory, start_sim  # noqa: F401
from tests.worker.transports.serial_lines import serial_machine  # noqa: F401
from tests.worker.transports.tcp_proxy import CuttableProxy, make_proxy  # noqa: F401
from worker.simulator.control import Mode, RunState

LINES = 5000


def program(lines: int = LINES) -> bytes:
    body = "".join(f"N{n} G1 X{n % 100}.0 Y{n % 37}.0 F500\n" for n in range(10, 10 * lines - 20,
                                                                           10))
    return ("O0100\n" + body + "M30\n").encode()


def add_dnc_machine(add_machines: Any, sim: Sim, machine_id: str = "2001") -> None:
    add_machines({"id": machine_id, "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": sim.port,
                              "heartbeat_interval_s": 0.5, "grace_s": 5.0}})


def start_run(client: Any, machine_id: str, data: bytes, **more: Any) -> dict[str, Any]:
    stored = client.post("/api/programs", content=data,
                         headers={"content-type": "application/octet-stream"}).json()
    answer = client.post("/api/jobs", json={
        "kind": "dnc_run", "machines": {"ids": [machine_id]}, "program": stored["id"],
        "fileName": "BIGPART.NC", **more})
    assert answer.status_code in (200, 202), answer.text
    return answer.json()


def the_run(client: Any, job_id: str) -> dict[str, Any]:
    return client.get(f"/api/jobs/{job_id}", params={"limit": 0}).json()["runs"][0]


def assert_restart_range_holds(run: dict[str, Any], executed: int) -> None:
    """The restart the message names holds the line the machine stopped at: a control runs
    on through what it held after its link is gone, which a restart at the last confirmed
    line would cut again."""
    assert run["line"] <= executed <= max(run["linesSent"], run["line"])
    if run["linesSent"] > run["line"]:
        assert f"--from-line at the line it shows ({run['line']} to {run['linesSent']})" \
            in run["message"], run["message"]
    else:
        assert f"--from-line {run['line']}" in run["message"], run["message"]


def test_a_run_goes_to_its_last_line_and_the_job_shows_the_line_while_running(
        queue_client, add_machines, start_sim: SimFactory) -> None:  # noqa: F811
    sim = start_sim("--block-rate", "2000")
    add_dnc_machine(add_machines, sim)
    data = program()
    job = start_run(queue_client, "2001", data)

    seen: list[int] = []

    def moving() -> bool:
        run = the_run(queue_client, job["id"])
        seen.append(run["line"])
        return 0 < run["line"] < run["linesTotal"] and run["state"] == "running"

    wait_until(moving)
    done = wait_done(queue_client, job["id"])

    run = done["runs"][0]
    total = data.count(b"\n")
    assert done["state"] == "succeeded" and run["state"] == "succeeded"
    assert run["line"] == run["linesTotal"] == total
    assert sim.executed() == data.decode().splitlines()  # every line once, in order
    assert queue_client.get("/api/runs", params={"program": "BIGPART.NC"}).json()[0]["id"] \
        == run["id"]


def test_a_program_whose_lines_end_in_cr_alone_runs_line_by_line(
        queue_client, add_machines, start_sim: SimFactory) -> None:  # noqa: F811
    sim = start_sim("--block-rate", "5000")
    add_dnc_machine(add_machines, sim)
    data = program(300)
    job = start_run(queue_client, "2001", data.replace(b"\n", b"\r"))

    done = wait_done(queue_client, job["id"])

    run = done["runs"][0]
    assert run["state"] == "succeeded"
    assert run["line"] == run["linesTotal"] == data.count(b"\n")
    assert sim.executed() == data.decode().splitlines()


def test_stop_resets_the_machine_and_ends_the_run_with_its_last_line(
        queue_client, add_machines, start_sim: SimFactory) -> None:  # noqa: F811
    sim = start_sim("--block-rate", "200")
    add_dnc_machine(add_machines, sim)
    job = start_run(queue_client, "2001", program())
    wait_until(lambda: the_run(queue_client, job["id"])["line"] > 50)

    assert queue_client.post(f"/api/jobs/{job['id']}/stop").json()["stopping"] == 1
    done = wait_done(queue_client, job["id"])

    run = done["runs"][0]
    assert run["state"] == "stopped" and done["targets"][0]["state"] == "cancelled"
    assert sim.runs()[-1]["ended"] == "reset"
    executed = len(sim.executed())
    assert 50 < run["line"] <= executed < LINES  # the record never claims more than was cut
    assert f"line {run['line']}" in run["message"]


def test_a_stopped_runs_job_stays_cancelled_and_names_who_stopped_it(
        queue_client, add_machines, start_sim: SimFactory) -> None:  # noqa: F811
    # Its run said `stopped` while its job and target said only `cancelled` and "stopped on
    # request": nothing told a stop from a cancel, nor who asked it.
    sim = start_sim("--block-rate", "200")
    add_dnc_machine(add_machines, sim)
    job = start_run(queue_client, "2001", program())
    wait_until(lambda: the_run(queue_client, job["id"])["line"] > 50)

    queue_client.post(f"/api/jobs/{job['id']}/stop", params={"by": "alice"})
    done = wait_done(queue_client, job["id"])

    [run], [target] = done["runs"], done["targets"]
    assert done["state"] == "cancelled" and done["stoppedBy"] == "alice"  # a known end
    assert run["state"] == "stopped" and run["stoppedBy"] == "alice"
    assert target["statusMsg"] == run["message"] == \
        f"stopped by alice at line {run['line']:,}; the machine was reset"
    listed = queue_client.get("/api/jobs", params={"state": "cancelled"}).json()
    assert [(j["id"], j["stoppedBy"]) for j in listed] == [(job["id"], "alice")]


def test_a_run_queued_behind_another_waits_for_it_on_a_machine_taking_two_operations(
        queue_client, add_machines, start_sim: SimFactory) -> None:  # noqa: F811
    # It started at once beside the first: two programs fed on one DNC link.
    sim = start_sim("--block-rate", "200")
    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "max_concurrent": 2, "options": {"host": "127.0.0.1", "port": sim.port,
                                                   "heartbeat_interval_s": 0.5,
                                                   "grace_s": 5.0}})
    first = start_run(queue_client, "2001", program())
    wait_until(lambda: the_run(queue_client, first["id"])["line"] > 50)
    second = start_run(queue_client, "2001", program(300), queue=True)

    def tried_once() -> bool:  # its attempt came and found the first running
        [target] = queue_client.get(f"/api/jobs/{second['id']}").json()["targets"]
        return "waits for" in (target["statusMsg"] or "") \
            or the_run(queue_client, second["id"])["state"] != "queued"

    wait_until(tried_once)
    assert the_run(queue_client, second["id"])["state"] == "queued"
    assert the_run(queue_client, first["id"])["state"] == "running"
    queue_client.post(f"/api/jobs/{first['id']}/stop")
    done = wait_done(queue_client, second["id"])

    assert (done["state"], done["runs"][0]["state"]) == ("succeeded", "succeeded")
    assert done["targets"][0]["attempts"] == 1  # its waits took none of its attempts
    assert [r["ended"] for r in sim.runs()] == ["reset", "done"]  # one after the other


def test_a_reset_at_the_machine_after_the_last_line_was_sent_says_where_to_restart(
        queue_client, add_machines, start_sim: SimFactory, tmp_path) -> None:  # noqa: F811
    panel = tmp_path / "panel"
    sim = start_sim("--block-rate", "200", "--panel", str(panel))
    add_dnc_machine(add_machines, sim)
    data = program(1500)  # the last line goes into the window of 1,000 by line 600 or so
    job = start_run(queue_client, "2001", data)
    total = data.count(b"\n")
    wait_until(lambda: the_run(queue_client, job["id"])["linesSent"] == total)

    (panel / "reset").write_text("")
    done = wait_done(queue_client, job["id"])

    run = done["runs"][0]
    assert run["state"] == "failed" and run["line"] < total
    assert sim.runs()[-1]["ended"] == "reset"
    assert run["message"].count(f"line {run['line']}") == 1, run["message"]
    assert_restart_range_holds(run, len(sim.executed()))


def test_a_run_that_ended_lost_counts_the_one_attempt_that_ran(
        queue_client, add_machines, start_sim: SimFactory, tmp_path) -> None:  # noqa: F811
    panel = tmp_path / "panel"
    sim = start_sim("--block-rate", "200", "--panel", str(panel))
    add_dnc_machine(add_machines, sim)
    job = start_run(queue_client, "2001", program())
    wait_until(lambda: the_run(queue_client, job["id"])["line"] > 50)

    (panel / "reset").write_text("")
    done = wait_done(queue_client, job["id"])

    [target] = done["targets"]
    assert done["runs"][0]["state"] == "failed" and target["state"] == "failed"
    assert target["attempts"] == 1  # not a second one, refused at once
    assert target["statusMsg"] == done["runs"][0]["message"]


def test_a_control_not_in_dnc_mode_leaves_the_run_waiting_not_failed(
        queue_client, add_machines, start_sim: SimFactory) -> None:  # noqa: F811
    sim = start_sim("--mode", "mem")
    add_dnc_machine(add_machines, sim)
    # Retried until stopped: a run that ran out of attempts before the stop would end failed.
    job = start_run(queue_client, "2001", program(50), deliver_within="1h")

    def waiting_between_attempts() -> bool:  # an attempt may be running at any look
        summary = queue_client.get(f"/api/jobs/{job['id']}", params={"limit": 1}).json()
        run = the_run(queue_client, job["id"])
        return summary["targets"][0]["attempts"] >= 2 and run["state"] == "queued" \
            and "DNC" in (run["message"] or "").upper()

    wait_until(waiting_between_attempts)
    assert sim.executed() == []
    queue_client.post(f"/api/jobs/{job['id']}/stop")
    assert wait_done(queue_client, job["id"])["runs"][0]["state"] == "cancelled"


def test_a_run_whose_every_attempt_found_the_link_down_ends_failed_with_its_job(
        queue_client, add_machines) -> None:
    # Each attempt put the run back in the queue for the next; after the last it stayed
    # queued for ever, and `dncq run` waited on it.
    from tests.servers import free_port

    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": free_port(), "timeout_s": 1}})
    job = start_run(queue_client, "2001", program(20))

    done = wait_done(queue_client, job["id"], timeout_s=60)
    run = the_run(queue_client, job["id"])
    assert done["state"] == "failed" and done["targets"][0]["errorCode"] == 20006
    assert run["state"] == "failed" and run["endedAt"] is not None


def test_a_machine_on_the_link_is_listed_written_read_deleted_and_backed_up(
        queue_client, add_machines, start_sim: SimFactory) -> None:  # noqa: F811
    sim = start_sim("--model", "Fanuc 0i-F")
    add_dnc_machine(add_machines, sim)
    part = b"%\nO0077\nG0 X0\nM30\n%\n"

    sent = queue_client.post("/api/cnc/sendFile", params={"machineID": "2001"},
                             json={"content": part.decode()})
    listing = queue_client.get("/api/cnc/readProgramList", params={"machineID": "2001"}).json()
    read = queue_client.get("/api/cnc/receiveFile",
                            params={"machineID": "2001", "fileName": "O0077"}).json()

    assert sent.json()["errorCode"] == 0, sent.text
    assert listing["programs"] == ["77"] and listing["dirAtCNC"] == "//CNC_MEM/"  # Fanuc style
    assert read["content"] == part.decode()
    assert (sim.root / "O0077").read_bytes() == part

    backup = queue_client.post("/api/jobs", json={"kind": "backup",
                                                  "machines": {"ids": ["2001"]}}).json()
    assert wait_done(queue_client, backup["id"])["state"] == "succeeded"

    deleted = queue_client.get("/api/cnc/deleteFile",
                                params={"machineID": "2001", "fileName": "O0077"})
    assert deleted.json()["errorCode"] == 0 and not (sim.root / "O0077").exists()


def test_a_worker_killed_mid_run_ends_the_run_failed_with_its_last_line(
        queue_settings, add_machines, start_sim: SimFactory, start_worker) -> None:  # noqa: F811
    from fastapi.testclient import TestClient

    from jobs.api.app import create_app
    from tests.conftest import API_KEY

    sim = start_sim("--block-rate", "300")
    add_dnc_machine(add_machines, sim)
    worker = start_worker("w1", queue_settings)
    worker.wait_for_log("ready")
    with TestClient(create_app(queue_settings), headers={"X-Api-Key": API_KEY}) as client:
        job = start_run(client, "2001", program())
        wait_until(lambda: the_run(client, job["id"])["line"] > 100)

        worker.proc.send_signal(signal.SIGKILL)
        worker.proc.wait(10)
        start_worker("w2", queue_settings).wait_for_log("ready")
        done = wait_done(client, job["id"], timeout_s=60)

    run = done["runs"][0]
    assert run["state"] == "failed" and done["targets"][0]["state"] == "failed"
    executed = sim.executed()
    assert 100 <= run["line"] <= len(executed) < LINES  # nothing after the kill, none twice
    assert executed == program().decode().splitlines()[:len(executed)]
    # The lines sent after the record's last write are in no record: the hint bounds the
    # restart from below only, and the machine's own line is at or past it.
    assert f"--from-line at the line the machine shows ({run['line']} or later" in \
        run["message"], run["message"]


def test_a_link_down_past_its_grace_fails_the_run_with_its_last_line_and_frees_the_machine(
        queue_client, add_machines, start_sim: SimFactory,  # noqa: F811
        make_proxy: Callable[[int], CuttableProxy]) -> None:  # noqa: F811
    """A drop of a few seconds against a 1 s grace (a 60 s drop against the default 30 s
    grace, made short)."""
    sim = start_sim("--block-rate", "300", "--grace-s", "1")
    proxy = make_proxy(sim.port)
    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": proxy.port, "timeout_s": 2.0,
                              "heartbeat_interval_s": 0.2, "grace_s": 1.0}})
    job = start_run(queue_client, "2001", program())
    wait_until(lambda: the_run(queue_client, job["id"])["line"] > 100)

    proxy.down()
    done = wait_done(queue_client, job["id"])
    proxy.up()

    run = done["runs"][0]
    assert run["state"] == "failed" and done["targets"][0]["errorCode"] == 20006
    assert 100 <= run["line"] <= len(sim.executed()) < LINES
    assert_restart_range_holds(run, len(sim.executed()))
    listing = queue_client.get("/api/cnc/readProgramList", params={"machineID": "2001"})
    assert listing.json()["dirAtCNC"] == "//CNC_MEM/"  # the machine's lease was given back


def test_a_run_never_holds_up_the_other_machines_of_its_worker(
        queue_settings, add_machines, start_sim: SimFactory, start_worker) -> None:  # noqa: F811
    """One machine operation at once (gevent, --concurrency 1): a run takes none of it."""
    from fastapi.testclient import TestClient

    from jobs.api.app import create_app
    from tests.conftest import API_KEY

    sim = start_sim("--block-rate", "100")
    add_dnc_machine(add_machines, sim)
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})
    start_worker("w1", queue_settings, pool="gevent", concurrency=1).wait_for_log("ready")
    with TestClient(create_app(queue_settings), headers={"X-Api-Key": API_KEY}) as client:
        run_job = start_run(client, "2001", program())
        wait_until(lambda: the_run(client, run_job["id"])["line"] > 10)

        send = client.post("/api/jobs", json={"kind": "send", "content": "G0 X0\n",
                                              "targets": [{"machineID": "m1",
                                                           "fileName": "P.nc"}]}).json()
        sent = wait_done(client, send["id"], timeout_s=30)

        assert sent["state"] == "succeeded"
        assert the_run(client, run_job["id"])["state"] == "running"
        client.post(f"/api/jobs/{run_job['id']}/stop")
        assert wait_done(client, run_job["id"])["runs"][0]["state"] == "stopped"


BRACKET = (Path(__file__).parent / "programs" / "mill_bracket.nc").read_bytes()


def test_a_restart_sends_the_planned_header_then_the_program_from_its_block(
        queue_client, add_machines, start_sim: SimFactory) -> None:  # noqa: F811
    sim = start_sim("--block-rate", "5000")
    add_dnc_machine(add_machines, sim)

    preview = start_run(queue_client, "2001", BRACKET, from_block="N230", dry_run=True)
    assert queue_client.get("/api/runs").json() == []  # a dry run queues nothing
    job = start_run(queue_client, "2001", BRACKET, from_block="N230")
    done = wait_done(queue_client, job["id"])

    lines = BRACKET.decode().splitlines()
    start = preview["startLine"]
    assert lines[start - 1].startswith("N230")
    assert {"G54", "T2 M6", "G43 H2"} <= set(preview["header"])  # T7 is only pre-selected
    assert sim.executed() == preview["header"] + lines[start - 1:]
    run = done["runs"][0]
    assert run["state"] == "succeeded" and run["startLine"] == start
    assert run["line"] == len(lines) and run["restartFrom"] == "block N230"


def test_a_restart_the_scan_cannot_be_sure_of_is_refused_with_its_reason(
        client, add_machines) -> None:
    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": 1}})
    stored = client.post("/api/programs", content=BRACKET,
                         headers={"content-type": "application/octet-stream"}).json()

    inside = client.post("/api/jobs", json={"kind": "dnc_run", "machines": {"ids": ["2001"]},
                                            "program": stored["id"], "from_block": "N200"})
    missing = client.post("/api/jobs", json={"kind": "dnc_run", "machines": {"ids": ["2001"]},
                                             "program": stored["id"], "from_block": "N9999"})

    said = inside.json()["statusMsg"]
    assert inside.status_code == 422 and "G81 canned cycle" in said
    assert said.startswith("cannot restart from block N200 (line 23): line 23 is inside")
    assert said.count("cannot restart") == 1 and said.count("(line 23)") == 1  # said once
    assert missing.status_code == 422 and missing.json()["errorCode"] == 158
    assert client.get("/api/runs").json() == []


def test_a_run_over_rs232_goes_to_its_last_line_with_flow_control(
        queue_client, add_machines, serial_machine) -> None:  # noqa: F811
    """Through a pty pair to the control's RS-232 side, whose small buffer holds the sender
    with XON/XOFF at 115,200 baud. The control runs at a third of the line's pace (about
    440 lines a second), so it holds the line even when a loaded host slows the sender."""
    machine = serial_machine(mode=Mode.DNC, block_rate=150)
    add_machines({"id": "2002", "name": "RS232-J", "model": "Fanuc 0i-F", "transport": "serial",
                  "options": {"url": str(machine.end.link), "baud": 115200}})
    data = program(600)

    job = start_run(queue_client, "2002", data)
    done = wait_done(queue_client, job["id"])

    run = done["runs"][0]
    assert done["state"] == "succeeded" and run["line"] == data.count(b"\n")
    wait_until(lambda: machine.control.state is RunState.DONE)
    assert machine.last_error is None and machine.overflowed_bytes == 0  # nothing lost
    log = machine.control._log_dir / "executed.log"  # type: ignore[operator]
    assert log.read_text(encoding="latin-1").splitlines() == data.decode().splitlines()
    assert machine.xoff_count > 0


def test_a_library_version_runs_without_a_copy_and_is_its_programs_run_record(
        queue_client, add_machines, start_sim: SimFactory) -> None:  # noqa: F811
    sim = start_sim("--block-rate", "5000")
    add_dnc_machine(add_machines, sim)
    data = program(300)
    queue_client.post("/api/library/programs", content=data,
                      headers={"content-type": "application/octet-stream"},
                      params={"folder": "VIPROS", "name": "0100", "approve": "true"}
                      ).raise_for_status()
    queue_client.post("/api/library/assignments",
                      json={"folder": "VIPROS", "machines": ["2001"]}).raise_for_status()

    answer = queue_client.post("/api/jobs", json={"kind": "dnc_run", "library": "VIPROS/0100",
                                                  "machines": {"ids": ["2001"]}})
    assert answer.status_code == 202, answer.text
    done = wait_done(queue_client, answer.json()["id"])

    assert done["runs"][0]["state"] == "succeeded" and done["runs"][0]["program"] == "0100"
    assert sim.executed() == data.decode().splitlines()
    shown = queue_client.get("/api/library/programs/VIPROS/0100").json()
    assert shown["runs"]["2001"]["success"] == 1
    local = queue_client.get("/machines/2001/api/gcodefiles/local").json()["files"]
    assert [(f["name"], f["prints"]["success"]) for f in local] == [("0100", 1)]
