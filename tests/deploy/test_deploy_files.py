"""The deploy files (compose, Dockerfile, systemd units) run real commands and fit together."""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import typer.main
import yaml
from pydantic import SecretStr
from typer.testing import CliRunner

from jobs.api.app import create_app
from jobs.cli.main import app as cli_app
from jobs.settings import Settings

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
COMPOSE_FILE = DEPLOY / "docker-compose.yml"
DOCKERFILE = DEPLOY / "Dockerfile"
ENV_EXAMPLE = DEPLOY / "dncq.env.example"
UNIT_FILES = sorted((DEPLOY / "systemd").glob("*.service"))
WORKER_APP = REPO / "worker" / "app.py"
CELERY_APPS = {"worker.app", "worker.app:celery_app"}
CELERY_PLUGIN_COMMANDS = {"flower"}  # installed only in their own image: name checked only
INSTALLED_DNCQ = "/opt/dncq/venv/bin/dncq"  # where the units expect the console script
UNIT_SPECIFIERS = {"i": "1", "I": "1", "n": "unit.service", "N": "unit", "p": "unit",
                   "H": "host", "l": "host", "%": "%"}
EXEC_KEYS = ("ExecStartPre", "ExecStart", "ExecStartPost", "ExecReload", "ExecStop")


# -- reading the files --------------------------------------------------------------


def load_compose() -> dict[str, Any]:
    """The compose file, anchors and merge keys resolved."""
    data: dict[str, Any] = yaml.safe_load(COMPOSE_FILE.read_text())
    return data


def uses_dncq_image(service: dict[str, Any]) -> bool:
    """Whether a compose service runs the image built from deploy/Dockerfile."""
    build = service.get("build")
    if isinstance(build, dict) and Path(build.get("dockerfile", "")).name == DOCKERFILE.name:
        return True
    return str(service.get("image", "")).startswith("dncq")


def dncq_services() -> dict[str, dict[str, Any]]:
    """The compose services running the dncq image."""
    return {name: svc for name, svc in load_compose()["services"].items() if uses_dncq_image(svc)}


def as_argv(value: str | list[str]) -> list[str]:
    """A command given as a list or as a shell-style string."""
    return [str(v) for v in value] if isinstance(value, list) else shlex.split(value)


def shell_unwrapped(argv: list[str]) -> list[list[str]]:
    """The commands inside `sh -c '... && ...'`, else the command itself."""
    if len(argv) == 3 and Path(argv[0]).name in {"sh", "bash"} and argv[1] == "-c":
        parts = re.split(r"&&|;|\|\|", argv[2])
        commands = [shlex.split(part) for part in parts if part.strip()]
        return [cmd[1:] if cmd[0] == "exec" else cmd for cmd in commands]
    return [argv]


def dockerfile_instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of the Dockerfile, continuation lines joined."""
    instructions: list[tuple[str, str]] = []
    pending = ""
    for line in DOCKERFILE.read_text().splitlines():
        stripped = line.strip()
        if not pending and (not stripped or stripped.startswith("#")):
            continue
        if stripped.startswith("#"):  # a comment inside a continued instruction
            continue
        pending += " " + stripped.removesuffix("\\")
        if not stripped.endswith("\\"):
            word, _, args = pending.strip().partition(" ")
            instructions.append((word.upper(), args.strip()))
            pending = ""
    return instructions


def dockerfile_exec(instruction: str) -> list[str]:
    """The argv of the last CMD or ENTRYPOINT (exec or shell form); [] when absent."""
    found = [args for word, args in dockerfile_instructions() if word == instruction]
    if not found:
        return []
    args = found[-1]
    return [str(a) for a in json.loads(args)] if args.startswith("[") else shlex.split(args)


def read_unit(path: Path) -> dict[str, list[tuple[str, str]]]:
    """A systemd unit as {section: [(key, value), ...]}; keys may repeat, as systemd allows."""
    sections: dict[str, list[tuple[str, str]]] = {}
    current: list[tuple[str, str]] = []
    pending = ""
    for line in path.read_text().splitlines():
        stripped = line.strip()
        if not pending and (not stripped or stripped[0] in "#;"):
            continue
        if stripped.startswith("[") and stripped.endswith("]") and not pending:
            current = sections.setdefault(stripped[1:-1], [])
            continue
        pending += stripped.removesuffix("\\") + (" " if stripped.endswith("\\") else "")
        if not stripped.endswith("\\"):
            key, _, value = pending.partition("=")
            current.append((key.strip(), value.strip()))
            pending = ""
    return sections


def unit_values(path: Path, section: str, key: str) -> list[str]:
    """Every value of `key` in `section` of a unit, in order."""
    return [v for k, v in read_unit(path).get(section, []) if k == key]


def expand_specifiers(text: str) -> str:
    """Unit specifiers (%i, %H, %%) replaced by sample values."""
    return re.sub(r"%(.)", lambda m: UNIT_SPECIFIERS.get(m.group(1), m.group(0)), text)


def exec_argv(value: str) -> list[str]:
    """The argv of an Exec*= line: prefixes (-@+!:) dropped, specifiers expanded."""
    return shlex.split(expand_specifiers(value.lstrip("-@+!:")))


def env_example() -> dict[str, str]:
    """The variables set by dncq.env.example."""
    pairs = (line.split("=", 1) for line in ENV_EXAMPLE.read_text().splitlines()
             if line.strip() and not line.lstrip().startswith("#"))
    return {key.strip(): value.strip() for key, value in pairs}


def service_environment(service: dict[str, Any]) -> dict[str, str]:
    """A compose service's environment, given as a mapping or as KEY=VALUE items."""
    env = service.get("environment") or {}
    if isinstance(env, list):
        return dict(item.split("=", 1) if "=" in item else (item, "") for item in env)
    return {str(k): str(v) for k, v in env.items()}


def collect_commands() -> list[tuple[str, list[str]]]:
    """(where, argv) of every command the deploy files run with the dncq image or install."""
    commands: list[tuple[str, list[str]]] = []
    image_entrypoint = dockerfile_exec("ENTRYPOINT")
    image_command = image_entrypoint + dockerfile_exec("CMD")
    for argv in shell_unwrapped(image_command):
        commands.append(("Dockerfile CMD", argv))
    for name, service in dncq_services().items():
        if "command" not in service and "entrypoint" not in service:
            continue  # runs the image's CMD, checked above
        entrypoint = (as_argv(service["entrypoint"]) if "entrypoint" in service
                      else image_entrypoint)
        argv = entrypoint + as_argv(service.get("command", []))
        for index, cmd in enumerate(shell_unwrapped(argv)):
            commands.append((f"compose {name} #{index}", cmd))
    for unit in UNIT_FILES:
        for key in EXEC_KEYS:
            for index, value in enumerate(unit_values(unit, "Service", key)):
                commands.append((f"{unit.name} {key} #{index}", exec_argv(value)))
    return commands


COMMANDS = collect_commands()
DNCQ_COMMANDS = [(w, a[1:]) for w, a in COMMANDS if Path(a[0]).name == "dncq"]
CELERY_COMMANDS = [(w, a[1:]) for w, a in COMMANDS if Path(a[0]).name == "celery"]


# -- checking commands -----------------------------------------------------------------


def dncq_subcommands() -> set[str]:
    """The names of dncq's top-level subcommands."""
    return set(getattr(typer.main.get_command(cli_app), "commands", {}))


def skip_unless_worker_app(what: str) -> None:
    """Skip while worker/app.py (the Celery app, being written) does not exist."""
    if not WORKER_APP.exists():
        pytest.skip(f"{what}: worker/app.py does not exist yet, so Celery's options cannot be "
                    "checked; this runs once the Celery app lands")


def option_names(args: list[str]) -> list[str]:
    """The option names in an argument list (`--port=5555` gives `--port`)."""
    return [arg.split("=", 1)[0] for arg in args if arg.startswith("-") and arg != "-"]


def split_celery_args(args: list[str]) -> tuple[str | None, str, list[str]]:
    """(app, subcommand, subcommand args) of a `celery` argument list."""
    app: str | None = None
    rest = list(args)
    while rest and rest[0].startswith("-"):
        arg = rest.pop(0)
        if arg in {"-A", "--app"}:
            app = rest.pop(0)
        elif arg.startswith("--app="):
            app = arg.removeprefix("--app=")
        elif arg.startswith("-A"):
            app = arg.removeprefix("-A")
    assert rest, f"celery {' '.join(args)}: no subcommand"
    return app, rest[0], rest[1:]


@pytest.fixture(scope="session")
def celery_help(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], str]:
    """Factory: the `celery -A worker.app SUBCOMMAND --help` text, run once per subcommand."""
    data_dir = tmp_path_factory.mktemp("celery-help")
    env = {k: v for k, v in os.environ.items() if not k.startswith("DNCQ_")}
    env["DNCQ_DATA_DIR"] = str(data_dir)
    texts: dict[str, str] = {}

    def get(subcommand: str) -> str:
        if subcommand not in texts:
            done = subprocess.run(
                [sys.executable, "-m", "celery", "-A", "worker.app", subcommand, "--help"],
                cwd=REPO, env=env, capture_output=True, text=True, timeout=120,
            )
            assert done.returncode == 0, done.stderr[-2000:]
            texts[subcommand] = done.stdout
        return texts[subcommand]

    return get


def assert_celery_options(subcommand: str, args: list[str], help_text: str, where: str) -> None:
    """Every option in `args` is one that `celery SUBCOMMAND` documents."""
    for name in option_names(args):
        pattern = rf"(?<![\w-]){re.escape(name)}(?![\w-])"
        assert re.search(pattern, help_text), f"{where}: celery {subcommand} has no {name}"


def test_deploy_files_run_only_dncq_and_celery() -> None:
    strangers = [(w, a) for w, a in COMMANDS if Path(a[0]).name not in {"dncq", "celery"}]
    assert not strangers
    assert DNCQ_COMMANDS and CELERY_COMMANDS


@pytest.mark.parametrize(("where", "args"),
                         [c for c in DNCQ_COMMANDS if c[1][:1] != ["worker"]],
                         ids=[w for w, a in DNCQ_COMMANDS if a[:1] != ["worker"]])
def test_dncq_command_is_a_real_subcommand_with_real_options(where: str, args: list[str]) -> None:
    result = CliRunner().invoke(cli_app, [*args, "--help"])
    assert result.exit_code == 0, f"{where}: dncq {' '.join(args)}\n{result.output}"


@pytest.mark.parametrize(("where", "args"),
                         [c for c in DNCQ_COMMANDS if c[1][:1] == ["worker"]],
                         ids=[w for w, a in DNCQ_COMMANDS if a[:1] == ["worker"]])
def test_dncq_worker_passes_real_celery_worker_options(
    where: str, args: list[str], celery_help: Callable[[str], str]
) -> None:
    if "worker" not in dncq_subcommands():
        skip_unless_worker_app(f"{where}: `dncq worker` is not in jobs.cli yet")
        pytest.fail(f"{where}: worker/app.py exists but jobs.cli has no `worker` command")
    skip_unless_worker_app(where)
    help_text = celery_help("worker")
    assert_celery_options("worker", args[1:], help_text, where)
    if "--pool" in args:
        pool = args[args.index("--pool") + 1]
        assert re.search(rf"\b{re.escape(pool)}\b", help_text), f"{where}: no pool {pool}"


@pytest.mark.parametrize(("where", "args"), CELERY_COMMANDS, ids=[w for w, _ in CELERY_COMMANDS])
def test_celery_command_names_the_dncq_app_and_a_real_subcommand(
    where: str, args: list[str], celery_help: Callable[[str], str]
) -> None:
    app, subcommand, sub_args = split_celery_args(args)
    assert app in CELERY_APPS, f"{where}: -A {app}"
    if subcommand in CELERY_PLUGIN_COMMANDS:
        return
    skip_unless_worker_app(where)
    assert_celery_options(subcommand, sub_args, celery_help(subcommand), where)


# -- compose ---------------------------------------------------------------------------


def test_compose_depends_on_names_defined_services() -> None:
    services = load_compose()["services"]
    for name, service in services.items():
        for dependency in service.get("depends_on") or []:
            assert dependency in services, f"{name} depends on unknown service {dependency}"


def test_compose_waits_for_health_only_of_services_with_a_healthcheck() -> None:
    services = load_compose()["services"]
    for name, service in services.items():
        depends = service.get("depends_on") or {}
        for dependency, rule in (depends.items() if isinstance(depends, dict) else []):
            if rule.get("condition") == "service_healthy":
                assert "healthcheck" in services[dependency], f"{name} waits on {dependency}"


def test_compose_dncq_services_set_database_and_broker_urls() -> None:
    for name, service in dncq_services().items():
        env = service_environment(service)
        assert env.get("DNCQ_DATABASE_URL"), name
        assert env.get("DNCQ_BROKER_URL"), name


def test_compose_dncq_variables_are_settings() -> None:
    fields = {f"DNCQ_{name.upper()}" for name in Settings.model_fields}
    for name, service in dncq_services().items():
        unknown = {k for k in service_environment(service) if k.startswith("DNCQ_")} - fields
        assert not unknown, f"{name}: {unknown}"


def test_compose_named_volumes_are_declared() -> None:
    compose = load_compose()
    declared = set(compose.get("volumes") or {})
    for name, service in compose["services"].items():
        for mount in service.get("volumes") or []:
            source = mount.split(":", 1)[0] if isinstance(mount, str) else mount.get("source")
            if source and not source.startswith((".", "/", "~", "$")):
                assert source in declared, f"{name} mounts undeclared volume {source}"


def test_compose_postgres_keeps_data_in_a_volume_and_has_a_healthcheck() -> None:
    postgres = load_compose()["services"]["postgres"]
    assert any(str(m).endswith(":/var/lib/postgresql/data") for m in postgres["volumes"])
    assert "healthcheck" in postgres


def test_compose_worker_can_be_scaled() -> None:
    worker = load_compose()["services"]["worker"]
    assert "container_name" not in worker
    assert not worker.get("ports"), "fixed host ports clash when scaled"


def test_compose_flower_image_installs_flower() -> None:
    build = load_compose()["services"]["flower"]["build"]
    assert "flower" in build["args"]["EXTRA_PACKAGES"].split()


def test_compose_api_healthcheck_polls_a_real_route(tmp_path: Path) -> None:
    test = load_compose()["services"]["api"]["healthcheck"]["test"]
    paths = re.findall(r"https?://[^/'\"]+(/[^'\"?]*)", " ".join(as_argv(test)))
    assert paths
    app = create_app(Settings(data_dir=tmp_path, api_key=SecretStr("k")))
    assert set(paths) <= set(app.openapi()["paths"])


# -- Dockerfile ------------------------------------------------------------------------


def test_dockerfile_builds_on_python_311_slim() -> None:
    bases = [args for word, args in dockerfile_instructions() if word == "FROM"]
    assert bases[-1].split()[0] == "python:3.11-slim"


def test_dockerfile_runs_as_a_non_root_user() -> None:
    users = [args for word, args in dockerfile_instructions() if word == "USER"]
    assert users and users[-1].split(":")[0] not in {"root", "0"}


# -- systemd units ---------------------------------------------------------------------


@pytest.mark.parametrize("unit", UNIT_FILES, ids=[u.name for u in UNIT_FILES])
def test_unit_runs_as_a_dedicated_user(unit: Path) -> None:
    assert unit_values(unit, "Service", "User") == ["dncq"]


@pytest.mark.parametrize("unit", UNIT_FILES, ids=[u.name for u in UNIT_FILES])
def test_unit_reads_the_environment_file(unit: Path) -> None:
    assert unit_values(unit, "Service", "EnvironmentFile") == ["/etc/dncq/dncq.env"]


@pytest.mark.parametrize("unit", UNIT_FILES, ids=[u.name for u in UNIT_FILES])
def test_unit_restarts_on_failure(unit: Path) -> None:
    assert unit_values(unit, "Service", "Restart") == ["on-failure"]


@pytest.mark.parametrize("unit", UNIT_FILES, ids=[u.name for u in UNIT_FILES])
def test_unit_is_hardened(unit: Path) -> None:
    for key, value in (("NoNewPrivileges", "yes"), ("ProtectSystem", "strict"),
                       ("PrivateTmp", "yes")):
        assert unit_values(unit, "Service", key) == [value], key


@pytest.mark.parametrize("unit", UNIT_FILES, ids=[u.name for u in UNIT_FILES])
def test_unit_may_write_the_data_dir_of_the_example_env(unit: Path) -> None:
    data_dir = Path(env_example()["DNCQ_DATA_DIR"])
    writable = [Path(p.lstrip("-+")) for v in unit_values(unit, "Service", "ReadWritePaths")
                for p in v.split()]
    assert any(data_dir.is_relative_to(path) for path in writable)


def test_unit_files_include_api_and_worker_template() -> None:
    assert {u.name for u in UNIT_FILES} >= {"dncq-api.service", "dncq-worker@.service"}


def test_env_example_sets_database_and_broker_urls() -> None:
    env = env_example()
    assert env["DNCQ_DATABASE_URL"].startswith("postgresql+psycopg://")
    assert env["DNCQ_BROKER_URL"].startswith("redis://")


def test_env_example_variables_are_settings() -> None:
    fields = {f"DNCQ_{name.upper()}" for name in Settings.model_fields}
    assert set(env_example()) <= fields


@pytest.mark.parametrize("unit", UNIT_FILES, ids=[u.name for u in UNIT_FILES])
def test_systemd_analyze_verify_accepts_unit(unit: Path, tmp_path: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed (apt-get install systemd to run this)")
    dncq = shutil.which("dncq")
    if dncq is None or " " in dncq:
        pytest.skip("no `dncq` on PATH (pip install .) to stand in for " + INSTALLED_DNCQ)
    copy = tmp_path / unit.name
    copy.write_text(unit.read_text().replace(INSTALLED_DNCQ, dncq))
    # A template is verified through an instance; systemd finds the template beside it.
    target = tmp_path / unit.name.replace("@.", "@1.")
    done = subprocess.run([analyze, "verify", "--man=no", str(target)],
                          capture_output=True, text=True, timeout=60)
    # Accepted: complaints that the dncq user or group does not exist on this host.
    problems = [line for line in done.stderr.splitlines()
                if not re.search(r"\b(user|group)\b", line, re.IGNORECASE)]
    assert not problems, "\n".join(problems)
    assert done.returncode == 0 or done.stderr.strip(), "failed without saying why"
