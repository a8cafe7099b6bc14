"""A drip-feed run followed from the terminal: its running line, live, until it ends.

`dncq run` follows the run it starts; `dncq job ID --watch` follows a run job the same way.
"""

from __future__ import annotations

import time
from typing import Any

from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from jobs.cli.client import ApiError
from jobs.cli.common import client, err, fail, out, segment

POLL_S = 0.5  # how often a followed run is asked for its line
ENDED = ("succeeded", "stopped", "failed", "cancelled")


def follow_run(job_id: str) -> int:
    """Show the run's line until it ends; returns the exit status (0: it ran to its end)."""
    columns = (TextColumn("{task.description}"), BarColumn(),
               TextColumn("line {task.completed:,.0f} of {task.fields[of]}"),
               TextColumn("{task.fields[rate]} blocks/s"), TimeRemainingColumn())
    last: dict[str, Any] = {}
    try:
        with client() as c, Progress(*columns, console=err) as bar:
            task = bar.add_task("line", total=None, rate="-", of="?")
            seen: tuple[float, int] | None = None
            while True:
                job = c.call("GET", f"/api/jobs/{segment(job_id)}", params={"limit": 0})
                run = job["runs"][0] if job.get("runs") else {}
                last = run
                line, total = run.get("line", 0), run.get("linesTotal") or None
                now = time.monotonic()
                rate = "-"
                if seen is not None and now > seen[0] and line >= seen[1]:
                    rate = f"{(line - seen[1]) / (now - seen[0]):,.0f}"
                seen = (now, line)
                state = run.get("state", job["state"])
                bar.update(task, completed=line, total=total, rate=rate,
                           of=f"{total:,}" if total else "?", description=state)
                if state in ENDED:
                    break
                time.sleep(POLL_S)
    except ApiError as exc:
        raise fail(str(exc)) from None
    except KeyboardInterrupt:
        out.print(f"\nThe run goes on. Stop it with: dncq stop {job_id}", highlight=False)
        return 130
    message = last.get("message") or ""
    said = f"Run {job_id} {last.get('state')} at line {last.get('line', 0):,}"
    if message and last.get("state") != "succeeded":  # a success's only says the line again
        said += f": {message}"
    out.print(said, highlight=False)
    return 0 if last.get("state") == "succeeded" else 1
