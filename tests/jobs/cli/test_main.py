"""The `dncq` command against a live API: the registry commands and the file commands."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tomllib
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path
from typing import Any

import pytest
from pydantic import SecretStr

from jobs import db
from jobs.api.app import create_app
from jobs.fleet import demo, door, registry, sealed
from jobs.models import Job, JobKind, Target
from jobs.run.queue import producer
from jobs.settings import get_settings
from tests.jobs.cli.runner import dncq
from tests.jobs.helpers import on_machine, wait_until
from tests.live_server import LiveServer, serving
from worker import transports
from worker.transports.mock import MockOptions, MockTransport

FLEET = """\
machines:
  - {id: 1010, name: Lathe-A, model: Fanuc 0i-F}
  - {id: ftp1, name: Mill-B, model: Mock, transport: mock-login, options: {password: s3cr3t-pw}}
"""
CONTRACT_ERROR_EXIT = 1


class LoginOptions(MockOptions):
    """A mock that needs a login, as an FTP or share transport does."""

    password: SecretStr | None = None


@pytest.fixture
def login_transport(monkeypatch) -> None:
    """A transport with a secret option, registered for this test only."""
    monkeypatch.setitem(transports.REGISTRY, "mock-login",
                        transports.TransportKind(MockTransport, LoginOptions))


@pytest.fixture
def fleet_file(elsewhere, login_transport) -> Path:
    path = elsewhere / "fleet.yaml"
    path.write_text(FLEET)
    return path


# -- the registry ---------------------------------------------------------------------------


def test_machines_import_twice_adds_then_updates(fleet_file):
    first = dncq("machines", "import", "fleet.yaml")
    second = dncq("machines", "import", "fleet.yaml")

    assert (first.exit_code, second.exit_code) == (0, 0)
    assert "2 added, 0 updated" in first.output
    assert "0 added, 2 updated" in second.output


def test_machines_list_shows_each_machine_once_after_two_imports(fleet_file):
    dncq("machines", "import", "fleet.yaml")
    dncq("machines", "import", "fleet.yaml")

    result = dncq("machines", "list")

    assert result.exit_code == 0
    assert (result.output.count("1010"), result.output.count("ftp1")) == (1, 1)


def test_machines_import_of_a_bad_file_fails_naming_the_entry_and_imports_nothing(elsewhere):
    (elsewhere / "bad.yaml").write_text(
        "machines:\n  - {id: ok, name: A, model: Mock}\n  - {id: bad, name: B, model: Zeiss}\n")

    result = dncq("machines", "import", "bad.yaml")

    assert result.exit_code == 1
    assert "entry 2 (id bad)" in result.output
    assert "ok" not in dncq("machines", "list").output


def test_machines_import_of_a_masked_password_for_a_new_machine_fails_naming_it(elsewhere):
    (elsewhere / "masked.yaml").write_text(
        "machines:\n  - {id: ok, name: A, model: Mock}\n"
        "  - {id: f1, name: B, model: Fanuc 0i-F, transport: ftp,\n"
        "     options: {host: 127.0.0.1, password: '**********'}}\n")

    result = dncq("machines", "import", "masked.yaml")

    assert result.exit_code == 1
    assert "entry 2 (id f1)" in result.output and "give the secret itself" in result.output
    assert "ok" not in dncq("machines", "list").output  # refused whole


def test_machines_show_masks_the_password(fleet_file):
    dncq("machines", "import", "fleet.yaml")

    result = dncq("machines", "show", "ftp1")

    assert result.exit_code == 0
    assert "**********" in result.output
    assert "s3cr3t-pw" not in result.output


def test_machines_show_writes_its_fields_as_a_fleet_file_would_not_as_python(elsewhere):
    (elsewhere / "fleet.yaml").write_text(
        "machines:\n  - {id: m1, name: A, model: Mock, tags: [lathes, hall-1],\n"
        "     options: {latency_ms: 5, current_program: O1234}}\n")
    dncq("machines", "import", "fleet.yaml")

    shown = dncq("machines", "show", "m1").output
    fields = {row[0]: row[1].strip() for row in (line.split(None, 1) for line in
              shown.splitlines()) if len(row) == 2}

    assert fields["tags"] == "lathes, hall-1" and fields["enabled"] == "yes"
    assert fields["options"] == "latency_ms: 5"  # one setting a line
    assert "current_program: O1234" in shown
    assert not any(mark in shown for mark in ("['", "{'", "True", "None"))


def test_machines_show_says_what_the_model_and_the_transport_allow_together(elsewhere):
    (elsewhere / "fleet.yaml").write_text(
        "machines:\n  - {id: m1, name: A, model: Fanuc 0i-F}\n"
        "  - {id: f1, name: B, model: Fanuc 0i-F, transport: ftp, options: {host: 127.0.0.1}}\n")
    dncq("machines", "import", "fleet.yaml")

    def can(machine_id: str) -> str:
        output = dncq("machines", "show", machine_id).output
        return " ".join(line for line in output.splitlines() if "can" in line)

    assert "lock" in can("m1") and "select" in can("m1")  # a Fanuc's own memory
    assert "lock" not in can("f1") and "select" not in can("f1")  # the same, behind FTP


def test_machines_show_of_an_unknown_machine_fails(elsewhere):
    result = dncq("machines", "show", "nope")

    assert result.exit_code == 1
    assert "Invalid MachineID (nope)" in result.output


def test_machines_rm_removes_the_machine(fleet_file):
    dncq("machines", "import", "fleet.yaml")

    result = dncq("machines", "rm", "1010")

    assert result.exit_code == 0
    assert "1010" not in dncq("machines", "list").output
    assert dncq("machines", "show", "1010").exit_code == 1


def test_machines_rm_of_an_unknown_machine_fails(elsewhere):
    assert dncq("machines", "rm", "nope").exit_code == 1


# -- files, through a live API ---------------------------------------------------------------


@pytest.fixture
def live(settings, demo_fleet, env, monkeypatch) -> Iterator[LiveServer]:
    """The demo fleet served on loopback, and the CLI pointed at it."""
    with serving(create_app(settings)) as server:
        monkeypatch.setenv("DNCQ_URL", server.url)
        get_settings.cache_clear()
        yield server


def test_ls_lists_the_root_of_a_machine(live):
    result = dncq("ls", "1010")

    assert result.exit_code == 0
    assert result.output.splitlines() == ["//CNC_MEM/", "  USER/", "  10", "  1234", "  8000"]


def test_ls_prints_controller_folders_and_names_as_they_are(live, settings):
    # A backslash before a closing markup tag, and brackets, are not Rich markup here.
    (settings.data_dir / "mock" / "1013" / "files" / "PRG" / "USER" / "[x]100").write_bytes(
        b"G0\n")

    result = dncq("ls", "1013")

    assert result.exit_code == 0
    assert result.output.splitlines()[0] == "PRG\\USER\\"
    assert "  [x]100" in result.output.splitlines()


def test_ls_recursive_lists_files_with_their_folders(live):
    result = dncq("ls", "1016", "-r")

    assert [line.split() for line in result.output.splitlines()] == [
        ["/", "SAMPLE"], ["1", "sample1.nc"], ["1/1", "sample2.nc"]]


def test_ls_says_a_folder_is_empty(live, settings):
    (settings.data_dir / "mock" / "1016" / "files" / "empty").mkdir()

    listed = dncq("ls", "1016", "empty")
    below = dncq("ls", "1016", "empty", "-r")

    assert (listed.exit_code, listed.output.splitlines()) == (0, ["/empty", "  (empty)"])
    assert (below.exit_code, below.output.splitlines()) == (0, ["No files below empty."])


def test_ls_of_an_unknown_machine_fails_with_10003(live):
    result = dncq("ls", "nope")

    assert result.exit_code == CONTRACT_ERROR_EXIT
    assert "10003" in result.output


def test_put_sends_a_local_file(live, settings, env):
    (env / "PART.NC").write_bytes(b"G0 X1\n")

    result = dncq("put", "1016", "PART.NC")

    assert result.exit_code == 0
    assert on_machine(settings, "1016", "PART.NC").read_bytes() == b"G0 X1\n"


def test_put_over_an_existing_file_fails_with_142(live, settings, env):
    (env / "SAMPLE").write_bytes(b"new\n")

    result = dncq("put", "1016", "SAMPLE")

    assert result.exit_code == CONTRACT_ERROR_EXIT
    assert "142" in result.output
    assert on_machine(settings, "1016", "SAMPLE").read_text() == demo.GCODE


def test_get_writes_the_file_to_the_output_path(live, env):
    result = dncq("get", "1016", "SAMPLE", "-o", "copy.nc")

    assert result.exit_code == 0
    assert (env / "copy.nc").read_text() == demo.GCODE


def test_get_into_an_existing_folder_saves_under_the_file_name(live, env):
    (env / "copies").mkdir()

    result = dncq("get", "1016", "SAMPLE", "-o", "copies")

    assert result.exit_code == 0, result.output
    assert (env / "copies" / "SAMPLE").read_text() == demo.GCODE
    assert sorted(p.name for p in env.iterdir() if p.name.endswith(".part")) == []


def test_get_into_a_folder_not_there_yet_makes_it_and_saves_under_the_file_name(live, env):
    result = dncq("get", "1016", "SAMPLE", "-o", "dl/")

    assert result.exit_code == 0, result.output
    assert [p.name for p in (env / "dl").iterdir()] == ["SAMPLE"]
    assert (env / "dl" / "SAMPLE").read_text() == demo.GCODE


def test_get_of_a_file_the_machine_has_not_into_a_new_folder_makes_no_folder(live, env):
    result = dncq("get", "1016", "NOPE", "-o", "dl/")

    assert result.exit_code == CONTRACT_ERROR_EXIT
    assert not (env / "dl").exists()


def test_get_into_a_missing_folder_fails_clearly_and_writes_nothing(live, env):
    result = dncq("get", "1016", "SAMPLE", "-o", "no/such/dir/x.nc")

    assert result.exit_code == 2
    assert "no folder no/such/dir to save into" in result.output
    assert not (env / "no").exists()


def test_get_of_a_name_with_a_folder_in_it_says_what_the_machine_says_and_writes_nothing(
        live, env):
    result = dncq("get", "1016", "1/sample1.nc")

    assert result.exit_code == CONTRACT_ERROR_EXIT
    assert "plain name" in result.output
    assert sorted(p.name for p in env.iterdir() if "sample1" in p.name) == []


def test_an_empty_job_id_is_refused_not_read_as_the_job_list(live):
    result = dncq("job", "")

    assert result.exit_code == 2
    assert "the id is empty" in result.output


def test_get_of_a_missing_file_fails_with_158_and_writes_nothing(live, env):
    result = dncq("get", "1016", "NOPE", "-o", "copy.nc")

    assert result.exit_code == CONTRACT_ERROR_EXIT
    assert "158" in result.output
    assert sorted(p.name for p in env.iterdir() if p.name.startswith("copy")) == []


def test_rm_deletes_the_file(live, settings):
    result = dncq("rm", "1016", "SAMPLE")

    assert result.exit_code == 0
    assert not on_machine(settings, "1016", "SAMPLE").exists()


def test_rm_of_a_missing_file_fails_with_158(live):
    result = dncq("rm", "1016", "NOPE")

    assert result.exit_code == CONTRACT_ERROR_EXIT
    assert "158" in result.output


def test_rm_of_the_running_program_fails_unless_forced(live, settings):
    refused = dncq("rm", "1010", "1234")
    forced = dncq("rm", "1010", "1234", "--force")

    assert (refused.exit_code, forced.exit_code) == (CONTRACT_ERROR_EXIT, 0)
    assert "20008" in refused.output
    assert not on_machine(settings, "1010", "CNC_MEM/O1234").exists()


def test_rm_of_the_running_program_names_the_option_that_goes_ahead(live):
    # It said "add force=true", the API's parameter, which no dncq command takes.
    refused = dncq("rm", "1010", "1234")

    assert refused.output == ("error: 20008 Program is running on the machine: 1234 is "
                              "running; add force=true (--force on the command line) to go "
                              "ahead\n")


def test_find_prints_the_folder_holding_the_file(live):
    result = dncq("find", "1016", "sample2.nc")

    assert result.exit_code == 0
    assert result.output.strip() == "/1/1"


def test_find_of_a_missing_file_fails_with_158(live):
    result = dncq("find", "1016", "nothing.nc")

    assert result.exit_code == CONTRACT_ERROR_EXIT
    assert "158" in result.output


def test_file_command_with_a_wrong_key_fails_with_403(live, monkeypatch):
    monkeypatch.setenv("DNCQ_API_KEY", "not-the-key")
    get_settings.cache_clear()

    result = dncq("ls", "1016")

    assert result.exit_code == 1
    assert "20403" in result.output


@pytest.mark.parametrize(("pool", "args", "prefetch"), [
    ("threads", [], 16),  # one task per slot: no worker hoards a fleet's tasks
    # a gevent pool holds 32 greenlets for 16 slots (worker/app.py), two tasks each: a full
    # pool must not leave the poller asleep
    ("gevent", [], 64),
    ("gevent", ["--prefetch-multiplier", "5"], 160),  # the option still decides when given
])
def test_a_worker_prefetches_by_its_pool(queue_settings, start_worker, pool, args, prefetch):
    worker = start_worker("p", queue_settings, concurrency=16, pool=pool, args=args)
    worker.wait_ready()
    stats: dict[str, Any] = {}

    def answered() -> bool:  # a broadcast sent as the worker starts may find nobody yet
        stats.update(producer(queue_settings).control.inspect(
            destination=[worker.hostname], timeout=1).stats() or {})
        return worker.hostname in stats

    wait_until(answered, timeout_s=15)
    assert stats[worker.hostname]["prefetch_count"] == prefetch


def test_api_without_a_key_fails_with_a_message_instead_of_a_traceback(env, monkeypatch):
    monkeypatch.delenv("DNCQ_API_KEY", raising=False)
    get_settings.cache_clear()
    result = dncq("api")
    assert result.exit_code == 1
    assert "no API key: set DNCQ_API_KEY" in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)


def test_get_of_a_download_that_breaks_off_says_so_and_leaves_no_part_file(
        live, env, settings, monkeypatch):
    from worker.transports.base import Dropped
    from worker.transports.mock import MockTransport

    big = on_machine(settings, "1016", "BIG.NC")
    big.write_bytes(b"G1 X1\n" * 1024 * 1024)  # more than one chunk
    read = MockTransport.read

    def dropping(self, path, **kwargs):
        chunks = read(self, path, **kwargs)
        yield next(chunks)
        raise Dropped("link lost mid-file")

    monkeypatch.setattr(MockTransport, "read", dropping)
    result = dncq("get", "1016", "BIG.NC", "-o", "copy.nc")

    assert result.exit_code != 0
    assert "broke off" in result.output and "Traceback" not in result.output
    assert sorted(p.name for p in env.iterdir() if p.name.startswith("copy")) == []


def test_get_stopped_with_ctrl_c_says_so_and_leaves_no_part_file(live, env, settings,
                                                               monkeypatch):
    import httpx

    on_machine(settings, "1016", "BIG.NC").write_bytes(b"G1 X1\n" * 1024 * 1024)
    iter_bytes = httpx.Response.iter_bytes

    def interrupted(self, *args, **kwargs):  # the user's Ctrl-C, after the first chunk
        chunks = iter_bytes(self, *args, **kwargs)
        yield next(chunks)
        raise KeyboardInterrupt

    monkeypatch.setattr(httpx.Response, "iter_bytes", interrupted)
    result = dncq("get", "1016", "BIG.NC", "-o", "copy.nc")

    assert result.exit_code == 130  # as Click ends on Ctrl-C
    assert "Stopped: copy.nc was not saved." in result.output
    assert sorted(p.name for p in env.iterdir() if p.name.startswith("copy")) == []


def test_machines_reseal_moves_the_secrets_to_a_new_first_key(fleet_file, monkeypatch, settings):
    old = dncq("secrets-key").output.strip()
    monkeypatch.setenv(sealed.KEY_ENV, old)
    dncq("machines", "import", "fleet.yaml")
    new = dncq("secrets-key").output.strip()
    monkeypatch.setenv(sealed.KEY_ENV, f"{new},{old}")
    monkeypatch.setenv("DNCQ_DATA_DIR", str(settings.data_dir))  # reseal runs by the database
    get_settings.cache_clear()
    with db.session_scope(settings.resolved_database_url) as session:  # an older dncq's record
        session.add(Job(id="old", kind=JobKind.SEND, targets=[Target(
            position=0, machine_id="ftp1", error_msg="530 Login incorrect for S3CR3T-PW")]))

    result = dncq("machines", "reseal")

    assert result.exit_code == 0 and "Sealed the secrets of 1 machines" in result.output
    assert "Masked a machine's secret in 1 stored messages" in result.output
    monkeypatch.setenv(sealed.KEY_ENV, new)
    with db.session_scope(settings.resolved_database_url) as session:
        spec = registry.get(session=session, machine_id="ftp1")
    with door.open_files(spec, data_dir=settings.data_dir) as files:
        assert files.transport.inner.base_options.password.get_secret_value() == "s3cr3t-pw"


@pytest.mark.parametrize("command", [("send",), ("jobs",), ("users", "add"), ("audit",),
                                     ("runs",), ("backup", "restore")])
def test_help_at_80_columns_cuts_no_option_nor_its_words(command: tuple[str, ...]) -> None:
    # Click's list of date formats, an enum's choices and the --no- forms of plain flags
    # left options' words cut with an ellipsis.
    shown = dncq(*command, "--help", width=80).output

    assert "…" not in shown and "%Y" not in shown, shown
    assert all(len(line) <= 80 for line in shown.splitlines())


def test_a_list_piped_into_another_program_gives_every_cell_whole(elsewhere, add_machines):
    # `dncq machines list | grep ...`: laid out at 80 columns, the name was cut.
    name = "Mill-B-" + "with-a-long-name-" * 8
    add_machines({"id": "m1", "name": name, "model": "Mock"})
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}

    done = subprocess.run([sys.executable, "-m", "jobs.cli", "machines", "list"],
                          cwd=elsewhere, env=env, stdin=subprocess.DEVNULL,
                          capture_output=True, text=True, timeout=120)

    assert done.returncode == 0, done.stderr
    [row] = [line for line in done.stdout.splitlines() if line.startswith("m1 ")]
    assert name in row.split()


@pytest.mark.parametrize("command", ["serve", "api"])
def test_a_server_whose_port_is_taken_exits_at_once_with_the_reason(tmp_path: Path,
                                                                    command: str) -> None:
    import os
    import socket
    import subprocess
    import sys

    with socket.create_server(("127.0.0.1", 0)) as taken:  # another program listens there
        port = taken.getsockname()[1]
        env = {**os.environ, "DNCQ_DATA_DIR": str(tmp_path / "data"), "DNCQ_PORT": str(port),
               "DNCQ_HOST": "127.0.0.1", "DNCQ_API_KEY": "k" * 32}
        for name in ("DNCQ_DATABASE_URL", "DNCQ_BROKER_URL"):
            env.pop(name, None)

        done = subprocess.run([sys.executable, "-m", "jobs.cli", command], cwd=tmp_path,
                              env=env, capture_output=True, text=True, timeout=120)

    assert done.returncode == 1, done.stdout + done.stderr
    assert f"error: cannot listen on 127.0.0.1:{port}: Address already in use" in done.stderr
    assert "listening on" not in done.stdout  # it never said it was


@pytest.mark.parametrize(("setting", "said"), [
    ({"DNCQ_PORT": "abc"}, "error: a setting is not valid: port: Input should be a valid "
                           "integer"),
    ({"DNCQ_BACKUP_ZIP_LEVEL": "12"}, "error: a setting is not valid: backup_zip_level: "
                                      "Input should be less than or equal to 9"),
    ({"DNCQ_PORT": "99999"}, "error: a setting is not valid: port: Input should be less "
                             "than or equal to 65535"),
    ({"DNCQ_URL": "http://127.0.0.1:abc"}, "error: a setting is not valid: url: "
                                           "not a URL of the API"),
    ({"DNCQ_CONFIG_FILE": "{tmp}/nosuch.toml"}, "error: the settings cannot be read "
                                                "(DNCQ_CONFIG_FILE): DNCQ_CONFIG_FILE: no "
                                                "file {tmp}/nosuch.toml"),
    ({"DNCQ_CONFIG_FILE": "{tmp}/broken.toml"}, "error: the settings cannot be read "
                                                "(DNCQ_CONFIG_FILE): Invalid value"),
    ({"DNCQ_CONFIG_FILE": "{tmp}/typo.toml"}, "error: the settings cannot be read "
                                              "(DNCQ_CONFIG_FILE): DNCQ_CONFIG_FILE: "
                                              "{tmp}/typo.toml: not a setting: batch_wait "
                                              "(did you mean batch_wait_s?)")])
def test_a_bad_setting_is_said_in_one_line_and_nothing_runs(
        tmp_path: Path, setting: dict[str, str], said: str) -> None:
    import os
    import subprocess
    import sys

    (tmp_path / "broken.toml").write_text("port = [\n")
    (tmp_path / "typo.toml").write_text("batch_wait = 120\n")  # for batch_wait_s
    env = {**os.environ, "DNCQ_DATA_DIR": str(tmp_path / "data"),
           **{k: v.format(tmp=tmp_path) for k, v in setting.items()}}

    done = subprocess.run([sys.executable, "-m", "jobs.cli", "machines", "list"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)

    assert done.returncode == 2, done.stdout + done.stderr
    assert said.format(tmp=tmp_path) in " ".join(done.stderr.split())
    assert "Traceback" not in done.stderr


def test_a_second_serve_on_one_data_folder_exits_and_leaves_the_first_ones_machines_alone(
        tmp_path: Path) -> None:
    import fcntl
    import os
    import socket
    import subprocess
    import sys

    data = tmp_path / "data"
    data.mkdir()
    with open(data / ".serve.lock", "a+") as first, socket.socket() as free:
        fcntl.flock(first, fcntl.LOCK_EX | fcntl.LOCK_NB)  # as the first dncq serve holds it
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
        free.close()
        env = {**os.environ, "DNCQ_DATA_DIR": str(data), "DNCQ_PORT": str(port),
               "DNCQ_HOST": "127.0.0.1", "DNCQ_API_KEY": "k" * 32}
        for name in ("DNCQ_DATABASE_URL", "DNCQ_BROKER_URL"):
            env.pop(name, None)

        done = subprocess.run([sys.executable, "-m", "jobs.cli", "serve"], cwd=tmp_path,
                              env=env, capture_output=True, text=True, timeout=120)

    assert done.returncode == 1, done.stdout + done.stderr
    assert f"another dncq serve runs on {data}/" in " ".join(done.stderr.split())
    assert not (data / "dncq.sqlite3").exists()  # nothing of the first one's was touched


def test_ctrl_c_while_the_command_loads_exits_130_without_a_traceback(tmp_path):
    # What the console script runs, as an install makes it from pyproject.toml.
    pyproject = tomllib.loads((Path(__file__).parents[3] / "pyproject.toml").read_text())
    module, function = pyproject["project"]["scripts"]["dncq"].split(":")
    script = f"import sys; from {module} import {function}; sys.exit({function}())"
    env = {**os.environ, "DNCQ_URL": "http://127.0.0.1:9", "DNCQ_DATA_DIR": str(tmp_path)}
    command = subprocess.Popen(  # -X importtime: a line as each module is loaded
        [sys.executable, "-X", "importtime", "-c", script, "ls", "1010"], env=env,
        stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert command.stderr is not None
    for line in command.stderr:  # the first of our modules loaded: the command is loading
        if line.rsplit("|", 1)[-1].strip() in ("jobs.settings", "jobs.db"):
            break
    command.send_signal(signal.SIGINT)
    said = command.stderr.read()
    command.wait(timeout=60)

    assert command.returncode == 130
    assert "Traceback" not in said and "KeyboardInterrupt" not in said, said


# What a command that only asks the API has no use for: the database (SQLAlchemy, Alembic),
# the queue (Celery) and the transports. They took seconds to load before `dncq stop` left.
SERVER_SIDE = ("sqlalchemy", "alembic", "celery", "jobs.db", "jobs.models", "worker.transports")


@pytest.mark.parametrize("args", [("--help",), ("stop", "j-1"), ("backup", "list")])
def test_a_command_that_asks_the_api_loads_no_database_queue_or_transport(tmp_path, args):
    script = ("import sys\n"
              "from jobs.cli import dncq\n"
              "try:\n"
              "    dncq()\n"
              "except SystemExit:\n"
              "    pass\n"
              "print(*sys.modules, file=sys.stderr)")
    env = {**os.environ, "DNCQ_URL": "http://127.0.0.1:9", "DNCQ_DATA_DIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", script, *args], env=env,
                          capture_output=True, text=True, timeout=120)
    loaded = done.stderr.split()

    assert "jobs.cli.main" in loaded, done.stderr  # the command ran to its end
    assert [m for m in loaded if any(m == s or m.startswith(f"{s}.") for s in SERVER_SIDE)
            ] == []


def test_version_prints_the_version_of_the_package():
    result = dncq("--version")

    assert result.exit_code == 0
    assert result.output == f"dncq {metadata.version('dncq')}\n"


@pytest.mark.parametrize(("command", "said"), [
    (("run", "2001", "nosuch.nc"), "error: no file nosuch.nc"),
    (("requests", "test", "2002", "nosuch.NC"), "error: no file nosuch.NC"),
    (("put", "1016", "."), "error: . is a folder, not a file"),
    (("runs", "--since", "yesterday"), "error: --since 'yesterday' is no date or time: give "
                                       "2026-11-24 or 2026-11-24 14:00 (local)"),
])
def test_a_file_or_a_time_the_cli_cannot_take_is_one_line_of_error(command, said) -> None:
    result = dncq(*command, width=200)

    assert result.exit_code == 2
    assert result.output.strip() == said  # not Click's box of usage
