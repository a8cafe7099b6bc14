"""`dncq run|stop|runs`: a drip-feed run from the command line, against a simulated control."""

from __future__ import annotations

import re
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from jobs.cli import run_line
from jobs.cli.run_line import blocks_per_s
from tests.jobs.cli.runner import dncq, table_rows
from tests.worker.simulator.sim_process import SimFactory, start_sim  # noqa: F401


def _program(tmp_path: Path, lines: int) -> Path:
    part = tmp_path / "BIGPART.NC"
    part.write_text("O0100\nG21 G90 G17\nT1 M6\nG54 G0 X0 Y0 S2000 M3\nG43 Z5. H1 M8\n"
                    + "".join(f"N{10 * i} G1 X{i % 50}.0 F600\n" for i in range(1, lines))
                    + "M30\n")
    return part


def test_run_follows_the_machines_line_to_the_end_and_runs_lists_it(
        live_with_worker, add_machines, start_sim: SimFactory, tmp_path) -> None:  # noqa: F811
    sim = start_sim("--block-rate", "5000")
    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": sim.port}})
    part = _program(tmp_path, 2000)

    result = dncq("run", "2001", str(part))

    assert result.exit_code == 0, result.output
    assert "succeeded at line 2,005" in result.output
    assert len(sim.executed()) == 2005
    assert "ran to line" not in result.output  # its last line is said once
    listed = dncq("runs", "--machine", "2001").output  # in 80 columns
    [run] = table_rows(listed)
    assert f"Run {run['job']}:" in result.output  # whole: what `dncq stop` takes
    assert (run["program"], run["state"], run["line"]) == (
        "BIGPART.NC", "succeeded", "2,005/2,005")  # the name unfolded
    assert re.fullmatch(r"\d\d:\d\d \S+|\d{4}-\d\d-\d\d", run["started"])  # today's: the time
    # A job's whole id leaves the message no room in 80 columns: the list says where it is.
    assert "message" not in run and "dncq runs JOB shows one run's" in listed
    assert "  message  ran to line 2005" in dncq("runs", run["job"]).output


def test_a_run_started_without_waiting_is_followed_by_the_command_it_names_with_its_line(
        live_with_worker, add_machines, start_sim: SimFactory, tmp_path) -> None:  # noqa: F811
    sim = start_sim("--block-rate", "5000")
    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": sim.port}})
    started = dncq("run", "2001", str(_program(tmp_path, 500)), "--no-wait")
    named = re.search(r"Follow it with: (dncq job \S+ --watch)", started.output)
    assert named, started.output

    followed = dncq(*named.group(1).split()[1:])

    assert followed.exit_code == 0, followed.output
    assert "succeeded at line 505" in followed.output  # the run's line, not a target count


def test_run_dry_run_shows_the_restart_header_and_queues_nothing(
        live_with_worker, add_machines, start_sim: SimFactory, tmp_path) -> None:  # noqa: F811
    sim = start_sim()
    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": sim.port}})
    part = _program(tmp_path, 100)

    result = dncq("run", "2001", str(part), "--from", "N500", "--dry-run")

    assert result.exit_code == 0, result.output
    assert "then the program from line 55" in result.output
    assert "T1 M6" in result.output and "G43 H1" in result.output
    assert "BIGPART" not in dncq("runs").output


def test_stop_of_a_job_that_is_no_run_says_so(live_with_worker) -> None:
    result = dncq("stop", "nosuchjob")

    assert result.exit_code == 1 and "no job nosuchjob" in result.output


def test_a_run_on_a_machine_without_a_dnc_link_is_refused_before_the_program_is_uploaded(
        live_with_worker, add_machines, tmp_path) -> None:
    add_machines({"id": "m9", "name": "Mill", "model": "Mock"})  # the mock has no DNC link

    result = dncq("run", "m9", str(_program(tmp_path, 100)))

    assert result.exit_code == 1
    assert "20003 machine m9 cannot be drip-fed: its mock transport has no DNC link" in \
        " ".join(result.output.split())
    assert dncq("runs").output.count("BIGPART") == 0  # no run was made
    assert "Uploading" not in result.output and "BIGPART.NC" not in result.output


def test_a_run_on_a_mistyped_machine_id_names_the_id_meant(elsewhere, add_machines,
                                                          tmp_path) -> None:
    add_machines(*({"id": m, "name": m, "model": "Mock"} for m in ("1001", "1016")))

    result = dncq("run", "1O01", str(_program(tmp_path, 100)))  # a letter O for the 0

    assert result.exit_code == 1
    assert "Invalid MachineID (1O01) (did you mean 1001?)" in " ".join(result.output.split())
    assert "Uploading" not in result.output


def _run(line: int, *, start_line: int = 1, updated_s: float = 0.5,
         ended_s: float | None = None) -> dict[str, object]:
    """A run as GET /api/jobs/{job} gives it, started at 12:00:00 (UTC)."""
    at = "2026-12-06T12:00:{:06.3f}Z".format
    return {"line": line, "startLine": start_line, "startedAt": at(0),
            "updatedAt": at(updated_s), "endedAt": None if ended_s is None else at(ended_s)}


def test_blocks_per_s_counts_the_lines_run_from_the_restart_line_not_the_lines_skipped() -> None:
    # restarted from line 12,529, 141 of its lines run in its first half second
    assert blocks_per_s(_run(12_669, start_line=12_529)) == 282


def test_blocks_per_s_is_unknown_before_the_runs_first_line() -> None:
    assert blocks_per_s(_run(0)) is None  # queued, or connecting
    assert blocks_per_s(_run(12_528, start_line=12_529)) is None  # its restart header


def test_blocks_per_s_of_an_ended_run_is_the_runs_own_from_its_start_to_its_end() -> None:
    # 1,511 lines from line 18,500 in 3.1 s, the last recorded half a second before its end
    assert blocks_per_s(_run(20_010, start_line=18_500, updated_s=2.6, ended_s=3.1)) == \
        pytest.approx(1_511 / 3.1)


def test_a_restarted_run_ends_with_its_own_blocks_per_s_never_the_lines_it_skipped(
        live_with_worker, add_machines, start_sim: SimFactory, tmp_path) -> None:  # noqa: F811
    sim = start_sim("--block-rate", "1000")
    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": sim.port}})

    result = dncq("run", "2001", str(_program(tmp_path, 3000)), "--from-line", "2000")

    assert result.exit_code == 0, result.output
    rates = [int(r.replace(",", "")) for r in re.findall(r"([\d,]+) blocks/s", result.output)]
    assert rates and all(0 < rate <= 1000 for rate in rates), result.output  # the control's


def test_a_run_followed_into_a_log_prints_a_plain_line_each_tenth_of_its_program(
        live_with_worker, add_machines, start_sim: SimFactory, tmp_path) -> None:  # noqa: F811
    sim = start_sim("--block-rate", "1000")
    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": sim.port}})

    result = dncq("run", "2001", str(_program(tmp_path, 3000)))  # not on a terminal: 3 s

    assert result.exit_code == 0, result.output
    running = [int(n.replace(",", "")) for n in re.findall(
        r"^running line ([\d,]+) of 3,005, (?:[\d,]+|-) blocks/s$", result.output, re.M)]
    assert running, result.output
    assert all(b - a >= 300 for a, b in zip(running, running[1:], strict=False))  # short
    assert re.search(r"^succeeded line 3,005 of 3,005, [\d,]+ blocks/s$", result.output, re.M)
    assert "━" not in result.output  # no bar drawn into the log


def test_a_second_run_on_a_machine_is_refused_naming_the_first_unless_queued_behind_it(
        elsewhere, add_machines, tmp_path) -> None:
    # No worker: the first run stays queued, and holds the machine as a running one does.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": 9}})
    part = str(_program(tmp_path, 100))
    first = re.search(r"Run (\S+):", dncq("run", "2001", part, "--no-wait").output)
    assert first, "the first run was not started"

    refused = dncq("run", "2001", part, "--no-wait")
    queued = dncq("run", "2001", part, "--no-wait", "--queue")

    said = " ".join(refused.output.split())
    assert refused.exit_code == 1
    assert f"machine 2001 has a drip-feed run queued (job {first[1]}, BIGPART.NC)" in said
    assert f"dncq stop {first[1]}" in said and "dncq run --queue" in said
    assert queued.exit_code == 0 and "Run " in queued.output
    assert [r["state"] for r in table_rows(dncq("runs", "--machine", "2001").output)] == [
        "queued", "queued"]


def test_ctrl_c_while_a_run_is_followed_into_a_log_says_on_the_terminal_that_it_goes_on(
        elsewhere, add_machines, tmp_path, monkeypatch) -> None:
    # `dncq run ... > run.log`: how to stop the run went into the log, the terminal said nothing.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": 9}})  # no worker: it stays queued

    def ctrl_c(_seconds: float) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(run_line, "time", SimpleNamespace(monotonic=time.monotonic,
                                                          sleep=ctrl_c))
    result = dncq("run", "2001", str(_program(tmp_path, 100)))

    started = re.search(r"Run (\S+):", result.stdout)
    assert started and result.exit_code == 130
    assert f"The run goes on. Stop it with: dncq stop {started[1]}" in result.stderr
    assert "The run goes on" not in result.stdout


LONG_MESSAGE = ("link lost at line 48213: the control stopped answering; restart with dncq run "
                "2001 BIGPART.NC --from-line 48213")


@pytest.fixture
def ended_run(elsewhere, settings) -> str:
    """A run that failed with a message longer than a terminal's line; its job's id."""
    from jobs import db
    from jobs.models import Job, JobKind, Run, RunState, Target

    with db.session_scope(settings.resolved_database_url) as session:
        session.add(Job(id="run-long", kind=JobKind.DNC_RUN,
                        targets=[Target(position=0, machine_id="2001")]))
        session.add(Run(job_id="run-long", position=0, machine_id="2001",
                        program_name="BIGPART.NC", program_id="0" * 64, state=RunState.FAILED,
                        lines_total=90_000, last_line=48_213, message=LONG_MESSAGE))
    return "run-long"


def test_runs_lists_a_runs_message_on_its_own_row_cut_to_the_terminal(ended_run) -> None:
    # The messages were a second table below the runs, each job's id said again.
    listed = dncq("runs").output  # in 80 columns

    [run] = table_rows(listed)
    assert len(table_rows(listed.split("\n\n")[0])) == 1  # one table, no second one
    assert run["job"] == ended_run and run["message"].endswith("…")
    assert LONG_MESSAGE.startswith(run["message"].removesuffix("…"))
    assert max(len(line) for line in listed.splitlines()) <= 80


def test_runs_on_a_wide_terminal_or_in_a_pipe_gives_the_whole_message(ended_run) -> None:
    [run] = table_rows(dncq("runs", width=10_000).output)

    assert run["message"] == LONG_MESSAGE


def test_runs_of_one_job_shows_the_run_with_its_whole_message(ended_run) -> None:
    shown = dncq("runs", ended_run)

    assert shown.exit_code == 0, shown.output
    assert f"Run {ended_run}: BIGPART.NC on machine 2001, failed" in shown.output
    assert "48,213 of 90,000" in shown.output
    assert f"  message  {LONG_MESSAGE}" in shown.output


def test_runs_of_a_job_that_is_no_run_says_so(ended_run, settings) -> None:
    from jobs import db
    from jobs.models import Job, JobKind

    with db.session_scope(settings.resolved_database_url) as session:
        session.add(Job(id="send-1", kind=JobKind.SEND))

    shown = dncq("runs", "send-1")

    assert shown.exit_code == 1
    assert "job send-1 is no drip-feed run (send): dncq job send-1 shows it" in shown.output


def test_ctrl_c_before_dncq_answers_a_stop_says_the_run_may_be_stopping(
        elsewhere, add_machines, tmp_path, ctrl_c_before_the_answer) -> None:
    # The run was stopped; the command ended on a bare ^C, the operator left to guess.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": 9}})  # no worker: it stays queued
    started = re.search(r"Run (\S+):", dncq("run", "2001", str(_program(tmp_path, 100)),
                                            "--no-wait").output)
    assert started, "the run was not started"
    ctrl_c_before_the_answer("/stop")

    result = dncq("stop", started[1])

    assert result.exit_code == 130
    assert (f"Stopped before dncq answered. If it had the whole request, run {started[1]} is "
            "stopping all the same: dncq runs shows its state.") in " ".join(result.output.split())
    assert [r["state"] for r in table_rows(dncq("runs", "--machine", "2001").output)] == [
        "cancelled"]  # a run stopped before it started


@pytest.mark.parametrize(("run", "said"), [
    ({"state": "stopped", "line": 4287,
      "message": "stopped by anna at line 4,287; the machine was reset"},
     "Run J1 stopped by anna at line 4,287; the machine was reset"),
    ({"state": "failed", "line": 48213, "message": "link lost: the control stopped answering"},
     "Run J1 failed at line 48,213: link lost: the control stopped answering"),
    ({"state": "succeeded", "line": 20011, "message": "ran to its end"},
     "Run J1 succeeded at line 20,011"),
])
def test_the_line_a_followed_run_ends_on_says_its_line_once(run, said) -> None:
    # A stopped run said "Run J1 stopped at line 4,287: stopped by anna at line 4287; ...".
    assert run_line.ended_line("J1", run) == said
