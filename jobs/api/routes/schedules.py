"""Backup schedules: `/api/schedules`."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Response
from sqlalchemy import select

from jobs import schedules
from jobs.api.deps import SessionDep, SettingsDep, requires
from jobs.api.errors import CodedHTTPError, resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Role
from jobs.backup import follow_up
from jobs.backup_models import Schedule
from jobs.errors import ContractError

router = APIRouter(prefix="/api/schedules", tags=["schedules"],
                   route_class=CheckedRoute)


def _get(session: Any, name: str) -> Schedule:
    with resource_errors():
        return schedules.get(session=session, name=name)


@router.get("", summary="Backup schedules",
            dependencies=[requires(Role.VIEWER)])
def list_schedules(session: SessionDep) -> list[dict[str, Any]]:
    found = session.scalars(select(Schedule).order_by(Schedule.name)).all()
    return [schedules.view(session, s) for s in found]


@router.post("", status_code=201, summary="Add or change a schedule",
             dependencies=[requires(Role.ADMIN, action="schedules.put")])
def put_schedule(session: SessionDep, settings: SettingsDep,
                 schedule_in: schedules.ScheduleIn) -> dict[str, Any]:
    try:
        saved = schedules.upsert(session=session, schedule_in=schedule_in,
                                 data_dir=settings.data_dir)
    except ContractError as exc:  # machines no one has: the request is wrong, not the state
        raise CodedHTTPError(422, exc.code, exc.status_msg) from None
    return schedules.view(session, saved)


@router.get("/{name}", summary="One schedule",
            dependencies=[requires(Role.VIEWER)])
def show_schedule(session: SessionDep, name: str) -> dict[str, Any]:
    return schedules.view(session, _get(session, name))


@router.delete("/{name}", status_code=204, summary="Remove a schedule (its backups stay)",
               dependencies=[requires(Role.ADMIN, action="schedules.delete")])
def delete_schedule(session: SessionDep, name: str) -> Response:
    with resource_errors():
        schedules.delete(session=session, name=name)
    return Response(status_code=204)


@router.post("/{name}/disable", summary="Pause a schedule: it starts no backup until enabled",
             dependencies=[requires(Role.ADMIN, action="schedules.disable")])
def disable_schedule(session: SessionDep, name: str) -> dict[str, Any]:
    return _switched(session, name, enabled=False)


@router.post("/{name}/enable", summary="Resume a paused schedule",
             dependencies=[requires(Role.ADMIN, action="schedules.enable")])
def enable_schedule(session: SessionDep, name: str) -> dict[str, Any]:
    return _switched(session, name, enabled=True)


def _switched(session: Any, name: str, *, enabled: bool) -> dict[str, Any]:
    with resource_errors():  # gone: 404
        return schedules.view(session, schedules.set_enabled(session=session, name=name,
                                                             enabled=enabled))


@router.post("/{name}/run", status_code=202, summary="Run the schedule's backup now",
             dependencies=[requires(Role.ADMIN, action="schedules.run")])
def run_now(settings: SettingsDep, name: str) -> dict[str, Any]:
    with resource_errors():  # gone meanwhile: 404; selecting no machine: 409
        return {"schedule": name, "job": schedules.run_now(settings=settings, name=name)}


@router.post("/prune", summary="Delete backups their schedule's retention no longer keeps",
             dependencies=[requires(Role.ADMIN, action="schedules.prune")])
def prune(settings: SettingsDep, dry_run: bool = False) -> dict[str, Any]:
    return {"dryRun": dry_run, "pruned": follow_up.prune(settings=settings, dry_run=dry_run)}
