"""Client addresses locked out for wrong API keys or failed sign-ins as admin (admin):
`/api/lockouts` lists them and the addresses whose failures count, `DELETE
/api/lockouts/{address}` ends an address's lock-outs (jobs.auth.lockouts)."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from fastapi import APIRouter, Request

from jobs.api import key_lockout
from jobs.api.deps import SessionDep, SettingsDep, note_target, requires
from jobs.api.errors import resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth import lockouts
from jobs.auth.lockouts import Lockout
from jobs.auth.roles import Role

router = APIRouter(prefix="/api/lockouts", tags=["lockouts"], route_class=CheckedRoute)


def _when(value: datetime | None) -> str | None:
    return value.isoformat() if value is not None else None


def lockout_view(lockout: Lockout) -> dict[str, Any]:
    """An address's count as the API shows it: of what (`api keys`, `admin sign-ins`), the
    failures of the current window, and until when it is locked out (null: it is not)."""
    return {"address": lockout.address, "counted": lockout.counted,
            "failures": lockout.failures, "failedSince": _when(lockout.failed_since),
            "lockedUntil": _when(lockout.locked_until)}


@router.get("", summary="Addresses locked out for wrong API keys or failed sign-ins as admin, "
                        "and those with failures counted", dependencies=[requires(Role.ADMIN)])
def list_lockouts(session: SessionDep, settings: SettingsDep) -> list[dict[str, Any]]:
    return [lockout_view(c) for c in lockouts.counted_now(session=session, settings=settings)]


# A path: an IPv6 address's row is its /64 (`2001:db8:7:1::/64`).
@router.delete("/{address:path}",
               summary="End an address's lock-outs (API keys, sign-ins as admin) and forget "
                       "its failures", dependencies=[requires(Role.ADMIN, action="lockouts.end")])
def end_lockout(request: Request, session: SessionDep, address: str) -> dict[str, Any]:
    note_target(request, address)
    with resource_errors():
        ended = key_lockout.end_lockout(request, session=session, address=address)
    note_target(request, ended[0].address, **lockouts.ended_detail(ended))
    return {"address": ended[0].address, "ended": [lockout_view(c) for c in ended]}
