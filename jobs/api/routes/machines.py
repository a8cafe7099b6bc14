"""Admin API of the machine registry: `/api/machines`."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Response
from pydantic import ValidationError
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session
from sqlalchemy.orm.exc import StaleDataError

from jobs.api.deps import SessionDep
from jobs.api.errors import resource_errors
from jobs.api.text import CheckedRoute
from jobs.errors import ContractError, validation_summary
from jobs.fleet import registry

router = APIRouter(prefix="/api/machines", tags=["machines"],
                   route_class=CheckedRoute)


def _saved(session: Session, machine_in: registry.MachineIn, *,
           new: bool = False) -> dict[str, Any]:
    """Add or replace the machine; a 422 that names what is wrong with it.

    Another request that saved or removed the same machine meanwhile makes this one a 409
    when it was to add a `new` machine; a replace is saved once more over the other's
    result, and is a 409 only when that is changed meanwhile too.
    """
    try:
        return _upsert(session, machine_in)
    except (IntegrityError, StaleDataError):
        session.rollback()
        if new:
            raise HTTPException(409, detail=f"machine {machine_in.id} exists; "
                                            "use PUT to change it") from None
    try:
        return _upsert(session, machine_in)
    except (IntegrityError, StaleDataError):
        session.rollback()
        raise HTTPException(409, detail=f"machine {machine_in.id} was changed meanwhile; "
                                        "try again") from None


def _upsert(session: Session, machine_in: registry.MachineIn) -> dict[str, Any]:
    try:
        spec, _ = registry.upsert(session=session, machine_in=machine_in)
    except ValidationError as exc:  # the transport's options
        raise HTTPException(422, detail=validation_summary(exc.errors(), under="options")) from None
    except (ValueError, ContractError) as exc:
        raise HTTPException(422, detail=str(exc)) from None
    return spec.public()


@router.get("", summary="List machines")
def list_machines(session: SessionDep, tag: str | None = None) -> list[dict[str, Any]]:
    return [m.public() for m in registry.list_all(session=session, tag=tag)]


@router.post("", status_code=201, summary="Add a machine")
def add_machine(session: SessionDep, machine_in: registry.MachineIn) -> dict[str, Any]:
    if session.get(registry.Machine, machine_in.id) is not None:
        raise HTTPException(409, detail=f"machine {machine_in.id} exists; use PUT to change it")
    return _saved(session, machine_in, new=True)


@router.get("/{machine_id}", summary="Show a machine")
def show_machine(session: SessionDep, machine_id: str) -> dict[str, Any]:
    with resource_errors():
        return registry.get(session=session, machine_id=machine_id).public()


@router.put("/{machine_id}", summary="Add or replace a machine")
def put_machine(session: SessionDep, machine_id: str,
                machine_in: registry.MachineIn) -> dict[str, Any]:
    if machine_in.id != machine_id:
        raise HTTPException(422, detail="id in the body differs from the path")
    return _saved(session, machine_in)


@router.delete("/{machine_id}", status_code=204, summary="Remove a machine")
def delete_machine(session: SessionDep, machine_id: str) -> Response:
    with resource_errors():
        registry.delete(session=session, machine_id=machine_id)
    return Response(status_code=204)


