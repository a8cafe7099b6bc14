"""What a machine's operator may ask from the control: `/api/machines/{id}/requests`.

The settings shown are the effective ones (the controller's preset with the machine's own
over it); those given are what the fleet file or a PUT stored. `.../requests/test` shows
what a received text would trigger, without doing any of it.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from jobs.api.deps import SessionDep, requires
from jobs.api.errors import resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Role
from jobs.errors import validation_summary
from jobs.fleet import registry, request_settings
from jobs.requests.explain import explain

router = APIRouter(prefix="/api/machines", tags=["requests"], route_class=CheckedRoute)

MAX_TEST_CHARS = 1024 * 1024  # a test text is held whole; larger ones are refused before


def _view(spec: registry.MachineSpec) -> dict[str, Any]:
    effective = spec.request_settings()
    return {"machineID": spec.id, "given": spec.requests,
            "settings": effective.model_dump(mode="json")}


@router.get("/{machine_id}/requests", summary="Show what the machine's operator may ask",
            dependencies=[requires(Role.VIEWER)])
def show_requests(session: SessionDep, machine_id: str) -> dict[str, Any]:
    with resource_errors():
        spec = registry.get(session=session, machine_id=machine_id)
    return _view(spec)


@router.put("/{machine_id}/requests",
            summary="Set what the machine's operator may ask (over its controller's preset)",
            dependencies=[requires(Role.ADMIN, action="requests.put")])
def set_requests(session: SessionDep, machine_id: str,
                 given: dict[str, Any]) -> dict[str, Any]:
    with resource_errors():
        spec = registry.get(session=session, machine_id=machine_id)
    try:
        request_settings.resolve(spec.model, given)
    except ValidationError as exc:
        raise HTTPException(422, detail=validation_summary(exc.errors(),
                                                           under="requests")) from None
    except ValueError as exc:
        raise HTTPException(422, detail=f"requests: {exc}") from None
    with resource_errors():
        updated = registry.set_requests(session=session, machine_id=machine_id,
                                        requests=given)
    return _view(updated)


class TestIn(BaseModel):
    """A received text to try the machine's settings on."""

    model_config = ConfigDict(extra="forbid")

    text: str = Field(max_length=MAX_TEST_CHARS)
    """The program as the control would send it (ISO text)."""


@router.post("/{machine_id}/requests/test",
             summary="Show what a received text would trigger on the machine (nothing is done)",
             dependencies=[requires(Role.VIEWER, action="requests.test")])
def test_requests(session: SessionDep, machine_id: str, body: TestIn) -> dict[str, Any]:
    with resource_errors():
        spec = registry.get(session=session, machine_id=machine_id)
    data = body.text.encode("latin-1", "replace")
    effective = spec.request_settings()
    # Off: dncq does not listen to the machine, and what it sends triggers none of the rows.
    return {"machineID": spec.id, "enabled": effective.enabled,
            "rows": explain(data, effective)}
