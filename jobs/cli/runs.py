"""`dncq run|stop|runs`: drip-feed a program to a machine while it runs, and the run history.

Like the job commands they talk to a running dncq through its HTTP API: the program is
uploaded to dncq's store (streamed: any size), the run is a `dnc_run` job, and its bar is
the machine's running line as the API reports it.
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Column

from jobs.cli.common import (
    SinceOpt,
    UntilOpt,
    api_call,
    existing_file,
    fail,
    folded,
    listing,
    local_time,
    out,
    segment,
    upload,
    when,
    whole,
)
from jobs.cli.jobs import WAIT, DryOpt, queue_job
from jobs.cli.library import _who
from jobs.cli.run_line import follow_run


def register(app: typer.Typer) -> None:
    """Add the run commands to the top-level CLI."""
    app.command("run")(run)
    app.command("stop")(stop)
    app.command("runs")(list_runs)


def run(
    machine: Annotated[str, typer.Argument(help="The machine that runs the program")],
    file: Annotated[Path | None, typer.Argument(
        callback=existing_file,
        help="The program (any size: it is streamed); or --library")] = None,
    library: Annotated[str | None, typer.Option(
        "--library", metavar="FOLDER/NAME[@V]",
        help="A library program instead of FILE: its approved version, or version V")] = None,
    from_block: Annotated[str | None, typer.Option(
        "--from", metavar="BLOCK",
        help="Restart from this block number (N1234), with a safe start")] = None,
    from_line: Annotated[int | None, typer.Option(
        "--from-line", metavar="LINE", min=1, help="Restart from this line of the file")] = None,
    from_tool: Annotated[str | None, typer.Option(
        "--from-tool", metavar="TOOL", help="Restart at the change to this tool (T7)")] = None,
    kind: Annotated[str | None, typer.Option(
        "--kind", help="With a restart: read the program as a mill's or a lathe's "
        "(default: from its codes)")] = None,
    dry_run: DryOpt = False,
    queue: Annotated[bool, typer.Option(
        "--queue", help="Queue the run behind one the machine has queued or running, to start "
        "when that one ends, however it ends, whatever the machine's max_concurrent (without "
        "--queue, such a run is refused)")
    ] = False,
    wait: Annotated[bool, typer.Option(
        "--wait/--no-wait", help="Follow the run to its end and exit 1 unless it succeeded "
        "(the default), or return once it is queued")] = WAIT,
) -> None:
    """Drip-feed FILE to MACHINE while it runs it, with a live bar of its running line.

    The machine's control must be in DNC mode (or waiting to receive, on a serial line).
    Ctrl-C leaves the run going; `dncq stop JOB` stops it.
    """
    if (file is None) == (library is None):
        raise fail("give FILE or --library FOLDER/NAME, one of them", code=2)
    shown = api_call("GET", f"/api/machines/{segment(machine)}")
    if "drip-feed" not in shown.get("can", ["drip-feed"]):  # before a byte is uploaded
        raise fail(f"20003 machine {machine} cannot be drip-fed: its {shown.get('transport')} "
                   "transport has no DNC link (dnc or serial drip-feed)")
    program = _upload(file) if file is not None else None
    request: dict[str, Any] = {
        "kind": "dnc_run", "machines": {"ids": [machine]},
        "program": program["id"] if program else None, "library": library,
        "fileName": file.name if file else None, "from_block": from_block,
        "from_line": from_line,
        "from_tool": from_tool, "machine_kind": kind, "dry_run": dry_run, "queue": queue,
        "created_by": "cli"}
    answer = queue_job(request)
    if dry_run:
        _show_restart(answer)
        return
    job_id = answer["id"]
    run = answer["runs"][0] if answer.get("runs") else {}
    out.print(f"Run {job_id}: {run.get('program', '')} on machine {machine}, "
              f"{run.get('linesTotal', 0):,} lines.", highlight=False)
    if not wait:
        out.print(f"Follow it with: dncq job {job_id} --watch; stop it with: dncq stop {job_id}",
                  highlight=False)
        return
    raise typer.Exit(follow_run(job_id))


def _upload(file: Path) -> dict[str, Any]:
    """Stream the file into dncq's program store, with a bar of its bytes."""
    return upload("/api/programs", file)  # type: ignore[no-any-return]


def _show_restart(plan: dict[str, Any]) -> None:
    """What a dry run of a restart would send before the program's own lines."""
    if plan["startLine"] == 1 and not plan["header"]:
        out.print("The run would start at the top: line 1, no header.")
        return
    out.print(f"The run would send this header, then the program from line "
              f"{plan['startLine']:,}:", highlight=False)
    for line in plan["header"]:
        out.print(f"  {line}", highlight=False)


def stop(job_id: Annotated[str, typer.Argument(metavar="JOB", help="The run's job id")]) -> None:
    """Stop a drip-feed run: it ends with its last line (a DNC link resets the machine; an
    RS-232 line sends the end of the tape, or nothing while the control holds it)."""
    maybe = (f"If it had the whole request, run {job_id} is stopping all the same: dncq runs "
             "shows its state.")
    answer = api_call("POST", f"/api/jobs/{segment(job_id)}/stop", params={"by": _who()},
                      if_it_got_there=maybe)
    if not answer["stopping"]:
        raise fail(f"job {job_id} has no run to stop (it has ended)")
    out.print(f"Stopping run {job_id}.", highlight=False)


def list_runs(
    job_id: Annotated[str | None, typer.Argument(
        metavar="JOB", help="One run's job id: that run in full, its whole message")] = None,
    machine: Annotated[str | None, typer.Option(help="Only this machine's runs")] = None,
    program: Annotated[str | None, typer.Option(help="Only runs of this program")] = None,
    state: Annotated[str | None, typer.Option(help="Only runs in this state")] = None,
    since: SinceOpt = None,
    until: UntilOpt = None,
    limit: Annotated[int, typer.Option(min=1, max=1000)] = 50,
) -> None:
    """The run history: every drip-feed run, newest first; or one run (JOB) in full."""
    if job_id is not None:
        if any(v is not None for v in (machine, program, state, since, until)):
            raise fail("give a run's JOB, or the options that choose runs; not both", code=2)
        _show_run(job_id)
        return
    params = {k: v for k, v in (("machine", machine), ("program", program), ("state", state),
                                ("since", when(since)), ("until", when(until)),
                                ("limit", limit)) if v is not None}
    found = api_call("GET", "/api/runs", params=params)
    rows = [(r["jobId"], r["machineID"], r["program"], r["state"],
             f"{r['line']:,}/{r['linesTotal']:,}", _started(r["startedAt"])) for r in found]
    headers = ("job", "machine", "program", "state", "line", "started")
    # The job's id is what `dncq stop` and `dncq runs JOB` take: never cut or folded, and
    # first. A run's message (why it failed, where to restart it) is cut to what the
    # terminal leaves it on the run's own line (a column of its own had a word a line at
    # 80 columns; a table below repeated every id): `dncq runs JOB` shows it whole.
    used = sum(max(map(len, column)) + len("  ")  # its padding and the rule between columns
               for column in zip(headers, *rows, strict=True))
    room = out.width - used
    said = any(r["message"] for r in found)
    columns = [*whole("job", "machine"), folded("program"), *whole("state", "line", "started")]
    if room >= MESSAGE_MIN:
        columns.append(Column("message", no_wrap=True, overflow="ellipsis", max_width=room))
    table = listing(*columns)
    for row, r in zip(rows, found, strict=True):
        table.add_row(*row, *([r["message"] or ""] if room >= MESSAGE_MIN else []))
    out.print(table)
    if said and room < MESSAGE_MIN:  # a few letters and "…" would say nothing
        out.print("\nToo narrow for the runs' messages: dncq runs JOB shows one run's.",
                  style="dim")


MESSAGE_MIN = 12  # the fewest characters of a message worth a column


def _show_run(job_id: str) -> None:
    """The runs of one job (one per machine it runs on), each field on its own line."""
    job = api_call("GET", f"/api/jobs/{segment(job_id)}", params={"limit": 0})
    if not job.get("runs"):
        raise fail(f"job {job_id} is no drip-feed run ({job.get('kind')}): dncq job "
                   f"{job_id} shows it")
    for r in job["runs"]:
        restart = f", restarted from {r['restartFrom']}" if r.get("restartFrom") else ""
        ended = f", ended {local_time(r['endedAt'], seconds=True)}" if r["endedAt"] else ""
        out.print(f"Run {r['jobId']}: {r['program']} on machine {r['machineID']}, {r['state']}",
                  highlight=False)
        for label, value in (
                ("line", f"{r['line']:,} of {r['linesTotal']:,} (from line "
                         f"{r['startLine']:,}{restart})"),
                ("started", (local_time(r["startedAt"], seconds=True) or "not yet")
                 + ended + f", by {r['startedBy']}"),
                ("message", r["message"] or "")):
            out.print(f"  {label:<8} {value}", highlight=False)


def _started(stamp: str | None) -> str:
    """When a run started, short: the time for today's (`04:11`), else the day."""
    shown = local_time(stamp)
    today = datetime.now().astimezone().strftime("%Y-%m-%d")
    return shown[11:] if shown.startswith(today) else shown[:10]
