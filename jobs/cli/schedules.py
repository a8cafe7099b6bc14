"""`dncq schedule add|list|rm|run-now`: backup schedules from the command line."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

import typer

from jobs.cli.backup_follow import follow_backup
from jobs.cli.client import ApiError
from jobs.cli.common import api_call, client, fail, folded, listing, out, refused, segment, whole
from jobs.cli.help_names import Cli
from jobs.cli.jobs import (
    WAIT,
    AllOpt,
    DirOpt,
    TagOpt,
    ToOpt,
    WaitOpt,
    selector,
)

schedule_app = Cli(help="Backup schedules (cron, time zone, retention, alerts).",
                           no_args_is_help=True)


@schedule_app.command("add")
def add(name: str,
        cron: Annotated[str | None, typer.Option(
            help='Cron expression, e.g. "0 2 * * *" (a new schedule needs it)')] = None,
        tz: Annotated[str | None, typer.Option(
            "--tz", metavar="ZONE", help="Time zone, e.g. Europe/Berlin (default: UTC)")] = None,
        to: ToOpt = None, tag: TagOpt = None, all_: AllOpt = False, folder: DirOpt = None,
        keep: Annotated[str | None, typer.Option(
            metavar="RULES",
            help='Retention, e.g. "last=3,daily=14,weekly=8,monthly=12" (default: keep all)')
        ] = None,
        notify: Annotated[list[str] | None, typer.Option(
            metavar="URL", help="Alert URL (webhook or apprise) when a run is partial or fails; "
                 "repeatable; "
                 "--notify '' removes them")] = None) -> None:
    """Add a schedule (--cron and where: --to, --tag or --all), or change the one of that
    name: what is not given stays as it was (cron, machines, time zone, folder, retention,
    alert URLs, paused)."""
    # An option not given is left out of the request: the API keeps what the schedule has.
    request: dict[str, Any] = {"name": name}
    if cron is not None:
        request["cron"] = cron
    if to or tag or all_:
        request["machines"] = selector(to, tag, all_)
    elif not _exists(name):  # the API's default, every machine, is not a new one's unasked
        if cron is None:
            raise fail("a new schedule needs --cron and where: --to ID[,ID...], --tag TAG or "
                       "--all", code=2)
        selector(to, tag, all_)  # refuses: say where
    if tz is not None:
        request["timezone"] = tz
    if folder is not None:
        request["dirAtCNC"] = folder or None  # --dir '': the machines' whole roots again
    if keep is not None:
        request["retention"] = keep
    if notify is not None:
        request["notify"] = [url for url in notify if url]
    shown = api_call("POST", "/api/schedules", json=request)
    if shown["enabled"]:
        out.print(f"Schedule {name}: next run {_next_run(shown)}.", highlight=False)
    else:
        out.print(f"Schedule {name} saved; it is paused (dncq schedule enable {name}).")


NO_SUCH_SCHEDULE = 158  # the API's code for it, the contract's "Path is not found."


def _exists(name: str) -> bool:
    with client() as c:
        try:
            c.call("GET", f"/api/schedules/{segment(name)}")
        except ApiError as exc:
            if exc.code == NO_SUCH_SCHEDULE:
                return False
            raise refused(exc) from None
    return True


@schedule_app.command("list")
def list_() -> None:
    """Every schedule with its next run ("paused" while it is disabled) and last run."""
    # The runs' times are in the schedule's zone (its `zone` column, folded, never cut: cut
    # with an ellipsis, it no longer said which zone), to the minute; on a narrow terminal
    # they go on below at the space, and the cron stays whole (`30 3 * *` over `*` read as
    # another cron).
    table = listing(*whole("name", "cron"), folded("zone"), "machines", folded("retention"),
                    "next run", "last run")
    for s in api_call("GET", "/api/schedules"):
        m = s["machines"]
        which = "all" if m.get("all") else ", ".join([*m.get("ids", []),
                                                      *(f"#{t}" for t in m.get("tags", []))])
        upcoming = _in_its_zone(s["nextRun"], s["timezone"]) if s["enabled"] else "paused"
        table.add_row(s["name"], s["cron"], s["timezone"], which, s["retention"] or "keep all",
                      upcoming, _in_its_zone(s["lastRun"], s["timezone"]))
    out.print(table)


def _next_run(schedule: dict[str, Any]) -> str:
    """`2026-12-07 02:00 Europe/Berlin`: the next run in the schedule's zone, named."""
    return f"{_in_its_zone(schedule['nextRun'], schedule['timezone'])} {schedule['timezone']}"


def _in_its_zone(stamp: str | None, zone: str) -> str:
    """`2026-12-07T02:00:00+01:00` as `2026-12-07 02:00`: the time in the schedule's zone, in
    which the API gives it; in the hour the clocks repeat, which pass (`02:00 CET`)."""
    from jobs.fire_times import on_the_clock  # croniter with it: for these commands alone

    if stamp is None:
        return ""
    try:
        return on_the_clock(datetime.fromisoformat(stamp), ZoneInfo(zone))
    except (ZoneInfoNotFoundError, ValueError):  # a zone this computer's database lacks
        return stamp[:16].replace("T", " ")


@schedule_app.command("rm")
def rm(name: str) -> None:
    """Remove a schedule (its backups stay)."""
    api_call("DELETE", f"/api/schedules/{segment(name, 'name')}")
    out.print(f"Removed schedule {name}.")


@schedule_app.command("disable")
def disable(name: str) -> None:
    """Pause a schedule: it starts no backup until enabled (its backups stay)."""
    api_call("POST", f"/api/schedules/{segment(name, 'name')}/disable")
    out.print(f"Schedule {name} paused.")


@schedule_app.command("enable")
def enable(name: str) -> None:
    """Resume a paused schedule."""
    shown = api_call("POST", f"/api/schedules/{segment(name, 'name')}/enable")
    out.print(f"Schedule {name}: next run {_next_run(shown)}.", highlight=False)


@schedule_app.command("run-now")
def run_now(name: str, wait: WaitOpt = WAIT) -> None:
    """Run a schedule's backup now."""
    maybe = (f"If it had the whole request, the backup of schedule {name} was started all "
             "the same: dncq jobs --kind backup shows it, and dncq cancel JOB cancels its "
             "targets not started.")
    job_id = api_call("POST", f"/api/schedules/{segment(name, 'name')}/run",
                           if_it_got_there=maybe)["job"]
    out.print(f"Backup job {job_id} of schedule {name}.", highlight=False)
    follow_backup(job_id, wait)
