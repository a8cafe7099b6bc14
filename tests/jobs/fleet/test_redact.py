"""A far side that echoes the password: masked in every message that leaves its transport."""

from __future__ import annotations

import logging
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from jobs import db
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import door, registry
from jobs.fleet.redact import MASK, Redactor
from tests.jobs.helpers import run_backup, wait_done
from tests.worker.transports.ftp_server import PASSWORD, FtpServer, ftp_server_of
from worker.transports.base import PermissionDenied


def _echo_password(handler: Any, line: str) -> None:
    # What some servers do: refuse the login and quote what they were sent.
    handler.respond(f"530 Login incorrect for {line}.")


def _echo_password_capitalized(handler: Any, line: str) -> None:
    # As pyftpdlib writes an authorizer's refusal: capitalized, the password in lower case.
    handler.respond("530 " + f"login incorrect for {line}.".capitalize())


@pytest.fixture
def echoing_server(tmp_path: Path) -> Iterator[FtpServer]:
    """A real FTP server whose refusal of a login quotes the password it was sent."""
    with ftp_server_of("plain", tmp_path / "ftp", ftp_PASS=_echo_password) as server:
        yield server


@pytest.fixture
def echoing_machine(echoing_server: FtpServer, add_machines: Any) -> str:
    add_machines({"id": "f1", "name": "Lathe", "model": "Fanuc 0i-F", "transport": "ftp",
                  "options": {**echoing_server.options, "timeout_s": 5.0}})
    return "f1"


def test_the_server_really_echoes_the_password(echoing_server: FtpServer) -> None:
    transport = echoing_server.transport()
    with pytest.raises(PermissionDenied) as raised:
        transport.list_dir("")
    transport.close()
    assert PASSWORD in str(raised.value)  # unmasked below the registry: what is masked above


def test_an_echoed_password_is_masked_in_status_msg(client, echoing_machine) -> None:
    body = client.get("/api/cnc/readProgramList", params={"machineID": echoing_machine}).json()

    assert body["errorCode"] == int(ErrorCode.PERMISSION_DENIED)
    assert PASSWORD not in body["statusMsg"]
    assert f"Login incorrect for {MASK}" in body["statusMsg"]


def test_a_password_echoed_in_another_case_is_masked_in_status_msg(
        client, add_machines, tmp_path) -> None:
    with ftp_server_of("plain", tmp_path / "ftp", ftp_PASS=_echo_password_capitalized) as server:
        add_machines({"id": "f2", "name": "Mill", "model": "Fanuc 0i-F", "transport": "ftp",
                      "options": {**server.options, "timeout_s": 5.0}})
        body = client.get("/api/cnc/readProgramList", params={"machineID": "f2"}).json()

    assert body["errorCode"] == int(ErrorCode.PERMISSION_DENIED)
    assert f"Login incorrect for {MASK}" in body["statusMsg"]
    assert PASSWORD.lower() not in body["statusMsg"].lower()


def test_an_echoed_password_is_masked_in_the_error_chain_a_log_prints(
        settings, echoing_machine, caplog) -> None:
    with db.session_scope(settings.resolved_database_url) as session:
        spec = registry.get(session=session, machine_id=echoing_machine)
    caplog.set_level(logging.DEBUG)
    with pytest.raises(ContractError) as raised:
        with door.open_files(spec, data_dir=settings.data_dir) as files:
            files.list_program_dir(None, None)
    logging.getLogger("test").error("failed", exc_info=raised.value)

    printed = "".join(traceback.format_exception(raised.value))
    assert "Login incorrect" in printed and PASSWORD not in printed
    assert PASSWORD not in caplog.text


def test_an_echoed_password_is_masked_in_the_job_record(
        queue_client, echoing_machine, queue_settings) -> None:
    response = queue_client.post("/api/cnc/batchSendFile", json={
        "content": "G0 X0\nM30\n", "targets": [{"machineID": echoing_machine,
                                                 "fileName": "P1.nc"}]})
    job = wait_done(queue_client, response.headers["X-Dncq-Job"])

    assert job["targets"][0]["errorCode"] == int(ErrorCode.PERMISSION_DENIED)
    assert MASK in job["targets"][0]["statusMsg"]
    assert PASSWORD not in queue_client.get(f"/api/jobs/{job['id']}").text


def test_an_echoed_password_is_masked_in_a_streamed_backup_error(client, echoing_machine) -> None:
    response = client.post("/api/cnc/backupFiles", json=[{"machineID": echoing_machine}])

    assert response.json()["errorCode"] == int(ErrorCode.PERMISSION_DENIED)
    assert MASK in response.json()["statusMsg"] and PASSWORD not in response.text


def test_an_echoed_password_is_masked_in_a_stored_backup_error(
        queue_client, echoing_machine) -> None:
    backup = run_backup(queue_client, machines={"ids": [echoing_machine]}, max_attempts=1)

    assert backup["machines"][0]["status"] == "failed"
    assert PASSWORD not in queue_client.get("/api/backups").text
    assert PASSWORD not in queue_client.get(f"/api/jobs/{backup['job']}").text


SPECIAL = "p@ss w\\rd"  # characters a URL and a repr() quote


@pytest.mark.parametrize("shown", [SPECIAL, "p%40ss%20w%5Crd", "p%40ss+w%5Crd", "p@ss w\\\\rd",
                                   "P@SS W\\RD", "P%40sS%20W%5crD"])
def test_a_secret_is_masked_as_written_and_as_a_url_or_repr_quotes_it_in_any_case(
        shown: str) -> None:
    assert Redactor([SPECIAL]).text(f"refused {shown}!") == f"refused {MASK}!"
