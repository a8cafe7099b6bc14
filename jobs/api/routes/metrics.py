"""`/metrics`: the fleet's figures and the API process's own, in Prometheus's text format."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from prometheus_client.exposition import choose_encoder

from jobs.api.deps import requires
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Role

router = APIRouter(tags=["metrics"], route_class=CheckedRoute)

PATH = "/metrics"
_EXPOSITION = {"schema": {"type": "string"}}


@router.get(
    PATH, response_class=Response,
    summary="Metrics in the Prometheus exposition format (OpenMetrics when asked for)",
    responses={200: {"description": "The metrics, names prefixed `dncq_`",
                     "content": {"text/plain": _EXPOSITION,
                                 "application/openmetrics-text": _EXPOSITION}}},
    dependencies=[requires(Role.VIEWER)],
)
def metrics(request: Request) -> Response:
    # A plain def: the figures are read from the database, off the event loop.
    encode, content_type = choose_encoder(request.headers.get("accept", ""))
    return Response(encode(request.app.state.metrics), headers={"Content-Type": content_type})
