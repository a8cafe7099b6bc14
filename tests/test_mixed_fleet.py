"""The batch and backup machinery, unchanged, across a fleet of different transports:
mock, FTP, shared folder, another gateway and OctoPrint, each a real server on loopback."""

from __future__ import annotations

import io
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from jobs import db
from jobs.api.app import create_app
from jobs.backup import store
from jobs.fleet import registry
from jobs.settings import AuthMode, Settings
from tests.conftest import API_KEY
from tests.jobs.helpers import run_backup
from tests.live_server import LiveServer, serving
from tests.worker.transports.ftp_server import ftp_server_of
from tests.worker.transports.octoprint_server import empty_octoprint

PROGRAM = "G21 G90\nG0 X0 Y0\nM30\n"


@pytest.fixture
def remote_gateway(tmp_path: Path) -> Iterator[LiveServer]:
    """A second dncq on loopback with one mock machine, reached through its seed API."""
    remote = Settings(data_dir=tmp_path / "remote", api_key="remote-key", auth=AuthMode.KEY)
    remote.data_dir.mkdir()
    db.upgrade(remote.resolved_database_url)
    with db.session_scope(remote.resolved_database_url) as session:
        registry.upsert(session=session, data_dir=remote.data_dir,
                        machine_in=registry.MachineIn(
            id="far1", name="Far", model="Mock"))
    with serving(create_app(remote)) as live:
        yield live


@pytest.fixture
def ftp_server(tmp_path: Path) -> Iterator[Any]:
    """A real pyftpdlib server on loopback."""
    folder = tmp_path / "ftp"
    folder.mkdir()
    with ftp_server_of("plain", folder) as server:
        yield server


@pytest.fixture
def mixed_fleet(add_machines: Any, tmp_path: Path, remote_gateway: LiveServer,
                ftp_server: Any, octoprint_server: Any
                ) -> Iterator[list[str]]:
    """Machine ids of a fleet reached by every transport that can run here."""
    share = tmp_path / "share"
    share.mkdir()
    add_machines(
        {"id": "octo1", "name": "Printer", "model": "OctoPrint", "transport": "octoprint",
         "options": {"url": octoprint_server.url, "api_key": octoprint_server.api_key}},
        {"id": "ftp1", "name": "Ftp", "model": "FTP server", "transport": "ftp",
         "options": ftp_server.options},
        {"id": "mock1", "name": "Mocked", "model": "Mock"},
        {"id": "fanuc1", "name": "Lathe", "model": "Fanuc 0i-F"},
        {"id": "share1", "name": "Shared", "model": "Shared folder", "transport": "share",
         "options": {"path": str(share)}},
        {"id": "gw1", "name": "Remote", "model": "Gateway file server", "transport": "gateway",
         "options": {"url": remote_gateway.url, "machine_id": "far1", "api_key": "remote-key"}},
    )
    yield ["mock1", "fanuc1", "share1", "gw1", "ftp1", "octo1"]
    empty_octoprint(octoprint_server)  # the server lives for the whole session


def attempts_of(client: TestClient, job_id: str) -> list[tuple[str, int, str | None]]:
    """Each target's machine, attempts and what its last one said: why a target failed."""
    job = client.get(f"/api/jobs/{job_id}", params={"limit": 100}).json()
    return [(t["machineID"], t["attempts"], t["statusMsg"]) for t in job["targets"]]


def test_batch_send_and_backup_work_across_every_transport(queue_client, mixed_fleet):
    content = "%\nO4711\n" + PROGRAM
    targets = [{"machineID": m, "fileName": "PART.NC"} for m in mixed_fleet]
    response = queue_client.post("/api/cnc/batchSendFile",
                                 json={"content": content, "targets": targets})
    assert response.json() == [{"errorCode": 0, "errorMsg": "Success"}] * len(mixed_fleet), \
        attempts_of(queue_client, response.headers["X-Dncq-Job"])
    again = queue_client.post("/api/cnc/batchSendFile",
                              json={"content": content, "targets": targets}).json()
    assert [r["errorCode"] for r in again] == [142] * len(mixed_fleet)  # never overwritten

    response = queue_client.post("/api/cnc/backupFiles",
                                 json=[{"machineID": m} for m in mixed_fleet])
    archive = zipfile.ZipFile(io.BytesIO(response.content))
    top = archive.namelist()[0]
    expected = {"mock1": "mock1_Mocked/PART.NC", "fanuc1": "fanuc1_Lathe/O4711",
                "share1": "share1_Shared/PART.NC", "gw1": "gw1_Remote/PART.NC",
                "ftp1": "ftp1_Ftp/PART.NC", "octo1": "octo1_Printer/PART.NC"}
    for path in expected.values():
        assert archive.read(top + path).decode() == content


def test_secrets_of_transport_options_are_masked_in_the_api(queue_client, mixed_fleet):
    shown = queue_client.get("/api/machines/gw1").json()
    assert shown["options"]["api_key"] == "**********"
    assert "remote-key" not in queue_client.get("/api/machines").text


def test_a_gevent_worker_sends_to_and_backs_up_every_transport(
        queue_settings, start_worker, mixed_fleet):
    # Every transport's waiting (sockets, SSL, the database, Redis) must cooperate with the
    # gevent worker's event loop, and backups must still deflate on its native threads.
    start_worker("green", queue_settings, pool="gevent").wait_ready()
    content = "%\nO4712\n" + PROGRAM
    with TestClient(create_app(queue_settings), headers={"X-Api-Key": API_KEY}) as client:
        sent = client.post("/api/cnc/batchSendFile", json={
            "content": content,
            "targets": [{"machineID": m, "fileName": "GREEN.NC"} for m in mixed_fleet]}).json()
        backup = run_backup(client, machines={"ids": mixed_fleet})
        verified = client.post(f"/api/backups/{backup['id']}/verify").json()

    assert sent == [{"errorCode": 0, "errorMsg": "Success"}] * len(mixed_fleet)
    assert backup["status"] == "complete", backup["machines"]
    assert verified["ok"], verified["problems"]
    with zipfile.ZipFile(store.backup_dir(queue_settings) / backup["name"]) as archive:
        top = archive.namelist()[0]
        for path in ("mock1_Mocked/GREEN.NC", "fanuc1_Lathe/O4712", "share1_Shared/GREEN.NC",
                     "gw1_Remote/GREEN.NC", "ftp1_Ftp/GREEN.NC", "octo1_Printer/GREEN.NC"):
            assert archive.read(top + path).decode() == content
