"""`dncq send|delete|jobs|job|retry|cancel|restore-replaced`: batch work from the command line.

These commands talk to a running dncq through its HTTP API, so they work the same
against the embedded demo and a distributed installation.
"""

from __future__ import annotations

import shlex
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Column

from jobs.cli.backup_follow import follow_backup
from jobs.cli.client import ApiError
from jobs.cli.common import (
    SinceOpt,
    UntilOpt,
    api_call,
    client,
    counted,
    existing_database,
    existing_file,
    fail,
    listing,
    local_time,
    out,
    refused,
    segment,
    shown_database,
    stopped_before_the_answer,
    when,
    whole,
)
from jobs.cli.help_names import Cli
from jobs.cli.job_follow import CLI_PAGE, follow, show, started
from jobs.cli.json_body import FileBody, FileChanged
from jobs.cli.library import _who
from jobs.cli.run_line import follow_run

jobs_app = Cli(help="Jobs: list them, or prune old ones.", invoke_without_command=True)

ToOpt = Annotated[str | None, typer.Option(
    "--to", metavar="IDS", help="Machine ids, comma-separated")]
TagOpt = Annotated[list[str] | None, typer.Option("--tag", help="Machines with this tag")]
AllOpt = Annotated[bool, typer.Option("--all", help="Every machine of the fleet")]
DirOpt = Annotated[str | None, typer.Option("--dir", "-d", help="Folder (dirAtCNC)")]
# One rule for every command that starts a job: it follows the job to its end unless --no-wait.
WAIT = True
WaitOpt = Annotated[bool, typer.Option(
    "--wait/--no-wait", help="Follow the job to its end and exit 1 if a target failed "
    "(the default), or return once it is queued")]
YesOpt = Annotated[bool, typer.Option("--yes", "-y", help="Do not ask before fleet-wide changes")]
DryOpt = Annotated[bool, typer.Option("--dry-run", help="Show what would happen, change nothing")]
ForceOpt = Annotated[bool, typer.Option(
    "--force", help="Also touch the program a machine is running")]
AnywayOpt = Annotated[bool, typer.Option(
    "--anyway", help="Queue it even when --to or --tag names machines or tags that are not "
    "there (an unknown id then fails as its own target)")]


def selector(to: str | None, tags: list[str] | None, all_: bool) -> dict[str, Any]:
    """The `machines` selector of a job request from --to, --tag and --all."""
    ids = [m.strip() for m in (to or "").split(",") if m.strip()]
    if not (ids or tags or all_):
        raise fail("say where: --to ID[,ID...], --tag TAG or --all", code=2)
    return {"ids": ids, "tags": tags or [], "all": all_}


def _confirm_fleet_wide(all_: bool, risky: bool, yes: bool, what: str) -> None:
    if all_ and risky and not yes and not typer.confirm(f"{what} on EVERY machine?"):
        raise fail("not confirmed; nothing was done", code=1)


def queue_job(request: dict[str, Any], *, file: Path | None = None) -> dict[str, Any]:
    """POST the job request (with `file`'s bytes as its `base64`, streamed); a selection
    naming machines or tags that are not there is refused by the API, and the user told how
    to queue it anyway."""
    try:
        with client() as c:
            if file is None:
                return c.call("POST", "/api/jobs", json=request)  # type: ignore[no-any-return]
            body = FileBody(request, key="base64", file=file)
            c.refuse_over_the_limit(body.length_bytes, limit="maxJsonBodyBytes")
            return c.call(  # type: ignore[no-any-return]
                "POST", "/api/jobs", content=iter(body), headers=body.headers())
    except FileChanged as exc:  # the body ended short: dncq took none of it
        raise fail(f"{exc}; nothing was queued") from None
    except KeyboardInterrupt:
        if request.get("dry_run"):
            raise
        # dncq records a job once it has the whole request: a Ctrl-C while it answers
        # left a rollout to the fleet running, its id never said.
        raise stopped_before_the_answer(_maybe_queued(request["kind"])) from None
    except ApiError as exc:
        hint = "; check the ids and tags, or add --anyway" if exc.refused_selection else ""
        if exc.body_too_large and file is not None:  # the file, in the JSON body
            hint = ("; a send job carries its file inside the request: add a program this "
                    "large to the library (dncq library add FILE --folder FOLDER "
                    "--approve), streamed, and send it with --library FOLDER/NAME")
        raise refused(exc, hint) from None


def _maybe_queued(kind: str) -> str:
    """What a Ctrl-C before the answer may have left running, and how to find and end it."""
    if kind == "dnc_run":
        return ("If it had the whole request, the run was started all the same: dncq runs "
                "shows it, and dncq stop JOB stops it.")
    return ("If it had the whole request, the job was queued all the same: dncq jobs shows "
            "it, and dncq cancel JOB cancels its targets not started.")


# What a restore asked (`restore-replaced`, `backup restore`) may have left queued.
MAYBE_RESTORING = ("If it had the whole request, the restore job was queued all the same: "
                   "dncq jobs --kind restore shows it, and dncq cancel JOB cancels its "
                   "targets not started.")


def show_plan(plan: dict[str, Any]) -> None:
    """A dry run's plan: what each target would do, and the ids and tags that are not there."""
    table = listing("#", "machine", "file", "would", "error")
    for t in plan["targets"]:
        table.add_row(str(t["position"]), t["machineID"], t.get("fileName") or "",
                      t["action"], "" if not t["errorCode"] else
                      f"{t['errorCode']} {t['errorMsg']}")
    out.print(table)
    if plan.get("unknown"):
        out.print(f"Not there: {plan['unknown']['message']}; without --anyway nothing would be "
                  "queued.", style="yellow", highlight=False)


def submit(request: dict[str, Any], wait: bool, *, said: str = "Job {id}: {total}.",
           counting: str = "target", then: Callable[[str, bool], None] | None = None,
           file: Path | None = None) -> None:
    """Queue the job request (a dry run: show its plan), say so with `said` (`{total}`: its
    count of targets, `counted` as `counting`), and follow it as every command that starts
    a job does (`then`, `started` by default); `file` is sent as its `base64`."""
    if request.get("dry_run"):
        show_plan(queue_job(request, file=file))
        return
    job = queue_job(request, file=file)
    out.print(said.format(id=job["id"], total=counted(job["total"], counting)),
              highlight=False)
    (then or started)(job["id"], wait)


def send(
    path: Annotated[Path | None, typer.Argument(
        metavar="FILE", callback=existing_file, help="The file; or give --library")]
    = None,
    library: Annotated[str | None, typer.Option(
        "--library", "-l", metavar="FOLDER/NAME[@V]",
        help="A library program: its current approved version, or version V")] = None,
    to: ToOpt = None, tag: TagOpt = None, all_: AllOpt = False, folder: DirOpt = None,
    name: Annotated[str | None, typer.Option("--name", "-n", help="Name on the machines")]
    = None,
    replace: Annotated[bool, typer.Option(
        "--replace", help="Replace an existing file (kept to restore)")]
    = False,
    skip_identical: Annotated[bool, typer.Option(
        "--skip-identical", help="Skip machines that have these bytes")]
    = False,
    verify: Annotated[bool, typer.Option(
        "--verify", help="Read back and compare after sending")] = False,
    force: ForceOpt = False,
    deliver_within: Annotated[str | None, typer.Option(
        metavar="DURATION", help="Keep retrying offline machines this long (e.g. 12h)")] = None,
    abort_after: Annotated[int | None, typer.Option(help="Stop after N failed targets")] = None,
    dry_run: DryOpt = False, yes: YesOpt = False, wait: WaitOpt = WAIT,
    anyway: AnywayOpt = False,
) -> None:
    """Send one program to many machines (mass rollout): a file, or a library version."""
    if (path is None) == (library is None):
        raise fail("give a FILE or --library FOLDER/NAME[@V], one of them", code=2)
    payload: dict[str, Any] = {}
    if library is not None:
        reference, at, number = library.rpartition("@")
        if not (at and number.isdecimal()):
            reference, number = library, ""
        payload = {"library": reference, "library_version": int(number) if number else None}
        shown = name or reference.rpartition("/")[2]
    else:
        assert path is not None
        # Streamed as it is sent: a file over the API's limit is refused from the body's
        # length before it is read (it was read and encoded whole first: 1 GB for 200 MB).
        shown = name or path.name
    _confirm_fleet_wide(all_, replace and not dry_run, yes, f"Replace {shown}")
    submit({
        "kind": "send", **payload,
        "machines": selector(to, tag, all_), "fileName": name or (path.name if path else None),
        "dirAtCNC": folder,
        "replace": replace, "skip_identical": skip_identical, "verify": verify, "force": force,
        "deliver_within": deliver_within, "abort_after_failures": abort_after,
        "dry_run": dry_run, "allow_unknown": anyway, "created_by": "cli",
    }, wait, file=path)


def delete(
    name: Annotated[str, typer.Argument(metavar="NAME", help="File name on the machines")],
    to: ToOpt = None, tag: TagOpt = None, all_: AllOpt = False, folder: DirOpt = None,
    force: ForceOpt = False, dry_run: DryOpt = False, yes: YesOpt = False, wait: WaitOpt = WAIT,
    anyway: AnywayOpt = False,
) -> None:
    """Delete one file on many machines."""
    _confirm_fleet_wide(all_, not dry_run, yes, f"Delete {name}")
    submit({"kind": "delete", "machines": selector(to, tag, all_), "fileName": name,
             "dirAtCNC": folder, "force": force, "dry_run": dry_run, "allow_unknown": anyway,
             "created_by": "cli"}, wait)


@jobs_app.callback()
def jobs_list(
    ctx: typer.Context,
    state: Annotated[str | None, typer.Option(
        help="Only jobs in this state: queued, running, succeeded, failed, cancelled")] = None,
    kind: Annotated[str | None, typer.Option(
        help="Only jobs of this kind: send, delete, backup, restore, dnc_run, request")] = None,
    machine: Annotated[str | None, typer.Option(help="Jobs with a target on this machine")]
    = None,
    since: SinceOpt = None, until: UntilOpt = None,
    limit: Annotated[int, typer.Option(help="At most this many, newest first")] = 30,
) -> None:
    """List jobs, newest first."""
    if ctx.invoked_subcommand:
        return
    params = {k: v for k, v in (("state", state), ("kind", kind), ("machine", machine),
                                ("since", when(since)), ("until", when(until)),
                                ("limit", limit)) if v is not None}
    # What says which job it is, where it stands and when it was made is never cut short;
    # the file's name and the targets wrap in what an 80-column terminal leaves them.
    table = listing(*whole("id", "kind", "state"), "file",
                    Column("targets", min_width=len("cancelled")), *whole("created"))
    for job in api_call("GET", "/api/jobs", params=params):
        table.add_row(job["id"], job["kind"], job["state"], job["fileName"] or "",
                      _targets(job["counts"]), local_time(job["createdAt"]))
    out.print(table)


def _targets(counts: dict[str, int]) -> str:
    """A job's targets in words, those of no target left out: `2 ok, 1 cancelled`,
    `3 ok, 1 failed, 496 left` while it runs."""
    by_word = {"ok": counts["succeeded"] + counts["skipped"], "failed": counts["failed"],
               "cancelled": counts["cancelled"]}
    by_word["left"] = sum(counts.values()) - sum(by_word.values())  # pending or running
    return ", ".join(f"{n} {word}" for word, n in by_word.items() if n) or "none"


@jobs_app.command("prune")
def jobs_prune(older_than_days: Annotated[int | None, typer.Option(
        "--older-than-days", min=0, max=36500,
        help="Default: the job_retention_days setting")] = None) -> None:
    """Delete finished jobs older than the retention period, and payloads no job needs."""
    from jobs import db, service
    from jobs.settings import get_settings

    settings = get_settings()
    days = older_than_days if older_than_days is not None else settings.job_retention_days
    url = existing_database()
    db.upgrade(url)
    with db.session_scope(url) as session:
        n = service.prune(session=session, older_than=timedelta(days=days))
    out.print(f"Pruned {n} jobs finished more than {days} days ago from the database "
              f"{shown_database(url)}.", highlight=False)


def job(job_id: Annotated[str, typer.Argument(metavar="ID")],
        watch: Annotated[bool, typer.Option("--watch", "-w", help="Follow it live")] = False,
        state: Annotated[str | None, typer.Option(
            help="Only targets in this state (pending, running, succeeded, failed...)")] = None,
        machine: Annotated[str | None, typer.Option(help="Only this machine's targets")] = None,
        limit: Annotated[int, typer.Option(min=1, help="Targets shown at most")] = CLI_PAGE,
        after: Annotated[int | None, typer.Option(
            metavar="POSITION",
            help="Targets after this position (as the previous page said)")] = None,
        ) -> None:
    """Show a job's progress and its per-target results in order, a page at a time."""
    if watch:
        summary = api_call("GET", f"/api/jobs/{segment(job_id)}", params={"limit": 0})
        if summary.get("kind") == "dnc_run":  # its running line, as `dncq run` shows it
            raise typer.Exit(follow_run(job_id))
        if summary.get("kind") == "backup":  # then its ZIP, as `dncq backup run` says it
            follow_backup(job_id, wait=True)
            return
        follow(job_id)
    else:
        params = {"limit": limit, "after": after, "state": state, "machine": machine}
        chosen = {"limit": limit if limit != CLI_PAGE else None, "state": state,
                  "machine": machine}
        show(api_call("GET", f"/api/jobs/{segment(job_id)}",
                      params={k: v for k, v in params.items() if v is not None}),
             page_options="".join(f" --{k} {shlex.quote(str(v))}" for k, v in chosen.items()
                           if v is not None))


def retry(job_id: Annotated[str, typer.Argument(metavar="ID")], wait: WaitOpt = WAIT) -> None:
    """Run a job's failed and cancelled targets again (the history of attempts is kept)."""
    maybe = (f"If it had the whole request, the failed and cancelled targets of job {job_id} "
             f"were queued again all the same: dncq job {job_id} shows them, and dncq cancel "
             f"{job_id} cancels those not started.")
    n = api_call("POST", f"/api/jobs/{segment(job_id)}/retry",
                      if_it_got_there=maybe)["retried"]
    if not n:  # not an error: what was to be done is done, or under way
        out.print(f"Nothing to retry: job {job_id} has no failed or cancelled target.")
        return
    out.print(f"Retrying {counted(n, 'target')} of job {job_id}.")
    started(job_id, wait)


def cancel(job_id: Annotated[str, typer.Argument(metavar="ID")]) -> None:
    """Cancel the targets not started yet; running ones finish."""
    maybe = (f"If it had the whole request, the targets of job {job_id} not started were "
             f"cancelled all the same: dncq job {job_id} shows them.")
    n = api_call("POST", f"/api/jobs/{segment(job_id)}/cancel", params={"by": _who()},
                 if_it_got_there=maybe)["cancelled"]
    out.print(f"Cancelled {counted(n, 'target')} of job {job_id}.")


def restore_replaced(job_id: Annotated[str, typer.Argument(metavar="JOB")],
                     wait: WaitOpt = WAIT) -> None:
    """Put back every file a replace rollout overwrote."""
    restore = api_call("POST", f"/api/jobs/{segment(job_id)}/restore-replaced",
                            if_it_got_there=MAYBE_RESTORING)
    out.print(f"Restore job {restore['id']}: {restore['total']} files.")
    started(restore["id"], wait)


def register(app: typer.Typer) -> None:
    """Add the batch commands to the `dncq` app."""
    app.command()(send)
    app.command()(delete)
    app.add_typer(jobs_app, name="jobs")
    app.command()(job)
    app.command()(retry)
    app.command()(cancel)
    app.command("restore-replaced")(restore_replaced)
