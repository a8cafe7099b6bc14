"""Client addresses locked out for wrong API keys (admin): `/api/lockouts` lists them and
the addresses whose wrong keys count, `DELETE /api/lockouts/{address}` ends one's lock-out."""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

from fastapi import APIRouter, Request

from jobs.api import key_lockout
from jobs.api.deps import SessionDep, SettingsDep, note_target, requires
from jobs.api.errors import resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth import wrong_keys
from jobs.auth.models import WrongKeyCount
from jobs.auth.roles import Role
from jobs.models import utcnow
from jobs.settings import Settings

router = APIRouter(prefix="/api/lockouts", tags=["lockouts"], route_class=CheckedRoute)


def _when(value: datetime | None) -> str | None:
    return value.isoformat() if value is not None else None


def lockout_view(row: WrongKeyCount, settings: Settings) -> dict[str, Any]:
    """An address's count as the API shows it: the wrong keys of the current window, and
    until when it is locked out (null: it is not)."""
    now = utcnow()
    in_window = row.failed_since is not None and \
        now - row.failed_since <= timedelta(seconds=settings.signin_window_s)
    locked = row.locked_until is not None and row.locked_until > now
    return {"address": row.address, "failures": row.failures if in_window else 0,
            "failedSince": _when(row.failed_since) if in_window else None,
            "lockedUntil": _when(row.locked_until) if locked else None}


@router.get("", summary="Addresses locked out for wrong API keys, and those with wrong keys "
                        "counted", dependencies=[requires(Role.ADMIN)])
def list_lockouts(session: SessionDep, settings: SettingsDep) -> list[dict[str, Any]]:
    return [lockout_view(r, settings)
            for r in wrong_keys.counted_now(session=session, settings=settings)]


# A path: an IPv6 address's row is its /64 (`2001:db8:7:1::/64`).
@router.delete("/{address:path}",
               summary="End an address's lock-out for wrong API keys and forget its wrong keys",
               dependencies=[requires(Role.ADMIN, action="lockouts.end")])
def end_lockout(request: Request, session: SessionDep, settings: SettingsDep,
                address: str) -> dict[str, Any]:
    note_target(request, address)
    with resource_errors():
        ended = key_lockout.end_lockout(request, session=session, address=address)
    shown = lockout_view(ended, settings)
    note_target(request, ended.address, failures=shown["failures"],
                until=shown["lockedUntil"])
    return {**shown, "ended": True}
