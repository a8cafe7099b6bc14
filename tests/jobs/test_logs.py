"""DNCQ_LOG_FORMAT=json: one JSON object per log line, in the API process and the workers'
Celery logging, with the API key masked as in text."""

from __future__ import annotations

import io
import json
import logging
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from celery.signals import after_setup_logger, after_setup_task_logger

from jobs import logs
from jobs.api import errors
from jobs.settings import get_settings
from tests.conftest import API_KEY
from tests.live_server import HTTP_TIMEOUT_S
from tests.servers import free_port, stop_process, wait_for_http


@pytest.fixture
def root_logger() -> Iterator[logging.Logger]:
    """The root logger, its handlers and level put back afterwards."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield root
    root.handlers[:] = handlers
    root.setLevel(level)


def json_lines(text: str) -> list[dict[str, Any]]:
    """The JSON objects of a log, one a line (other lines, such as the CLI's own, left out)."""
    return [json.loads(line) for line in text.splitlines() if line.startswith("{")]


def test_a_record_is_one_json_object_with_time_level_logger_message_and_extra_fields():
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logs.JsonLines())
    log = logging.getLogger("dncq.test.json")
    log.addHandler(handler)
    log.propagate = False
    log.setLevel(logging.INFO)
    try:
        log.warning("target %s of job %s failed", 7, "j1",
                    extra={"job_id": "j1", "machine_id": "m1"})
    finally:
        log.removeHandler(handler)
    [line] = stream.getvalue().splitlines()
    record = json.loads(line)
    assert record["level"] == "WARNING" and record["logger"] == "dncq.test.json"
    assert record["message"] == "target 7 of job j1 failed"
    assert (record["job_id"], record["machine_id"]) == ("j1", "m1")
    assert record["time"].endswith("+00:00")
    assert "args" not in record and "msg" not in record


def test_a_traceback_stays_inside_its_one_json_line(root_logger, capsys):
    logs.configure("json")
    try:
        raise ValueError("boom")
    except ValueError:
        logging.getLogger("dncq.test").exception("it failed")
    [record] = json_lines(capsys.readouterr().err)
    assert record["message"] == "it failed"
    assert "ValueError: boom" in record["exc_info"]


def test_the_api_key_in_an_access_log_line_is_masked_in_json():
    errors.hide_keys_in_access_log([API_KEY])
    access = logging.getLogger("uvicorn.access")
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logs.JsonLines())
    access.addHandler(handler)
    level, disabled = access.level, access.disabled
    access.setLevel(logging.INFO)
    access.disabled = False  # as uvicorn leaves it; an earlier logging setup may not
    try:  # as uvicorn logs a request: the path with its query is an argument
        access.info('%s - "%s %s HTTP/%s" %d', "127.0.0.1:5000", "GET",
                    f"/metrics?apikey={API_KEY}", "1.1", 200)
    finally:
        access.removeHandler(handler)
        access.setLevel(level)
        access.disabled = disabled
    [record] = json_lines(stream.getvalue())
    assert "/metrics?apikey=***" in record["message"]
    assert API_KEY not in stream.getvalue()


def test_a_one_letter_key_is_masked_as_a_value_and_leaves_the_rest_of_the_line_alone():
    errors.hide_keys_in_access_log(["k"])
    [hiding] = [f for f in logging.getLogger("uvicorn.access").filters
                if isinstance(f, errors._HideApiKey)]
    assert hiding.masked("/api/jobs?apikey=k&x=k") == "/api/jobs?apikey=***&x=***"
    assert hiding.masked("/api/keys/kept") == "/api/keys/kept"


def test_a_named_key_is_masked_wherever_it_stands_in_the_line():
    from jobs.auth.passwords import new_key

    errors.hide_keys_in_access_log([API_KEY])  # the admin key: a named key is not among them
    [hiding] = [f for f in logging.getLogger("uvicorn.access").filters
                if isinstance(f, errors._HideApiKey)]
    key = new_key()

    for given in (f"/api/cnc/readProgramList?machineID=1010&api_key={key}",
                  f"/api/cnc/readProgramList?machineID=1010;apikey={key}",
                  f"/api/files/local?apikey%00={key}@1010", f"/x/{key}"):
        assert key not in hiding.masked(given) and "***" in hiding.masked(given), given
    assert hiding.masked("/api/jobs?machine=dncq_demo") == "/api/jobs?machine=dncq_demo"


def test_celery_logging_of_workers_and_beat_is_turned_into_json(monkeypatch):
    monkeypatch.setenv("DNCQ_LOG_FORMAT", "json")
    get_settings.cache_clear()
    import worker.app  # noqa: F401 - connects the receivers

    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logging.Formatter("%(message)s"))  # as Celery made it
    log = logging.getLogger("dncq.test.celery")
    log.addHandler(handler)
    log.propagate = False
    log.setLevel(logging.INFO)
    try:
        for signal in (after_setup_logger, after_setup_task_logger):
            signal.send(sender=None, logger=log, loglevel=logging.INFO, logfile=None,
                        format="", colorize=False)
        log.info("task received", extra={"job_id": "j2"})
    finally:
        log.removeHandler(handler)
        get_settings.cache_clear()
    [record] = json_lines(stream.getvalue())
    assert (record["message"], record["job_id"]) == ("task received", "j2")


def test_dncq_api_with_json_logs_writes_uvicorns_lines_as_json_with_the_key_masked(
        tmp_path: Path):
    port = free_port()
    env = {**os.environ, "DNCQ_DATA_DIR": str(tmp_path), "DNCQ_API_KEY": API_KEY,
           "DNCQ_PORT": str(port), "DNCQ_HOST": "127.0.0.1", "DNCQ_LOG_FORMAT": "json"}
    env.pop("DNCQ_AUTH", None)
    log_path = tmp_path / "api.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "jobs.cli", "api"], env=env,
                                stdout=subprocess.DEVNULL, stderr=log)
    try:
        base = f"http://127.0.0.1:{port}"
        wait_for_http(lambda: httpx.get(f"{base}/api/health"), timeout_s=30)
        assert httpx.get(f"{base}/metrics?apikey={API_KEY}",
                         timeout=HTTP_TIMEOUT_S).status_code == 200
    finally:
        stop_process(proc)
    logged = log_path.read_text()
    records = json_lines(logged)
    loggers = {r["logger"] for r in records}
    assert {"uvicorn.error", "uvicorn.access"} <= loggers
    [scrape] = [r for r in records if "/metrics" in r["message"]]
    assert "apikey=***" in scrape["message"] and scrape["level"] == "INFO"
    assert API_KEY not in logged
    # What the command says as it starts is a record too, and uvicorn's text format is gone.
    assert any(r["message"].startswith("dncq listening on") for r in records)
    assert any(r["message"].startswith("Database: ") for r in records)
    assert not [line for line in logged.splitlines() if line.startswith(("INFO:", "Database:"))]
