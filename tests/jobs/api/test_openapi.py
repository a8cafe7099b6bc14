"""/openapi.json says what dncq answers: checked operation by operation by schemathesis,
which sends requests generated from the document itself (valid and invalid) to the app on a
real database and mock machines, and fails on a server error or an answer the document does
not describe."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    ignored_auth,
    response_schema_conformance,
    status_code_conformance,
)

from jobs import db
from jobs.api.app import create_app
from jobs.fleet import fleet_file
from jobs.settings import AuthMode, Settings
from tests.conftest import API_KEY


def fuzzed_app(folder: Path) -> Any:
    """The API on SQLite and the embedded queue with two mock machines; batch calls
    answer at once instead of waiting for a worker."""
    # The fuzzer sends wrong keys on purpose, to see them refused: counted, its address
    # would be locked out after five, and every operation answered 429 from then on.
    s = Settings(data_dir=folder, api_key=API_KEY, auth=AuthMode.KEY, batch_wait_s=0.05,
                 busy_wait_s=0.05, signin_max_failures=1_000_000)
    db.upgrade(s.resolved_database_url)
    with db.session_scope(s.resolved_database_url) as session:
        fleet_file.import_fleet(session=session, machines=fleet_file.parse_fleet(
            "machines:\n"
            "  - {id: '1010', name: Lathe, model: Fanuc 0i-F, transport: mock}\n"
            "  - {id: '1016', name: Sim, model: Mock, transport: mock}\n"), data_dir=folder)
    return create_app(s)


# What the document must hold to. Not the checks that a bad request gets a 4xx: the contract
# answers a request it cannot do with HTTP 200 and its error body, by design.
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance,
          response_schema_conformance, ignored_auth]

# Made when the module is collected (the schema is read then), so no fixture can own it:
# removed when the session ends (conftest.py).
FOLDER = Path(tempfile.mkdtemp(prefix="dncq-openapi-"))
APP = fuzzed_app(FOLDER)
schema = schemathesis.openapi.from_asgi("/openapi.json", APP)


@schema.parametrize()
@settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck))
def test_every_operation_answers_as_its_openapi_document_says(case):
    case.call_and_validate(headers={"X-Api-Key": API_KEY}, checks=CHECKS)


def test_422_comes_with_the_contract_body_and_never_from_the_contracts_own_operations():
    with TestClient(APP) as client:
        document = client.get("/openapi.json").json()

    promised = {(path, method): op["responses"]["422"]["content"]["application/json"]
                for path, ops in document["paths"].items()
                for method, op in ops.items() if "422" in op["responses"]}
    assert promised and not [p for p, _ in promised if p.startswith("/api/cnc/")]
    assert all(c["schema"] == {"$ref": "#/components/schemas/ContractError"}
               for c in promised.values())
    assert "HTTPValidationError" not in document["components"]["schemas"]


def test_a_streamed_file_answer_also_documents_the_contracts_json_error():
    with TestClient(APP) as client:
        document = client.get("/openapi.json").json()

    for path in ("/api/cnc/receiveFileStream", "/api/cnc/backupFiles"):
        [operation] = document["paths"][path].values()
        json_answer = operation["responses"]["200"]["content"]["application/json"]
        assert json_answer["schema"] == {"$ref": "#/components/schemas/ContractError"}


@pytest.mark.parametrize("status", ["400", "401", "403", "429"])
def test_every_operation_documents_the_contract_body_for_its_errors(status):
    with TestClient(APP) as client:
        document = client.get("/openapi.json").json()

    for ops in document["paths"].values():
        for op in ops.values():
            assert op["responses"][status]["content"]["application/json"]["schema"] == {
                "$ref": "#/components/schemas/ContractError"}


def test_a_body_over_the_limit_is_documented_with_the_code_it_answers():
    with TestClient(APP) as client:
        document = client.get("/openapi.json").json()
        limit = Settings.model_fields["max_json_body_bytes"].default
        answered = client.post("/api/cnc/sendFile", params={"machineID": "1016", "fileName": "P"},
                               content=b"{" + b" " * limit + b"}",
                               headers={"Content-Type": "application/json", "X-Api-Key": API_KEY})

    code = answered.json()["errorCode"]
    assert (answered.status_code, code) == (413, 20013)
    [operation] = document["paths"]["/api/cnc/sendFile"].values()
    assert f"({code})" in operation["responses"]["413"]["description"]
