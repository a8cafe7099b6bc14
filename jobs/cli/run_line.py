"""A drip-feed run followed from the terminal: its running line, live, until it ends.

`dncq run` follows the run it starts; `dncq job ID --watch` follows a run job the same way.
Into a log or a pipe, the line is printed plain from time to time instead.
"""

from __future__ import annotations

import time
from datetime import datetime
from typing import Any

from rich.progress import BarColumn, Progress, TextColumn

from jobs.cli.client import ApiError
from jobs.cli.common import client, err, out, refused, segment

POLL_S = 0.5  # how often a followed run is asked for its line
# Into a log, a plain line: at each change of state, each time the run has gone a
# tenth of its program further, and at least once a minute (a run waiting on its machine).
PLAIN_EVERY_S = 60.0
PLAIN_STEP = 0.1
ENDED = ("succeeded", "stopped", "failed", "cancelled")


def blocks_per_s(run: dict[str, Any]) -> float | None:
    """The run's own rate: the program's lines it ran from its start line (a restart's
    skipped lines are not run) over the time from its start to its last record (its end,
    once ended); None before its first line. The times are the server's, so the figure
    does not depend on when the CLI looked."""
    ran = run.get("line", 0) - (run.get("startLine", 1) - 1)
    until = run.get("endedAt") or run.get("updatedAt")
    if ran <= 0 or not run.get("startedAt") or not until:
        return None
    seconds = (datetime.fromisoformat(until)
               - datetime.fromisoformat(run["startedAt"])).total_seconds()
    return ran / seconds if seconds > 0 else None


def _time_left(run: dict[str, Any], per_s: float | None) -> str:
    """What the program has left at the run's rate, as `0:02:44`; `-:--:--` unknown."""
    left = (run.get("linesTotal") or 0) - run.get("line", 0)
    if not per_s or left < 0:
        return "-:--:--"
    minutes, seconds = divmod(round(left / per_s), 60)
    return f"{minutes // 60}:{minutes % 60:02}:{seconds:02}"


def follow_run(job_id: str) -> int:
    """Show the run's line until it ends; returns the exit status (0: it ran to its end)."""
    columns = (TextColumn("{task.description}"), BarColumn(),
               TextColumn("line {task.completed:,.0f} of {task.fields[of]}"),
               TextColumn("{task.fields[rate]} blocks/s"), TextColumn("{task.fields[left]}"))
    last: dict[str, Any] = {}
    plain = not out.is_terminal  # `> run.log`: the bar, redrawn in place, is not in it
    printed: tuple[float, str, int] | None = None  # when, in which state, at which line
    try:
        with client() as c, Progress(*columns, console=err, disable=not err.is_terminal) as bar:
            task = bar.add_task("line", total=None, rate="-", of="?", left="")
            while True:
                job = c.call("GET", f"/api/jobs/{segment(job_id)}", params={"limit": 0})
                run = job["runs"][0] if job.get("runs") else {}
                last = run
                line, total = run.get("line", 0), run.get("linesTotal") or None
                per_s = blocks_per_s(run)
                rate = "-" if per_s is None else f"{per_s:,.0f}"
                state = run.get("state", job["state"])
                of = f"{total:,}" if total else "?"
                bar.update(task, completed=line, total=total, rate=rate, of=of,
                           description=state, left=_time_left(run, per_s))
                now = time.monotonic()
                if plain and (printed is None or state != printed[1]
                              or now - printed[0] >= PLAIN_EVERY_S
                              or line - printed[2] >= PLAIN_STEP * (total or 0) > 0):
                    out.print(f"{state} line {line:,} of {of}, {rate} blocks/s", highlight=False)
                    printed = (now, state, line)
                if state in ENDED:
                    break
                time.sleep(POLL_S)
    except ApiError as exc:
        raise refused(exc) from None
    except KeyboardInterrupt:  # said where the user is, not into the log the run's lines go to
        err.print(f"\nThe run goes on. Stop it with: dncq stop {job_id}", highlight=False)
        return 130
    out.print(ended_line(job_id, last), highlight=False)
    return 0 if last.get("state") == "succeeded" else 1


def ended_line(job_id: str, run: dict[str, Any]) -> str:
    """The line that says how a followed run ended, at which line, and why."""
    state, message = run.get("state"), run.get("message") or ""
    if state == "stopped" and message.startswith("stopped "):  # says the line, and who
        return f"Run {job_id} {message}"
    said = f"Run {job_id} {state} at line {run.get('line', 0):,}"
    if message and state != "succeeded":  # a success's only says the line again
        said += f": {message}"
    return said
