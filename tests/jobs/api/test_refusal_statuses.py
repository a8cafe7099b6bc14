"""No route of dncq's own answers a refusal with HTTP 200, which a client takes for done:
the gateway contract's operations alone answer theirs 200, as the contract says."""

from __future__ import annotations

import re
from collections.abc import Iterator

import pytest
from fastapi import FastAPI
from fastapi.routing import APIRoute, iter_route_contexts
from fastapi.testclient import TestClient

from jobs.api.app import create_app
from jobs.api.deps import get_principal, optional_principal
from jobs.api.routes import batch, cnc
from jobs.errors import ContractError, ErrorCode
from jobs.settings import Settings
from tests.conftest import API_KEY

CONTRACT = {route.path for router in (cnc.router, batch.router) for route in router.routes}


def _refused() -> None:
    """A refusal no route wrapped in its own status, as a service raises it."""
    raise ContractError(ErrorCode.BAD_PARAMETER, "refused as the service refuses it")


@pytest.fixture
def refusing_app(settings: Settings) -> Iterator[FastAPI]:
    """The API, every operation of which meets a raw refusal as it asks who is asking."""
    app = create_app(settings)
    app.dependency_overrides = {get_principal: _refused, optional_principal: _refused}
    yield app


def _operations(app: FastAPI) -> list[tuple[str, str]]:
    """Every operation of the API as (method, path), its path parameters filled in."""
    return [(method, re.sub(r"\{[^}]+\}", "1", route.path_format))
            for route in iter_route_contexts(app.routes)  # the included routers' too
            if isinstance(route.original_route, APIRoute)
            and route.original_route.include_in_schema
            for method in sorted(route.methods or ())]


def test_every_own_operation_refuses_with_a_4xx_and_every_contract_one_with_200(
        refusing_app: FastAPI) -> None:
    answered: dict[tuple[str, str], tuple[int, int]] = {}
    with TestClient(refusing_app, headers={"X-Api-Key": API_KEY}) as client:
        for method, path in _operations(refusing_app):
            response = client.request(method, path)
            answered[method, path] = (response.status_code, response.json()["errorCode"])

    own = {op: said for op, said in answered.items() if op[1] not in CONTRACT}
    contract = {op: said for op, said in answered.items() if op[1] in CONTRACT}
    assert len(own) > 50 and len(contract) > 10  # every router was walked
    assert {op: said for op, said in own.items() if not 400 <= said[0] < 500} == {}
    assert set(own.values()) == {(400, 20001)}  # a bad parameter's status, the code kept
    assert set(contract.values()) == {(200, 20001)}
