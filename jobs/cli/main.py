"""The `dncq` command: run the service, manage the registry, move files (Typer + Rich).

A command that only asks the API loads none of the service's code: the database, the queue
and the transports are imported by the commands that run them, inside the command.
"""

from __future__ import annotations

import sys

if sys.argv[1:2] == ["worker"]:  # before any other import (see jobs.run.green)
    from jobs.run import green

    green.patch(sys.argv)

import fcntl  # noqa: E402
import logging  # noqa: E402
import socket  # noqa: E402
from pathlib import Path
from typing import Annotated, Any

import typer

from jobs import __version__, folders, heap, logs
from jobs.cli import backups as cli_backups
from jobs.cli import inbox as cli_inbox
from jobs.cli import jobs as cli_jobs
from jobs.cli import library as cli_library
from jobs.cli import lockouts as cli_lockouts
from jobs.cli import machines as cli_machines
from jobs.cli import requests as cli_requests
from jobs.cli import runs as cli_runs
from jobs.cli import schedules as cli_schedules
from jobs.cli import sim as cli_sim
from jobs.cli import users as cli_users
from jobs.cli.common import (
    OutputOpt,
    api_call,
    download,
    err,
    existing_file,
    fail,
    out,
    saved_at,
    shown_database,
)
from jobs.cli.help_names import Cli
from jobs.run import green
from jobs.settings import AuthMode, Settings, get_settings

log = logging.getLogger(__name__)

app = Cli(help="dncq: file transfer, batch rollout and backup for CNC fleets.",
                  no_args_is_help=True, pretty_exceptions_enable=False)
app.add_typer(cli_machines.machines_app, name="machines")
cli_jobs.register(app)
cli_runs.register(app)
app.add_typer(cli_backups.backup_app, name="backup")
app.add_typer(cli_schedules.schedule_app, name="schedule")
app.add_typer(cli_library.library_app, name="library")
app.add_typer(cli_requests.requests_app, name="requests")
app.add_typer(cli_inbox.inbox_app, name="inbox")
cli_sim.register(app)
cli_users.register(app)
cli_lockouts.register(app)


def _version(shown: bool) -> None:
    if shown:
        out.print(f"dncq {__version__}", highlight=False)
        raise typer.Exit()


@app.callback()
def _options(version: Annotated[bool, typer.Option(
        "--version", callback=_version, is_eager=True,
        help="Print the version of dncq and exit")] = False) -> None:
    """dncq: file transfer, batch rollout and backup for CNC fleets."""


def _db(settings: Settings) -> str:
    from jobs import db

    if settings.log_format == "json":  # from the first line; Celery's setup takes over later
        logs.configure("json")
    folders.private_dir(settings.data_dir)
    url = settings.resolved_database_url
    db.upgrade(url)
    _say(settings, f"Database: {shown_database(url)}", console=err)
    return url


def _say(settings: Settings, text: str, *, console: Any = out, style: str | None = None) -> None:
    """What the service says as it starts: on the console, or as a log record in JSON."""
    if settings.log_format == "json":
        log.info(text)
    else:
        console.print(text, style=style, highlight=False)


# -- running the service ----------------------------------------------------------


@app.command()
def serve(
    fleet: Annotated[Path | None, typer.Option(help="Fleet file (YAML) to import at start")] = None,
    host: Annotated[str | None, typer.Option(help="Listen address")] = None,
    port: Annotated[int | None, typer.Option(help="Listen port")] = None,
) -> None:
    """Run dncq embedded: API, database (SQLite) and queue in one process; no server needed.

    Without --fleet and with an empty registry it creates a demo fleet of simulated machines.
    """
    from jobs import db
    from jobs.fleet import demo, registry
    from jobs.fleet.demo_links import DemoLinks
    from jobs.requests import demo as request_demo

    settings = _settings(host=host, port=port)
    _refuse_a_taken_port(settings)  # before the demo's controls are pointed anywhere
    held = _hold_the_data_folder(settings)  # noqa: F841 - held until the process ends
    url = _db(settings)
    with db.session_scope(url) as session:
        if fleet is not None:
            cli_machines.import_into_database(fleet, url, session, settings.data_dir)
        elif not registry.list_all(session=session):
            count = demo.create(session=session, data_dir=settings.data_dir)
            request_demo.seed(session=session, settings=settings)
            _say(settings, f"Created a demo fleet of {count} simulated machines "
                           f"(data in {settings.data_dir}/).")
    links = DemoLinks()
    with db.session_scope(url) as session:
        if links.start(session=session, data_dir=settings.data_dir):
            _say(settings, "Simulated the demo's DNC (2001) and RS-232 (2002) controls on "
                           f"loopback: try `dncq run 2001 {settings.data_dir}/samples/BIGPART.NC`.")
    try:
        _run_api(settings, announce=True, embedded_worker=True)
    finally:
        links.close()


@app.command()
def api(
    host: Annotated[str | None, typer.Option(help="Listen address")] = None,
    port: Annotated[int | None, typer.Option(help="Listen port")] = None,
) -> None:
    """Run the HTTP API alone (distributed mode: workers run with `dncq worker`)."""
    settings = _settings(host=host, port=port)
    _refuse_a_taken_port(settings)
    _db(settings)
    _run_api(settings, announce=False)


def _hold_the_data_folder(settings: Settings) -> Any:
    """The data folder's lock, held as long as this `dncq serve` runs; exit 1 when another
    holds it. Two embedded servers on one folder share its database and its queue, and the
    second pointed the demo's DNC and RS-232 controls at its own simulators."""
    folders.private_dir(settings.data_dir)
    lock = open(settings.data_dir / ".serve.lock", "a+")  # noqa: SIM115 - held, not closed
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        lock.close()
        raise fail(f"another dncq serve runs on {settings.data_dir}/: stop it first, or give "
                   "this one a folder of its own (DNCQ_DATA_DIR)") from None
    return lock


def _refuse_a_taken_port(settings: Settings) -> None:
    """Exit 1 with the reason when the API's address cannot be listened on: found after the
    start, the embedded queue worker went on alone, and a second demo in the same folder
    pointed the demo's controls at its own."""
    try:
        with socket.create_server((settings.host, settings.port), reuse_port=False) as probe:
            probe.close()
    except OSError as exc:
        raise fail(f"cannot listen on {settings.host}:{settings.port}: {exc.strerror or exc}"
                   f" (another dncq, or another program; choose one with --port or "
                   f"DNCQ_PORT)") from None


def _settings(**overrides: Any) -> Settings:
    base = get_settings()
    changes = {k: v for k, v in overrides.items() if v is not None}
    return base.model_copy(update=changes) if changes else base


def _run_api(settings: Settings, *, announce: bool, embedded_worker: bool = False) -> None:
    import uvicorn

    from jobs.api.app import MissingApiKey, create_app
    from jobs.web.app import install as install_dashboard

    logs.configure(settings.log_format)
    key = settings.effective_api_key(create=announce)
    try:
        app_ = create_app(settings)
    except MissingApiKey as exc:  # say so without a traceback
        raise fail(str(exc)) from None
    install_dashboard(app_)
    _say(settings, f"dncq listening on http://{settings.host}:{settings.port}  "
                   f"(API docs: http://{settings.host}:{settings.port}/docs)")
    _say(settings, f"Dashboard: http://{settings.host}:{settings.port}/  "
                   + ("(sign in as admin with the API key)" if settings.auth is not AuthMode.NONE
                      else "(no sign-in: authentication is off)"))
    if settings.auth is AuthMode.NONE:
        _say(settings, "Authentication is off (DNCQ_AUTH=none).", style="yellow")
    elif announce and settings.api_key is None and key:
        # Its first letters only: this output often ends up in a log.
        _say(settings, f"API key: {key[:3]}…  (kept in {settings.data_dir}/api-key; "
                       "send it as the X-Api-Key header)")
    heap.settle()  # the app is made: what lives now lives as long as the API
    if embedded_worker:
        from worker import embedded

        embedded.run(settings, app_)
    else:
        uvicorn.run(app_, host=settings.host, port=settings.port, log_level="info",
                    **logs.uvicorn_options(settings.log_format))


@app.command(context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def beat(ctx: typer.Context) -> None:
    """Run Celery beat: it ticks the backup schedules (run exactly one per installation).

    Every option is Celery's (`celery beat --help`). A second beat would not double a
    backup (each fire time runs once), but would tick twice as often.
    """
    from worker.app import celery_app, run_celery

    settings = get_settings()
    _db(settings)
    state = settings.data_dir / "celerybeat-schedule"
    raise typer.Exit(run_celery(celery_app, ["beat", "--schedule", str(state), *ctx.args]))


@app.command(context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def worker(ctx: typer.Context) -> None:
    """Run a Celery worker; every option is Celery's (`dncq worker --help-celery`).

    With --pool gevent, --concurrency is how many machines it talks to at once.

    Example: dncq worker --pool gevent --concurrency 64 --loglevel INFO
    """
    from worker.app import celery_app, run_celery

    settings = get_settings()
    _db(settings)
    args = list(ctx.args)
    if "--help-celery" in args:
        args = ["--help"]
    if green.active():
        # With a prefetch of exactly one task per slot, a full gevent pool left kombu's
        # Redis poller with nothing to wait on, and it slept up to 1 s before looking
        # again (500 targets took 15 s instead of 2.7 s). On Redis, a worker now takes no
        # more than its pool can start and waits for a task's end instead
        # (jobs/run/redis_broker.py); on the file-backed queue the pool blocks the consumer
        # while every slot is busy. `--prefetch-multiplier` still decides when given.
        celery_app.conf.worker_prefetch_multiplier = 2
    # Celery's status, so that a worker that ended on an error is restarted by its service.
    raise typer.Exit(run_celery(celery_app, ["worker", *args]))


@app.command("secrets-key")
def secrets_key() -> None:
    """Print a new key for machine secrets (for DNCQ_SECRETS_KEY or the secrets-key file)."""
    from jobs.fleet import sealed

    print(sealed.new_key())


# -- files on one machine, through the API ------------------------------------------

DirOpt = Annotated[str | None, typer.Option("--dir", "-d", help="Folder (dirAtCNC)")]


def _params(**values: Any) -> dict[str, Any]:
    return {k: v for k, v in values.items() if v is not None}


@app.command()
def ls(machine: str, folder: Annotated[str | None, typer.Argument(help="dirAtCNC")] = None,
       recursive: Annotated[bool, typer.Option("-r", "--recursive")] = False) -> None:
    """List a folder of a machine (or every file below it with -r)."""
    if recursive:
        body = api_call("GET", "/api/cnc/readAllPrograms",
                    params=_params(machineID=machine, dirAtCNC=folder))
        for program in body["programs"]:
            out.print(f"{program['dirAtCNC']}\t{program['fileName']}", highlight=False)
        if not body["programs"]:  # else a folder with no file below it printed nothing at all
            out.print(f"No files below {folder or 'the root'}.", highlight=False)
        return
    body = api_call("GET", "/api/cnc/readProgramList", params=_params(machineID=machine,
                                                                 dirAtCNC=folder))
    out.print(body["dirAtCNC"] or "(root)", style="bold", highlight=False)
    for sub in body["subDirs"]:
        out.print(f"  {sub}/", style="blue", highlight=False)
    for program in body["programs"]:
        out.print(f"  {program}", highlight=False)
    if not body["subDirs"] and not body["programs"]:  # the folder's name alone read as a hang
        out.print("  (empty)", style="dim", highlight=False)


@app.command()
def get(machine: str, file_name: Annotated[str, typer.Argument(metavar="FILE")],
        output: OutputOpt = None, folder: DirOpt = None) -> None:
    """Download a file from a machine (streamed, any size)."""
    # Under its name's last part: the machine, not this side's folders, says what is wrong
    # with a name that has a folder in it (that belongs in --dir).
    target = saved_at(output, lambda: file_name)
    params = _params(machineID=machine, fileName=file_name, dirAtCNC=folder)
    download("/api/cnc/receiveFileStream", target, what=file_name, params=params)


@app.command()
def put(machine: str, path: Annotated[Path, typer.Argument(metavar="FILE",
                                                            callback=existing_file)],
        name: Annotated[str | None, typer.Option("--name", "-n",
                                                 help="Name on the machine")] = None,
        folder: DirOpt = None) -> None:
    """Send a file to a machine (never overwrites; Fanuc names it from its content)."""
    params = _params(machineID=machine, fileName=name or path.name, dirAtCNC=folder)
    try:
        with open(path, "rb") as f:
            api_call("POST", "/api/cnc/sendFileStream", params=params, content=_chunks(f))
    except KeyboardInterrupt:
        # dncq takes the whole body before it writes to the machine: a body cut short is
        # written nowhere, a whole one is sent on.
        err.print(f"\nStopped waiting. If all of {path.name} had reached dncq, it still goes "
                  f"to machine {machine} (dncq ls {machine} shows it); if not, nothing was "
                  "written.", highlight=False)
        raise
    out.print(f"Sent {path} to {machine}.")


def _chunks(f: Any) -> Any:
    while chunk := f.read(256 * 1024):
        yield chunk


@app.command()
def rm(machine: str, file_name: Annotated[str, typer.Argument(metavar="FILE")],
       folder: DirOpt = None,
       force: Annotated[bool, typer.Option(
           "--force", help="Delete even the running program")] = False
       ) -> None:
    """Delete a file from a machine."""
    params = _params(machineID=machine, fileName=file_name, dirAtCNC=folder,
                     force="true" if force else None)
    api_call("GET", "/api/cnc/deleteFile", params=params)
    out.print(f"Deleted {file_name} on {machine}.")


@app.command()
def find(machine: str, name: str, folder: DirOpt = None) -> None:
    """Find the folder of a file below a folder (subfolders too)."""
    body = api_call("GET", "/api/cnc/searchFile",
                params=_params(machineID=machine, fileName=name, dirAtCNC=folder))
    out.print(body["dirAtCNC"] or "(root)", highlight=False)


def main() -> None:
    """Entry point of the `dncq` console script."""
    from pydantic import ValidationError

    try:  # read once before any command: a bad setting is one line, not a traceback
        get_settings()
    except ValidationError as exc:
        from jobs.errors import validation_summary  # it loads the transports' errors

        raise SystemExit(fail(f"a setting is not valid: {validation_summary(exc.errors())} "
                              "(DNCQ_* variables, or the DNCQ_CONFIG_FILE)", code=2).exit_code
                         ) from None
    except ValueError as exc:  # the configuration file: missing, or not TOML
        raise SystemExit(fail(f"the settings cannot be read (DNCQ_CONFIG_FILE): {exc}",
                              code=2).exit_code) from None
    app()


if __name__ == "__main__":
    main()
