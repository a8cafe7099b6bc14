"""Admin API of the machine registry: `/api/machines`."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Response
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session
from sqlalchemy.orm.exc import StaleDataError

from jobs import rollout
from jobs.api.deps import SessionDep, SettingsDep, requires
from jobs.api.errors import CodedHTTPError, resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Role
from jobs.errors import ContractError, ErrorCode, validation_summary
from jobs.fleet import door, fleet_file, registry
from jobs.run import checking
from jobs.settings import Settings

router = APIRouter(prefix="/api/machines", tags=["machines"],
                   route_class=CheckedRoute)


def _saved(session: Session, settings: Settings, machine_in: registry.MachineIn, *,
           new: bool = False) -> dict[str, Any]:
    """Add or replace the machine; a 422 that names what is wrong with it.

    Another request that saved or removed the same machine meanwhile makes this one a 409
    when it was to add a `new` machine; a replace is saved once more over the other's
    result, and is a 409 only when that is changed meanwhile too.
    """
    try:
        return _upsert(session, settings, machine_in)
    except (IntegrityError, StaleDataError):
        session.rollback()
        if new:
            raise HTTPException(409, detail=f"machine {machine_in.id} exists; "
                                            "use PUT to change it") from None
    try:
        return _upsert(session, settings, machine_in)
    except (IntegrityError, StaleDataError):
        session.rollback()
        raise HTTPException(409, detail=f"machine {machine_in.id} was changed meanwhile; "
                                        "try again") from None


def _upsert(session: Session, settings: Settings,
            machine_in: registry.MachineIn) -> dict[str, Any]:
    try:
        spec, _ = registry.upsert(session=session, machine_in=machine_in,
                                  data_dir=settings.data_dir)
    except ValidationError as exc:  # the transport's options
        raise HTTPException(422, detail=validation_summary(exc.errors(), under="options")) from None
    except (ValueError, ContractError) as exc:
        raise HTTPException(422, detail=str(exc)) from None
    return spec.public()


@router.get("", summary="List machines",
            dependencies=[requires(Role.VIEWER)])
def list_machines(session: SessionDep, tag: str | None = None) -> list[dict[str, Any]]:
    found = registry.list_all(session=session, tag=tag)
    if tag and not found:  # a mistyped tag, named as a rollout to it names it
        unknown = rollout.unknown(session=session, selector=rollout.Selector(tags=[tag]))
        if unknown:
            raise CodedHTTPError(422, ErrorCode.BAD_PARAMETER, unknown.message())
    return [m.public() for m in found]


@router.post("", status_code=201, summary="Add a machine",
             dependencies=[requires(Role.ADMIN, action="machines.add")])
def add_machine(session: SessionDep, settings: SettingsDep,
                machine_in: registry.MachineIn) -> dict[str, Any]:
    if session.get(registry.Machine, machine_in.id) is not None:
        raise HTTPException(409, detail=f"machine {machine_in.id} exists; use PUT to change it")
    return _saved(session, settings, machine_in, new=True)


class FleetFile(BaseModel):
    """A fleet file's text, as `dncq machines import` sends it."""

    model_config = ConfigDict(extra="forbid")

    fleet: str = Field(description="YAML with a `machines:` list, as in a fleet file")


@router.post("/import", summary="Add or update the machines of a fleet file (all or none)",
             dependencies=[requires(Role.ADMIN, action="machines.import")])
def import_fleet(session: SessionDep, settings: SettingsDep,
                 fleet_in: FleetFile) -> dict[str, int]:
    try:
        machines = fleet_file.parse_fleet(fleet_in.fleet)
        added, updated = fleet_file.import_fleet(session=session, machines=machines,
                                                 data_dir=settings.data_dir)
    except fleet_file.FleetFileError as exc:
        session.rollback()
        raise HTTPException(422, detail=str(exc)) from None
    return {"added": added, "updated": updated}


class CheckRequest(BaseModel):
    """Which machines to check."""

    model_config = ConfigDict(extra="forbid")

    ids: list[str] = Field(default_factory=list)
    all: bool = False


@router.post("/check", summary="Connect to machines: whether they answer, how fast, what they "
             "can do",
             dependencies=[requires(Role.VIEWER, action="machines.check")])
def check_machines(session: SessionDep, settings: SettingsDep,
                   request: CheckRequest) -> list[dict[str, Any]]:
    if not (request.ids or request.all):
        raise HTTPException(422, detail="give ids or all")
    with resource_errors():
        specs = (registry.list_all(session=session) if request.all else
                 [registry.get(session=session, machine_id=m) for m in request.ids])
    session.commit()  # no read transaction open while the machines answer
    return checking.check_now(settings, specs)


@router.get("/{machine_id}", summary="Show a machine, its model's roots and what it can do",
            dependencies=[requires(Role.VIEWER)])
def show_machine(session: SessionDep, machine_id: str) -> dict[str, Any]:
    with resource_errors():
        spec = registry.get(session=session, machine_id=machine_id)
    return {**spec.public(), "roots": list(registry.governing_row(spec).roots),
            "can": door.abilities(spec)}


@router.put("/{machine_id}", summary="Add or replace a machine",
            dependencies=[requires(Role.ADMIN, action="machines.put")])
def put_machine(session: SessionDep, settings: SettingsDep, machine_id: str,
                machine_in: registry.MachineIn) -> dict[str, Any]:
    if machine_in.id != machine_id:
        raise HTTPException(422, detail="id in the body differs from the path")
    return _saved(session, settings, machine_in)


@router.delete("/{machine_id}", status_code=204, summary="Remove a machine",
               dependencies=[requires(Role.ADMIN, action="machines.delete")])
def delete_machine(session: SessionDep, machine_id: str) -> Response:
    with resource_errors():
        registry.delete(session=session, machine_id=machine_id)
    return Response(status_code=204)


