"""The audit middleware: every state-changing API request recorded as it is answered.

State-changing: POST, PUT, PATCH and DELETE under `/api/` and `/machines/`, and the
contract's operations that change a machine although they are GETs (deleteFile...). What is
recorded: when, who (the principal the request was recognised as, `-` when it was refused
before), its role, the client's address, the method, the path without its query (a key may
be there), the status, the route's action name and a target (a machine, a job, a user).
Never a body: a password or a program is not the trail's to keep. Not recorded: the requests
refused while their address is locked out for wrong keys, which its `lock out` entry stands
for (`key_lockout`).
"""

from __future__ import annotations

import logging
from typing import Any

import anyio
from starlette.concurrency import run_in_threadpool
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from jobs.api.deps import role_checks
from jobs.auth import audit
from jobs.auth.roles import Principal
from jobs.db import session_scope

log = logging.getLogger(__name__)

CHANGING_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
AUDITED_PREFIXES = ("/api/", "/machines/")
# Where a target is found in the path, in order of preference.
TARGET_PARAMS = ("machine_id", "job_id", "item_id", "backup_id", "name", "path", "run_id",
                 "program_id")
# Query parameters worth keeping (never `apikey`): what a contract operation acted on.
DETAIL_QUERY = ("fileName", "dirAtCNC", "subDir", "dirName", "force", "isLock", "version")


def action_of(route: Any, path: str) -> str:
    """The audit action of a route: the one it declares, else `resource.endpoint`."""
    named = [c.action for c in role_checks(route) if c.action]
    if named:
        return named[0]
    parts = [p for p in path.split("/") if p]
    resource = parts[1] if parts[:1] == ["api"] and len(parts) > 1 else "octoprint"
    return f"{resource}.{getattr(route, 'name', 'unknown')}"


class AuditTrail:
    """ASGI middleware recording each state-changing request after its answer."""

    def __init__(self, app: ASGIApp, *, database_url: str,
                 changing_gets: frozenset[str] = frozenset()) -> None:
        self.app = app
        self.database_url = database_url
        self.changing_gets = changing_gets

    def audited(self, scope: Scope) -> bool:
        """Whether the request changes state and is the API's."""
        path: str = scope.get("path", "")
        method: str = scope.get("method", "")
        if method == "GET":
            return path in self.changing_gets
        return method in CHANGING_METHODS and path.startswith(AUDITED_PREFIXES)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not self.audited(scope):
            await self.app(scope, receive, send)
            return
        recorded = False

        async def record(status: int) -> None:
            nonlocal recorded
            recorded = True
            with anyio.CancelScope(shield=True):  # a client gone meanwhile is recorded too
                try:
                    await run_in_threadpool(self._record, scope, status)
                except Exception:  # the request is answered anyway; the failure is logged
                    log.exception("could not record %s %s in the audit trail",
                                  scope.get("method"), scope.get("path"))

        async def sending(message: Message) -> None:
            # Recorded before the answer leaves: a client that has it finds it in the trail.
            if message["type"] == "http.response.start" and not recorded:
                await record(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, sending)
        finally:
            if not recorded:  # failed before any answer: the server's 500
                await record(500)

    def _record(self, scope: Scope, status: int) -> None:
        state: dict[str, Any] = scope.get("state") or {}
        if state.get("audit_skip"):  # a key from a locked address: its lock-out is recorded
            return
        principal = state.get("principal")
        path: str = scope.get("path", "")
        params: dict[str, Any] = scope.get("path_params") or {}
        query = _query(scope)
        target = state.get("audit_target") or next(
            (str(params[p]) for p in TARGET_PARAMS if params.get(p)), None) \
            or query.get("machineID")
        detail = dict(state.get("audit_detail") or {})
        if query.get("machineID") and target != query["machineID"]:
            detail["machineID"] = query["machineID"]
        detail.update({k: query[k] for k in DETAIL_QUERY if k in query})
        client = scope.get("client")
        with session_scope(self.database_url) as session:
            audit.record(session=session,
                         principal=principal if isinstance(principal, Principal) else None,
                         address=client[0] if client else None, method=scope["method"],
                         path=path, status=status, action=action_of(scope.get("route"), path),
                         target=target, detail=detail or None)


def _query(scope: Scope) -> dict[str, str]:
    from urllib.parse import parse_qsl

    raw = scope.get("query_string", b"").decode("latin-1")
    return {k: v for k, v in parse_qsl(raw, keep_blank_values=True) if k in
            ("machineID", *DETAIL_QUERY)}
