"""The FastAPI application: routes, auth, body limits and the contract's error shape."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI
from fastapi.routing import APIRoute
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from jobs import VERSION_HEADER, __version__, folders
from jobs.api import audit_trail, docs, errors, key_lockout, openapi
from jobs.api.contract_spelling import ContractSpelling
from jobs.api.deps import require_api_key
from jobs.api.routes import audit as audit_routes
from jobs.api.routes import (
    backups,
    batch,
    cnc,
    gcodefiles,
    health,
    inbox,
    jobs,
    library,
    lockouts,
    machines,
    metrics,
    octoprint_upload,
    requests,
    runs,
    schedules,
    users,
)
from jobs.api.text import TextSafeJSON
from jobs.metrics.collector import registry_for
from jobs.settings import AuthMode, Settings

log = logging.getLogger(__name__)

STREAM_PATHS = frozenset({"/api/cnc/sendFileStream", runs.PROGRAMS_PATH,
                          library.PROGRAMS_PATH, *octoprint_upload.UPLOAD_PATHS})


class Versioned:
    """Every answer names dncq's version in VERSION_HEADER, and no other site's page may
    frame it (a dashboard button clicked through a page laid over it) nor read it as
    another type than it says (ASGI middleware)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self.headers = [(VERSION_HEADER.lower().encode(), __version__.encode()),
                        (b"x-frame-options", b"DENY"),
                        (b"content-security-policy", b"frame-ancestors 'none'"),
                        (b"x-content-type-options", b"nosniff")]

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def versioned(message: Message) -> None:
            if message["type"] == "http.response.start":
                message["headers"] = [*message.get("headers", []), *self.headers]
            await send(message)

        await self.app(scope, receive, versioned)


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    """What the app does as it starts serving: learn which addresses are locked out."""
    key_lockout.remember_locked(app)
    yield


class MissingApiKey(RuntimeError):
    """The API would start without a key while authentication is on."""


def create_app(settings: Settings) -> FastAPI:
    """An app serving dncq's API with `settings`."""
    app = FastAPI(
        title="dncq",
        version=__version__,
        description="File transfer, batch rollout and backup for fleets of CNC machines. "
        "`/api/cnc/...` follows the gateway file-management contract (section 2.6).",
        docs_url=None, redoc_url=None,  # served from the package by docs.install, not a CDN
        default_response_class=TextSafeJSON,
        lifespan=_lifespan,
    )
    app.state.settings = settings
    folders.private_dir(settings.data_dir)
    app.state.api_key = settings.effective_api_key(create=False)
    app.state.locked_addresses = key_lockout.LockedAddresses()
    if settings.auth is AuthMode.NONE:
        log.warning("API authentication is switched off (DNCQ_AUTH=none): "
                    "anyone who reaches this port can change machine programs")
    elif app.state.api_key is None:
        raise MissingApiKey("no API key: set DNCQ_API_KEY, run `dncq serve` once to create one, "
                            "or set DNCQ_AUTH=none on a closed network")
    app.state.metrics = registry_for(settings.resolved_database_url,
                                     check_max_age_s=settings.check_max_age_s)
    # The gateway contract's operations, which answer their own refusals with HTTP 200.
    contract = [route.path for router in (cnc.router, batch.router) for route in router.routes
                if isinstance(route, APIRoute)]
    errors.install(app, contract_paths=contract)
    openapi.install(app)
    errors.hide_keys_in_access_log([app.state.api_key])
    errors.quiet_broken_downloads()
    app.add_middleware(
        errors.BodyLimit,
        json_limit=settings.max_json_body_bytes,
        stream_limit=settings.max_stream_body_bytes,
        stream_paths=STREAM_PATHS,
    )
    # Added last, so outside the body limit: a request refused for its size is recorded too.
    app.add_middleware(audit_trail.AuditTrail, database_url=settings.resolved_database_url,
                       changing_gets=cnc.CHANGING_GETS)
    # Outside the audit trail and the body limit: a refusal of either is dncq's answer too
    # (Starlette's own answer to an unexpected error, outside them all, is not).
    app.add_middleware(Versioned)
    # Outermost: every layer within (the audit trail, the body limit, the routes) sees the
    # path and its query named as the contract writes them.
    app.add_middleware(ContractSpelling, paths=contract)
    for router in (cnc.router, batch.router, jobs.router, backups.router, schedules.router,
                   machines.router, requests.router, runs.router, library.router, inbox.router,
                   gcodefiles.router, octoprint_upload.router, users.users_router,
                   users.keys_router, lockouts.router, audit_routes.router, metrics.router):
        # Every route also declares its role (jobs.api.deps.requires); this is the floor.
        app.include_router(router, dependencies=[Depends(require_api_key)])
    app.include_router(health.router)
    docs.install(app)  # liveness without a key; it checks the key itself
    return app
