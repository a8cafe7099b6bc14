"""The CLI run in any folder: it talks to the running dncq at DNCQ_URL, fails naming that URL
when nothing answers there, and the commands that open a database say which one."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, PlainTextResponse
from starlette.routing import Route

from jobs import db
from jobs.fleet import registry
from jobs.settings import get_settings
from tests.conftest import API_KEY
from tests.jobs.cli.runner import dncq
from tests.live_server import serving
from tests.servers import free_port

# Every command about a running dncq that needs no worker, as a user in another folder types it.
READING = [
    ["machines", "list"],
    ["machines", "show", "1016"],
    ["machines", "check", "1016"],
    ["ls", "1016"],
    ["ls", "1016", "-r"],
    ["find", "1016", "sample2.nc"],
    ["get", "1016", "SAMPLE", "-o", "-"],
    ["jobs"],
    ["backup", "list"],
    ["schedule", "list"],
]
# And those that change something or start a job.
CHANGING = [
    ["machines", "import", "fleet.yaml"],
    ["machines", "rm", "1016"],
    ["put", "1016", "P.nc"],
    ["rm", "1016", "SAMPLE"],
    ["send", "P.nc", "--to", "1016"],
    ["delete", "SAMPLE", "--to", "1016"],
    ["job", "0123456789abcdef"],
    ["retry", "0123456789abcdef"],
    ["cancel", "0123456789abcdef"],
    ["backup", "run", "--to", "1016"],
    ["backup", "restore", "0123456789abcdef", "--machine", "1016"],
    ["schedule", "run-now", "nightly"],
]
FLEET = "machines:\n  - {id: new1, name: New, model: Mock}\n"


@pytest.fixture
def nowhere(monkeypatch, tmp_path) -> Iterator[str]:
    """The CLI in an empty folder, pointed at a loopback port where nothing listens."""
    url = f"http://127.0.0.1:{free_port()}"
    for name in ("DNCQ_DATA_DIR", "DNCQ_DATABASE_URL", "DNCQ_AUTH", "DNCQ_CONFIG_FILE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("DNCQ_API_KEY", API_KEY)
    monkeypatch.setenv("DNCQ_URL", url)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "P.nc").write_text("G0 X1\n")
    (tmp_path / "fleet.yaml").write_text(FLEET)
    get_settings.cache_clear()
    yield url
    get_settings.cache_clear()


PAGE = "<!DOCTYPE html>\n<html><head><title>Welcome</title></head>\n<body>\n</body></html>\n"


@pytest.fixture(params=[200, 404], ids=["200", "404"])
def another_server(request, nowhere, monkeypatch) -> Iterator[str]:
    """The CLI pointed at a web server that answers every path with an HTML page."""
    async def page(_request: Request) -> HTMLResponse:
        return HTMLResponse(PAGE, status_code=request.param)

    app = Starlette(routes=[Route("/{path:path}", page, methods=["GET", "POST", "DELETE"])])
    with serving(app) as server:
        monkeypatch.setenv("DNCQ_URL", server.url)
        get_settings.cache_clear()
        yield server.url


@pytest.fixture
def a_proxy_without_dncq(nowhere, monkeypatch) -> Iterator[str]:
    """The CLI pointed at a proxy whose dncq is down: every path a plain-text 502."""
    async def bad_gateway(_request: Request) -> PlainTextResponse:
        return PlainTextResponse("Bad Gateway", status_code=502)

    app = Starlette(routes=[Route("/{path:path}", bad_gateway,
                                  methods=["GET", "POST", "DELETE"])])
    with serving(app) as server:
        monkeypatch.setenv("DNCQ_URL", server.url)
        get_settings.cache_clear()
        yield server.url


@pytest.fixture(params=[(200, {"hello": "world"}), (200, ["a", "b"]),
                        (404, {"detail": "Not Found"})], ids=["object", "list", "error"])
def another_api(request, nowhere, monkeypatch) -> Iterator[str]:
    """The CLI pointed at another server's API: every path a JSON answer not of dncq's shape
    (or another FastAPI's refusal)."""
    status, body = request.param

    async def answer(_request: Request) -> JSONResponse:
        return JSONResponse(body, status_code=status)

    app = Starlette(routes=[Route("/{path:path}", answer, methods=["GET", "POST", "DELETE"])])
    with serving(app) as server:
        monkeypatch.setenv("DNCQ_URL", server.url)
        get_settings.cache_clear()
        yield server.url


@pytest.mark.parametrize("args", [("machines", "list"), ("jobs",), ("backup", "list")],
                         ids=" ".join)
def test_a_proxys_plain_error_is_said_with_the_url_and_what_may_be_wrong(
        a_proxy_without_dncq, args):
    result = dncq(*args)

    assert result.exit_code == 1, result.output
    said = " ".join(result.output.split())
    assert f"{a_proxy_without_dncq}" in said and "answered HTTP 502: Bad Gateway" in said
    assert "DNCQ_URL may point at another server, or at a proxy that cannot reach dncq" in said


def test_machines_list_in_another_folder_shows_the_fleet_of_the_running_dncq(
        demo_fleet, elsewhere):
    result = dncq("machines", "list")

    assert result.exit_code == 0, result.output
    assert all(m in result.output for m in ("1010", "1013", "1016"))


@pytest.mark.parametrize("args", READING, ids=" ".join)
def test_a_command_run_in_an_empty_folder_answers_from_the_server_and_leaves_the_folder_empty(
        demo_fleet, elsewhere, args):
    result = dncq(*args)

    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in elsewhere.iterdir()) == []


def test_a_dncq_url_ending_in_api_is_said_to_be_the_servers_address_alone(
        demo_fleet, elsewhere, monkeypatch):
    # `A=http://host:8000/api/cnc` in the README, so DNCQ_URL=http://host:8000/api looks
    # right; it answered "158 Path is not found. (Not Found)" alone.
    monkeypatch.setenv("DNCQ_URL", os.environ["DNCQ_URL"] + "/api")
    get_settings.cache_clear()

    result = dncq("machines", "list")

    assert result.exit_code == 1
    assert "no such path" in result.output and "without /api" in result.output


def test_machines_list_with_a_wrong_key_is_refused_with_20403(demo_fleet, elsewhere,
                                                               monkeypatch):
    monkeypatch.setenv("DNCQ_API_KEY", "not-the-key")
    get_settings.cache_clear()

    result = dncq("machines", "list")

    assert result.exit_code == 1
    assert " ".join(result.output.split()) == (
        "error: 20403 API key is not valid: the key sent is neither this dncq's admin key nor "
        "one of its named keys; the CLI sent the key set by DNCQ_API_KEY")


def test_a_wrong_key_kept_in_the_data_folder_is_refused_naming_that_file(
        demo_fleet, elsewhere, monkeypatch, tmp_path):
    data = tmp_path / "shop" / "data"
    data.mkdir(parents=True)
    (data / "api-key").write_text("not-the-key\n")
    monkeypatch.delenv("DNCQ_API_KEY")
    monkeypatch.setenv("DNCQ_DATA_DIR", str(tmp_path / "shop" / ".." / "shop" / "data"))
    get_settings.cache_clear()

    result = dncq("machines", "list")

    assert result.exit_code == 1
    said = " ".join(result.output.split())
    assert said.startswith("error: 20403 API key is not valid: the key sent is neither")
    assert said.endswith(f"; the CLI sent the key in {data.resolve() / 'api-key'}; "
                         "DNCQ_API_KEY sends another")


@pytest.mark.parametrize(("args", "said"), [
    (["machines", "list"], "error: 20401 API key is missing: the CLI sends DNCQ_API_KEY, or "
                           "else the key in {here}/data/api-key, which is not there "
                           "(DNCQ_DATA_DIR names the data folder `dncq serve` made it in)"),
    (["machines", "show", "1O16"], "error: 10003 Machine ID does not exist: Invalid MachineID "
                                   "(1O16) (did you mean 1016?)"),
    (["send", "../P.nc", "--to", "1O16"], "error: 10003 Machine ID does not exist: no machine "
                                          "1O16 (did you mean 1016?); nothing was queued; "
                                          "check the ids and tags, or add --anyway"),
], ids=["no key", "mistyped machine", "mistyped selection"])
def test_a_refusal_is_said_in_one_sentence(demo_fleet, elsewhere, program, monkeypatch, args,
                                           said):
    if args == ["machines", "list"]:
        monkeypatch.delenv("DNCQ_API_KEY")
        get_settings.cache_clear()

    result = dncq(*args)

    assert result.exit_code == 1
    assert " ".join(result.output.split()) == said.format(here=elsewhere.resolve())


def test_machines_import_goes_to_the_running_dncq(elsewhere, settings):
    (elsewhere / "fleet.yaml").write_text(FLEET)

    result = dncq("machines", "import", "fleet.yaml")

    assert result.exit_code == 0, result.output
    with db.session_scope(settings.resolved_database_url) as session:
        assert [m.id for m in registry.list_all(session=session)] == ["new1"]
    assert sorted(p.name for p in elsewhere.iterdir()) == ["fleet.yaml"]


@pytest.mark.parametrize("args", READING + CHANGING, ids=" ".join)
def test_a_command_fails_naming_the_url_when_no_dncq_answers_there(nowhere, args):
    result = dncq(*args)

    assert result.exit_code == 1, result.output
    assert f"cannot reach dncq at {nowhere}" in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)


def test_a_command_that_finds_no_dncq_on_its_port_names_the_port_setting(
        nowhere, monkeypatch) -> None:
    # The tour's `DNCQ_PORT=8001 dncq serve` in one terminal, the CLI in another without it:
    # the hint named DNCQ_URL alone, which the tour never sets.
    port = free_port()
    monkeypatch.delenv("DNCQ_URL")
    monkeypatch.setenv("DNCQ_PORT", str(port))
    get_settings.cache_clear()

    result = dncq("machines", "list")

    assert result.exit_code == 1, result.output
    assert f"cannot reach dncq at http://127.0.0.1:{port}" in result.output
    assert "DNCQ_URL, or DNCQ_PORT as dncq serve was started with," in result.output


@pytest.fixture
def a_host_that_does_not_answer(nowhere, monkeypatch) -> Iterator[str]:
    """The CLI pointed at a loopback port whose queue of connections is full: a connection
    waits there, as one to a host that is down or behind a firewall that drops it."""
    listener = socket.create_server(("127.0.0.1", 0), backlog=0)
    url = f"http://127.0.0.1:{listener.getsockname()[1]}"
    queued: list[socket.socket] = []
    while True:
        queued.append(socket.socket())
        queued[-1].settimeout(0.5)
        try:
            queued[-1].connect(listener.getsockname())
        except TimeoutError:
            break  # full: the next connection waits too
    monkeypatch.setenv("DNCQ_URL", url)
    yield url
    for each in (*queued, listener):
        each.close()


def test_a_command_to_a_host_that_does_not_answer_fails_in_seconds_naming_the_url(
        a_host_that_does_not_answer):
    # It waited for the connection as long as for an answer: ten minutes, or the two the
    # system takes to give up, before it said anything.
    done = subprocess.run([sys.executable, "-m", "jobs.cli", "jobs"], stdin=subprocess.DEVNULL,
                          capture_output=True, text=True, timeout=60)

    assert done.returncode == 1
    assert f"cannot reach dncq at {a_host_that_does_not_answer} (timed out)" in done.stderr


@pytest.mark.parametrize("args", READING + CHANGING, ids=" ".join)
def test_a_command_answered_with_a_web_page_says_so_in_one_line(another_server, args):
    result = dncq(*args)

    assert result.exit_code == 1, result.output
    assert result.output.count("\n") == 1 and "<html>" not in result.output, result.output
    assert "with a web page (text/html)" in result.output
    assert "DNCQ_URL may point at another server" in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)


@pytest.mark.parametrize("args", READING + CHANGING, ids=" ".join)
def test_a_command_answered_with_another_apis_json_says_so_in_one_line(another_api, args):
    result = dncq(*args)

    assert result.exit_code == 1, result.output
    assert result.output.count("\n") == 1, result.output
    assert f"{another_api}/" in result.output and "not dncq's answer" in result.output
    assert "DNCQ_URL may point at another server" in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)


def test_machines_import_direct_writes_the_configured_database_and_names_it(env, settings):
    (env / "fleet.yaml").write_text(FLEET)

    result = dncq("machines", "import", "--direct", "fleet.yaml")

    assert result.exit_code == 0, result.output
    assert str(settings.data_dir / "dncq.sqlite3") in result.output.replace("\n", "")
    with db.session_scope(settings.resolved_database_url) as session:
        assert [m.id for m in registry.list_all(session=session)] == ["new1"]


def test_machines_import_of_a_file_that_is_not_yaml_fails_saying_so(elsewhere):
    (elsewhere / "fleet.yaml").write_text("machines: [{id: a, name: A\n")

    result = dncq("machines", "import", "fleet.yaml")

    assert result.exit_code == 1
    assert "a fleet file is YAML, and this is not" in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)


def test_the_api_says_which_database_it_opened(env, settings, monkeypatch):
    monkeypatch.delenv("DNCQ_API_KEY")  # it stops right after opening the database
    get_settings.cache_clear()

    result = dncq("api")

    assert f"Database: sqlite:///{settings.data_dir}/dncq.sqlite3" in result.output.replace(
        "\n", "")


def test_jobs_prune_names_the_database_it_opened(env, settings):
    result = dncq("jobs", "prune")

    assert result.exit_code == 0, result.output
    assert str(settings.data_dir / "dncq.sqlite3") in result.output.replace("\n", "")


def test_jobs_prune_where_there_is_no_database_fails_and_makes_none(nowhere, tmp_path):
    result = dncq("jobs", "prune")

    assert result.exit_code == 1
    assert "no dncq database at" in result.output
    assert sorted(p.name for p in Path(tmp_path).iterdir()) == ["P.nc", "fleet.yaml"]
