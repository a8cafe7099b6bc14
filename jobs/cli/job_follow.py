"""How a command follows the job it started: a live progress bar until the job ends, then
its per-target results as a table (exit 1 when a target failed)."""

from __future__ import annotations

import math
import time
from datetime import UTC, datetime
from typing import Any

import typer
from rich.progress import (
    BarColumn,
    DownloadColumn,
    Progress,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
)
from rich.text import Text

from jobs.cli.common import api_call, counted, err, listing, out, segment

CLI_PAGE = 100  # targets a results table shows; --after pages on


def started(job_id: str, wait: bool) -> None:
    """What every command that starts a job does next: follow it, or say how to."""
    if wait:
        follow(job_id)
    else:
        out.print(f"Follow it with: dncq job {job_id} --watch", highlight=False)


def follow(job_id: str, *, state_in_title: bool = True) -> None:
    """Show a live progress bar until the job ends, then its results; exit 1 on failures.

    A send job's bar counts the bytes delivered (a large program to a few machines moves
    long before a target finishes); other jobs count targets. While every target left
    waits for its retry, the line says when the next one is due. Ctrl-C stops following,
    not the job. `state_in_title`: as `show`'s.
    """
    path = f"/api/jobs/{segment(job_id)}"
    try:
        _progress(job_id, path)
    except KeyboardInterrupt:
        err.print(f"Stopped following; job {job_id} goes on. Follow it with: dncq job {job_id} "
                  "--watch", highlight=False)
        raise typer.Exit(130) from None
    show(api_call("GET", path, params={"limit": CLI_PAGE}), state_in_title=state_in_title)


def _progress(job_id: str, path: str) -> None:
    """The live bar, polling the job's summary alone, until no target is left to run."""
    job = api_call("GET", path, params={"limit": 0})
    by_bytes = bool(job.get("bytes", {}).get("total"))
    # One line of an 80-column terminal: the job's id, a short bar with the bytes or the
    # share done, and of the counts only those that are not 0.
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(bar_width=12),
                  DownloadColumn() if by_bytes else TaskProgressColumn(),
                  TextColumn("{task.fields[tally]}"), TimeElapsedColumn(),
                  console=err, disable=not err.is_terminal) as progress:
        bar = progress.add_task(job_id, total=None, tally="")
        while True:
            total, completed = job["total"], _done(job["counts"])
            if by_bytes:
                total, completed = job["bytes"]["total"], job["bytes"]["done"]
            progress.update(bar, total=total, completed=completed, tally=_tally(job))
            if not _left_to_run(job):
                return
            asked = time.monotonic()
            # The API answers when the job ends or after the wait: the bar moves every half
            # second and the results show the moment the last target is done.
            job = api_call("GET", path, params={"limit": 0, "wait_s": PROGRESS_S})
            if _left_to_run(job):  # the pace holds even if an answer came early
                time.sleep(max(0.0, PROGRESS_S - (time.monotonic() - asked)))


PROGRESS_S = 0.5  # how often the bar moves


def _tally(job: dict[str, Any]) -> str:
    """`7/9 done · 1 failed · 1 cancelled · 1 running · retrying in 23 s`, as markup; a
    count of 0 is left out."""
    c = job["counts"]
    parts = [f"{_done(c)}/{job['total']} done"]
    if c["failed"]:
        parts.append(f"[red]{c['failed']} failed[/red]")
    if c["cancelled"]:
        parts.append(f"[yellow]{c['cancelled']} cancelled[/yellow]")
    if c["running"]:
        parts.append(f"{c['running']} running")
    return " · ".join(parts) + _retry_note(job)


def _done(counts: dict[str, int]) -> int:
    """Targets that reached a final state."""
    return counts["succeeded"] + counts["skipped"] + counts["failed"] + counts["cancelled"]


def _left_to_run(job: dict[str, Any]) -> bool:
    return bool(job["counts"]["pending"] or job["counts"]["running"])


def _retry_note(job: dict[str, Any]) -> str:
    """` · retrying in 23 s` while nothing runs and the next try waits for its time."""
    due = job.get("nextAttemptAt")
    if not due or job["counts"]["running"]:
        return ""
    wait_s = (datetime.fromisoformat(due) - datetime.now(UTC)).total_seconds()
    return f" · retrying in {max(0, math.ceil(wait_s))} s"


def _message(target: dict[str, Any]) -> str:
    """The result's message; for a target waiting to try again, why its last try failed."""
    history = target.get("history") or []
    if target["state"] == "pending" and history and history[-1]["errorCode"]:
        last = history[-1]
        return f"waiting to retry after {last['errorCode']} {last['errorMsg']}"
    status = target.get("statusMsg")
    return target["errorMsg"] + (f" ({status})" if status else "")


def _name_the_rest(job: dict[str, Any], page_options: str) -> None:
    """How to list the failed and cancelled targets a page of a large job leaves out: the
    end of a rollout to 200 machines showed its first 100, and `1 failed` below them."""
    for state in ("failed", "cancelled"):
        left_out = job["counts"][state] - sum(t["state"] == state for t in job.get("targets", []))
        if left_out > 0:
            out.print(f"{counted(left_out, f'{state} target')} not in this page: "
                      f"dncq job {job['id']}{page_options} --state {state}", highlight=False)


def show(job: dict[str, Any], page_options: str = "", *, state_in_title: bool = True) -> None:
    """A job's per-target results as a table; exit 1 when any target did not succeed.

    `page_options`: those that chose the page (`--limit 2 --state failed`), which the line
    that says how to see the next one repeats. `state_in_title`: False where the caller
    gives the verdict itself (`backup run`: the backup's, which a job failed on one machine
    of nine is not)."""
    sent = job.get("library")
    of = f", library {sent['path']} v{sent['version']}" if sent and "path" in sent else ""
    request = job["kind"] == "request"  # what the operator asked, and what went back
    table = listing("#", "machine", *(("action",) if request else ()), "file", "state", "code",
                    "message", *(("answer",) if request else ()), "tries",
                    title=f"job {job['id']} ({job['kind']}{of})"
                    + (f": {job['state']}" if state_in_title else "")
                    + (f" (stopped by {job['stoppedBy']})"
                       if state_in_title and job.get("stoppedBy") else ""))
    for t in job.get("targets", []):
        style = "green" if t["state"] in ("succeeded", "skipped") else (
            "yellow" if t["state"] in ("pending", "running") else "red")
        asked = (t.get("action") or "",) if request else ()
        file = "/".join(p for p in (t.get("folder"), t.get("fileName")) if p) if request \
            else t.get("fileName") or ""
        answer = (t.get("answer") or "",) if request else ()
        table.add_row(str(t["position"]), t["machineID"], *asked, file,
                      Text(t["state"], style=style), str(t["errorCode"]), _message(t),
                      *answer, str(t["attempts"]))
    out.print(table)
    if job.get("nextAfter") is not None:
        shown = len(job.get("targets", []))
        filtered = " --state " in page_options or " --machine " in page_options
        of = "the matching targets" if filtered else f"{job['total']} targets"  # not all
        out.print(f"Showing {shown} of {of}; the next ones: "
                  f"dncq job {job['id']}{page_options} --after {job['nextAfter']}",
                  highlight=False)
        if not filtered:
            _name_the_rest(job, page_options)
    c = job["counts"]
    out.print(f"{c['succeeded']} succeeded, {c['skipped']} skipped, {c['failed']} failed, "
              f"{c['cancelled']} cancelled, {c['pending'] + c['running']} not finished")
    if c["failed"] or c["cancelled"]:
        raise typer.Exit(1)
