"""The `dncq` command: run the service, manage the registry, move files (Typer + Rich)."""

from __future__ import annotations

import sys

if sys.argv[1:2] == ["worker"]:  # before any other import (see jobs.run.green)
    from jobs.run import green

    green.patch(sys.argv)

import logging  # noqa: E402
from pathlib import Path
from typing import Annotated, Any

import httpx
import typer
from rich.table import Table
from rich.text import Text

from jobs import db
from jobs.cli import backups as cli_backups
from jobs.cli import jobs as cli_jobs
from jobs.cli import schedules as cli_schedules
from jobs.cli.client import ApiError, checked
from jobs.cli.common import api_call, client, err, fail, out
from jobs.fleet import registry
from jobs.run import green
from jobs.settings import AuthMode, Settings, get_settings

app = typer.Typer(help="dncq: file transfer, batch rollout and backup for CNC fleets.",
                  no_args_is_help=True, pretty_exceptions_enable=False)
machines_app = typer.Typer(help="The machine registry.", no_args_is_help=True)
app.add_typer(machines_app, name="machines")
cli_jobs.register(app)
app.add_typer(cli_backups.backup_app, name="backup")
app.add_typer(cli_schedules.schedule_app, name="schedule")


def _db(settings: Settings) -> str:
    url = settings.resolved_database_url
    db.upgrade(url)
    return url


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
    from jobs.fleet import demo

    settings = _settings(host=host, port=port)
    url = _db(settings)
    with db.session_scope(url) as session:
        if fleet is not None:
            _import(session, fleet)
        elif not registry.list_all(session=session):
            count = demo.create(session=session, data_dir=settings.data_dir)
            out.print(f"Created a demo fleet of {count} simulated machines "
                      f"(data in {settings.data_dir}/).")
    _run_api(settings, announce=True, embedded_worker=True)


@app.command()
def api(
    host: Annotated[str | None, typer.Option(help="Listen address")] = None,
    port: Annotated[int | None, typer.Option(help="Listen port")] = None,
) -> None:
    """Run the HTTP API alone (distributed mode: workers run with `dncq worker`)."""
    settings = _settings(host=host, port=port)
    _db(settings)
    _run_api(settings, announce=False)


def _settings(**overrides: Any) -> Settings:
    base = get_settings()
    changes = {k: v for k, v in overrides.items() if v is not None}
    return base.model_copy(update=changes) if changes else base


def _run_api(settings: Settings, *, announce: bool, embedded_worker: bool = False) -> None:
    import uvicorn

    from jobs.api.app import MissingApiKey, create_app

    logging.basicConfig(level=logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    key = settings.effective_api_key(create=announce)
    try:
        app_ = create_app(settings)
    except MissingApiKey as exc:  # say so without a traceback
        raise fail(str(exc)) from None
    out.print(f"dncq listening on http://{settings.host}:{settings.port}  "
              f"(API docs: http://{settings.host}:{settings.port}/docs)")
    if settings.auth is AuthMode.NONE:
        out.print("Authentication is off (DNCQ_AUTH=none).", style="yellow")
    elif announce and settings.api_key is None and key:
        # Its first letters only: this output often ends up in a log.
        out.print(f"API key: {key[:3]}…  (kept in {settings.data_dir}/api-key; "
                  "send it as the X-Api-Key header)")
    if embedded_worker:
        from worker import embedded

        embedded.run(settings, app_)
    else:
        uvicorn.run(app_, host=settings.host, port=settings.port, log_level="info")


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
        # With a prefetch of exactly one task per slot, a full gevent pool leaves kombu's
        # Redis poller with nothing to wait on, and it sleeps up to 1 s before looking
        # again (500 targets took 15 s instead of 2.7 s). The pool blocks the consumer
        # while every slot is busy, so a second task per slot is never actually taken.
        # `--prefetch-multiplier` still decides when given.
        celery_app.conf.worker_prefetch_multiplier = 2
    # Celery's status, so that a worker that ended on an error is restarted by its service.
    raise typer.Exit(run_celery(celery_app, ["worker", *args]))


# -- the registry -----------------------------------------------------------------


def _import(session: Any, path: Path) -> None:
    try:
        parsed = registry.parse_fleet(path.read_text())
        added, updated = registry.import_fleet(session=session, machines=parsed)
    except OSError as exc:
        raise fail(f"cannot read {path}: {exc.strerror}") from None
    except registry.FleetFileError as exc:
        raise fail(str(exc)) from None
    out.print(f"Imported {path}: {added} added, {updated} updated.")


@machines_app.command("import")
def machines_import(path: Annotated[Path, typer.Argument(help="Fleet file (YAML)")]) -> None:
    """Add or update the machines of a fleet file; importing twice never duplicates."""
    settings = get_settings()
    with db.session_scope(_db(settings)) as session:
        _import(session, path)


@machines_app.command("list")
def machines_list(tag: Annotated[str | None, typer.Option(help="Only machines with this tag")]
                  = None) -> None:
    """List the registered machines."""
    settings = get_settings()
    with db.session_scope(_db(settings)) as session:
        specs = registry.list_all(session=session, tag=tag)
    table = Table("id", "name", "model", "transport", "root", "max", "enabled", "tags")
    for spec in specs:
        shown = spec.public()
        table.add_row(spec.id, spec.name, spec.model, spec.transport, shown["root"],
                      str(spec.max_concurrent), "yes" if spec.enabled else "no",
                      ", ".join(spec.tags))
    out.print(table)


@machines_app.command("show")
def machines_show(machine_id: Annotated[str, typer.Argument(metavar="ID")]) -> None:
    """Show one machine (secrets masked) and what its model allows."""
    settings = get_settings()
    with db.session_scope(_db(settings)) as session:
        try:
            spec = registry.get(session=session, machine_id=machine_id)
        except Exception as exc:
            raise fail(str(exc)) from None
    table = Table(show_header=False)
    for key, value in spec.public().items():
        table.add_row(key, str(value))
    table.add_row("roots", ", ".join(r or "(unnamed)" for r in registry.governing_row(spec).roots))
    table.add_row("can", ", ".join(registry.abilities(spec)) or "files only")
    out.print(table)


@machines_app.command("check")
def machines_check(
    machine_id: Annotated[str | None, typer.Argument(metavar="[ID]")] = None,
    all_: Annotated[bool, typer.Option("--all", help="Every machine")] = False,
) -> None:
    """Connect to machines and show whether they answer, how fast, and what they can do."""
    from concurrent.futures import ThreadPoolExecutor

    if not (machine_id or all_):
        raise fail("give a machine id or --all", code=2)
    settings = get_settings()
    with db.session_scope(_db(settings)) as session:
        try:
            specs = ([registry.get(session=session, machine_id=machine_id)] if machine_id
                     else registry.list_all(session=session))
        except Exception as exc:
            raise fail(str(exc)) from None
    with ThreadPoolExecutor(16) as pool:
        found = list(pool.map(lambda s: registry.check(s, data_dir=settings.data_dir), specs))
    table = Table("id", "name", "transport", "model", "reachable", "latency", "programs", "can")
    for f in found:
        state = Text("yes", style="green") if f["reachable"] else \
            Text.assemble(("no", "red"), f" {f['error']}")
        table.add_row(f["id"], f["name"], f["transport"], f["model"], state,
                      f"{f['latency_ms']} ms" if f["latency_ms"] is not None else "",
                      str(f["programs"] if f["programs"] is not None else ""),
                      ", ".join(f["can"]))
    out.print(table)
    if not all(f["reachable"] for f in found):
        raise typer.Exit(1)


@machines_app.command("rm")
def machines_rm(machine_id: Annotated[str, typer.Argument(metavar="ID")]) -> None:
    """Remove a machine from the registry (its files are not touched)."""
    settings = get_settings()
    with db.session_scope(_db(settings)) as session:
        try:
            registry.delete(session=session, machine_id=machine_id)
        except Exception as exc:
            raise fail(str(exc)) from None
    out.print(f"Removed machine {machine_id}.")


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
        return
    body = api_call("GET", "/api/cnc/readProgramList", params=_params(machineID=machine,
                                                                 dirAtCNC=folder))
    out.print(body["dirAtCNC"] or "(root)", style="bold", highlight=False)
    for sub in body["subDirs"]:
        out.print(f"  {sub}/", style="blue", highlight=False)
    for program in body["programs"]:
        out.print(f"  {program}", highlight=False)


@app.command()
def get(machine: str, file_name: Annotated[str, typer.Argument(metavar="FILE")],
        output: Annotated[Path | None, typer.Option("-o", "--output",
                                                    help="Where to write; - for stdout")] = None,
        folder: DirOpt = None) -> None:
    """Download a file from a machine (streamed, any size)."""
    target = output or Path(file_name)
    if target.is_dir():  # into that folder, under the file's own name
        target = target / Path(file_name).name
    if str(target) != "-" and not target.parent.is_dir():
        raise fail(f"no folder {target.parent} to save into", code=2)
    params = _params(machineID=machine, fileName=file_name, dirAtCNC=folder)
    with client() as c, c.http.stream("GET", "/api/cnc/receiveFileStream",
                                                 params=params) as response:
        if response.headers.get("content-type", "").startswith("application/json"):
            response.read()
            try:
                checked(response)
            except ApiError as exc:
                raise fail(str(exc)) from None
        if response.is_error:
            response.read()
            raise fail(f"HTTP {response.status_code}: {response.text[:200]}")
        if str(target) == "-":
            for chunk in response.iter_bytes():
                sys.stdout.buffer.write(chunk)
            return
        part = target.with_name(target.name + ".part")
        try:
            with open(part, "wb") as f:
                for chunk in response.iter_bytes():
                    f.write(chunk)
            part.replace(target)
        except OSError as exc:  # a full disk, a folder in the way: no half file left
            part.unlink(missing_ok=True)
            raise fail(f"cannot save {target}: {exc.strerror or exc}") from None
        except httpx.HTTPError as exc:  # the download was cut short: nothing saved
            part.unlink(missing_ok=True)
            raise fail(f"the download of {file_name} broke off: {exc}") from None
    err.print(f"Saved {target}")


@app.command()
def put(machine: str, path: Annotated[Path, typer.Argument(metavar="FILE", exists=True,
                                                            dir_okay=False)],
        name: Annotated[str | None, typer.Option("--name", "-n",
                                                 help="Name on the machine")] = None,
        folder: DirOpt = None) -> None:
    """Send a file to a machine (never overwrites; Fanuc names it from its content)."""
    params = _params(machineID=machine, fileName=name or path.name, dirAtCNC=folder)
    with open(path, "rb") as f:
        api_call("POST", "/api/cnc/sendFileStream", params=params, content=_chunks(f))
    out.print(f"Sent {path} to {machine}.")


def _chunks(f: Any) -> Any:
    while chunk := f.read(256 * 1024):
        yield chunk


@app.command()
def rm(machine: str, file_name: Annotated[str, typer.Argument(metavar="FILE")],
       folder: DirOpt = None,
       force: Annotated[bool, typer.Option(help="Delete even the running program")] = False
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
    app()


if __name__ == "__main__":
    main()
