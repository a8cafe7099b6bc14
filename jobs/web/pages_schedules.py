"""The schedules page: backup schedules listed, added, changed, paused, removed, run now.

A schedule is saved as the API saves it (`POST /api/schedules`): checked by
`schedules.ScheduleIn`, then written by name in one statement. Two admins saving one
schedule at once both land and the later save is what stays (last write wins, as the API);
the form says so.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Form, Request
from fastapi.responses import HTMLResponse, Response
from pydantic import ValidationError
from sqlalchemy import select
from sqlalchemy.orm import Session

from jobs import rollout, schedules
from jobs.backup_models import Schedule
from jobs.errors import ContractError, resource_status, validation_summary
from jobs.web.deps import (
    PageRoute,
    SessionDep,
    SettingsDep,
    Viewer,
    ViewerDep,
    acting,
    audit,
    render,
    told,
)
from jobs.web.principal import Role
from jobs.web.refusals import audited_as

router = APIRouter(route_class=PageRoute)

Admin = Annotated[Viewer, Depends(acting(Role.ADMIN))]
Text = Annotated[str, Form(max_length=1000)]
PAGE = "/schedules"


def _words(text: str) -> list[str]:
    """A form's list: items separated by commas, spaces or lines."""
    return [w for w in text.replace(",", " ").split() if w]


def _form_of(schedule: Schedule) -> dict[str, Any]:
    """A stored schedule as the form shows it to be changed (its alert URLs stay hidden)."""
    chosen = schedule.machines
    return {"name": schedule.name, "cron": schedule.cron, "timezone": schedule.timezone,
            "ids": ", ".join(chosen.get("ids", [])), "tags": ", ".join(chosen.get("tags", [])),
            "all": chosen.get("all", False), "dir": schedule.dir_at_cnc or "",
            "retention": schedule.retention, "notify": "", "kept_alerts": len(schedule.notify),
            "enabled": schedule.enabled, "editing": True}


def _page(request: Request, session: Session, who: Viewer, status: int = 200,
          **context: Any) -> Response:
    found = session.scalars(select(Schedule).order_by(Schedule.name)).all()
    edit = request.query_params.get("edit")
    form = context.pop("form", None)
    if form is None and edit:
        form = _form_of(schedules.get(session=session, name=edit))  # 404 when gone
    return render(request, who, "schedules.html", status=status,
                  schedules=[schedules.view(session, s) for s in found],
                  form=form or {"timezone": "UTC", "all": True, "enabled": True},
                  message=request.query_params.get("message"), **context)


@router.get(PAGE, response_class=HTMLResponse)
def schedules_page(request: Request, session: SessionDep, who: ViewerDep) -> Response:
    return _page(request, session, who)


@router.post(PAGE)
@audited_as("save schedule")
def save_schedule(request: Request, session: SessionDep, settings: SettingsDep, who: Admin,
                  name: Annotated[str, Form(max_length=100)], cron: Annotated[str, Form()],
                  timezone: Text = "UTC", ids: Text = "", tags: Text = "",
                  every_machine: Annotated[str, Form(alias="all")] = "",
                  dir: Text = "", retention: Text = "",
                  notify: Annotated[str, Form(max_length=10_000)] = "",
                  clear_alerts: Text = "", enabled: Text = "", editing: Text = "",
                  shown_enabled: Text = "") -> Response:
    """Add a schedule, or change the one of that name (the later of two saves stays).

    An edit form sent after the schedule was removed adds nothing back, and one whose
    *enabled* box was left as shown keeps what the schedule is now: another admin's
    *Remove* or *Disable* meanwhile is not undone by a form opened before it."""
    form = {"name": name, "cron": cron, "timezone": timezone, "ids": ids, "tags": tags,
            "all": every_machine == "on", "dir": dir, "retention": retention,
            "notify": notify, "enabled": enabled == "on"}
    before = session.get(Schedule, name.strip())
    if editing == "on" and before is None:
        audit(request, session, who, action="save schedule", target=name, status=409)
        return told(PAGE, f"Schedule {name} was removed meanwhile; it was not saved. "
                          "Add it again if it is still wanted.")
    if editing == "on" and before is not None and enabled == shown_enabled:
        enabled = "on" if before.enabled else ""  # as it is now, say the box was untouched
    urls = _words(notify)
    # The form never shows them: left empty, the alert URLs are left out, and kept.
    alerts = {} if not urls and clear_alerts != "on" else {"notify": urls}
    try:
        schedule_in = schedules.ScheduleIn(
            name=name.strip(), cron=cron.strip(), timezone=timezone.strip() or "UTC",
            machines=rollout.Selector(ids=_words(ids), tags=_words(tags),
                                      all=every_machine == "on"),
            dirAtCNC=dir.strip() or None, retention=retention.strip(),
            enabled=enabled == "on", **alerts)
        schedules.upsert(session=session, schedule_in=schedule_in, data_dir=settings.data_dir)
    except (ValidationError, ContractError) as exc:  # nothing was saved
        reason = (validation_summary(exc.errors()) if isinstance(exc, ValidationError)
                  else exc.status_msg)
        # as the API answers it: a schedule that does not parse 400, machines no one has 422
        status = 400 if isinstance(exc, ValidationError) else 422
        audit(request, session, who, action="save schedule", target=name, status=status,
              detail={"cron": cron})
        return _page(request, session, who, status=status, form={
            **form, "editing": before is not None,
            "kept_alerts": len(before.notify) if before else 0},
            error=f"Schedule {name} not saved: {reason}")
    audit(request, session, who, action="save schedule", target=schedule_in.name,
          detail={"cron": schedule_in.cron, "machines": schedule_in.machines.model_dump(),
                  "new": before is None})
    done = "Added" if before is None else "Saved"
    return told(PAGE, f"{done} schedule {schedule_in.name}: {schedule_in.cron} "
                      f"({schedule_in.timezone}).")


def _switched(request: Request, session: Session, who: Viewer, name: str, *,
              enabled: bool) -> Response:
    schedules.set_enabled(session=session, name=name, enabled=enabled)  # 404 when gone
    audit(request, session, who, action="enable schedule" if enabled else "disable schedule",
          target=name)
    return told(PAGE, f"Schedule {name} runs again at its times." if enabled else
                f"Schedule {name} is paused: it starts no backup until enabled.")


@router.post(PAGE + "/{name}/enable")
@audited_as("enable schedule")
def enable_schedule(request: Request, session: SessionDep, who: Admin, name: str) -> Response:
    return _switched(request, session, who, name, enabled=True)


@router.post(PAGE + "/{name}/disable")
@audited_as("disable schedule")
def disable_schedule(request: Request, session: SessionDep, who: Admin,
                     name: str) -> Response:
    return _switched(request, session, who, name, enabled=False)


@router.post(PAGE + "/{name}/delete")
@audited_as("delete schedule")
def delete_schedule(request: Request, session: SessionDep, who: Admin, name: str) -> Response:
    schedules.delete(session=session, name=name)  # 404 when gone
    audit(request, session, who, action="delete schedule", target=name)
    return told(PAGE, f"Removed schedule {name}; its backups stay.")


@router.post(PAGE + "/{name}/run")
@audited_as("run schedule")
def run_schedule(request: Request, session: SessionDep, settings: SettingsDep, who: Admin,
                 name: str) -> Response:
    status = 200
    try:
        job_id = schedules.run_now(settings=settings, name=name)
        message = f"Started backup job {job_id}."
    except ContractError as exc:  # as the API answers it: gone 404, no machine chosen 409
        message, status = f"Not started: {exc.status_msg}", resource_status(exc)
    audit(request, session, who, action="run schedule", target=name, status=status)
    return told(PAGE, message)
