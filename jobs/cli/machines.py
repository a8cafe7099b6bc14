"""`dncq machines import|list|show|check|rm|reseal`: the machine registry, through the API."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.text import Text

from jobs import folders
from jobs.cli.common import api_call, fail, listing, local_time, out, segment, shown_database, whole
from jobs.cli.help_names import Cli
from jobs.settings import get_settings

machines_app = Cli(help="The machine registry.", no_args_is_help=True)


def import_into_database(path: Path, database_url: str, session: Any, data_dir: Path) -> None:
    """Import the fleet file at `path` in `session`, saying how many were added and updated;
    secrets are sealed with the keys of `data_dir`."""
    from jobs.fleet import fleet_file

    try:
        parsed = fleet_file.parse_fleet(path.read_text())
        added, updated = fleet_file.import_fleet(session=session, machines=parsed,
                                                 data_dir=data_dir)
    except OSError as exc:
        raise fail(f"cannot read {path}: {exc.strerror}") from None
    except fleet_file.FleetFileError as exc:
        raise fail(str(exc)) from None
    out.print(f"Imported {path} into the database {shown_database(database_url)}: {added} added, "
              f"{updated} updated.", highlight=False)


@machines_app.command("import")
def machines_import(
    path: Annotated[Path, typer.Argument(help="Fleet file (YAML)")],
    direct: Annotated[bool, typer.Option(
        "--direct", help="Write into this host's database, for a host without a running dncq "
        "(DNCQ_DATA_DIR or DNCQ_DATABASE_URL say which)")] = False,
) -> None:
    """Add or update the machines of a fleet file; importing twice never duplicates."""
    if direct:
        from jobs import db

        settings = get_settings()
        url = settings.resolved_database_url
        folders.private_dir(settings.data_dir)
        db.upgrade(url)
        with db.session_scope(url) as session:
            import_into_database(path, url, session, settings.data_dir)
        return
    try:
        text = path.read_text()
    except OSError as exc:
        raise fail(f"cannot read {path}: {exc.strerror}") from None
    done = api_call("POST", "/api/machines/import", json={"fleet": text})
    out.print(f"Imported {path}: {done['added']} added, {done['updated']} updated.",
              highlight=False)


@machines_app.command("reseal")
def machines_reseal() -> None:
    """Seal every machine's secrets and schedule's alert URLs again with the first secrets
    key (after a new one), and mask the secrets in the messages stored of each machine.

    Opens this host's database (DNCQ_DATA_DIR or DNCQ_DATABASE_URL) and its keys directly:
    run it where the secrets key is.
    """
    from jobs import db, schedules
    from jobs.fleet import registry, scrub

    settings = get_settings()
    url = settings.resolved_database_url
    db.upgrade(url)
    with db.session_scope(url) as session:
        count = registry.reseal(session=session, data_dir=settings.data_dir)
        alerting = schedules.reseal(session=session, data_dir=settings.data_dir)
        masked = scrub.mask_stored(session=session, data_dir=settings.data_dir)
    out.print(f"Sealed the secrets of {count} machines and the alert URLs of {alerting} "
              f"schedules in the database {shown_database(url)} with the first key.",
              highlight=False)
    if masked:
        out.print(f"Masked a machine's secret in {masked} stored messages that still showed "
                  "one.", highlight=False)


@machines_app.command("list")
def machines_list(tag: Annotated[str | None, typer.Option(help="Only machines with this tag")]
                  = None) -> None:
    """List the registered machines."""
    found = api_call("GET", "/api/machines", params={"tag": tag} if tag else {})
    table = listing("id", "name", "model", "transport", "root", "max", "enabled", "tags")
    for m in found:
        table.add_row(m["id"], m["name"], m["model"], m["transport"], m["root"],
                      str(m["max_concurrent"]), "yes" if m["enabled"] else "no",
                      ", ".join(m["tags"]))
    out.print(table)


@machines_app.command("show")
def machines_show(machine_id: Annotated[str, typer.Argument(metavar="ID")]) -> None:
    """Show one machine (secrets masked) and what its model allows."""
    shown = api_call("GET", f"/api/machines/{segment(machine_id)}")
    roots, can = shown.pop("roots"), shown.pop("can")
    table = listing(show_header=False)
    for key, value in shown.items():
        table.add_row(key, _shown(value))
    table.add_row("roots", ", ".join(r or "(unnamed)" for r in roots))
    table.add_row("can", _can(can))
    out.print(table)


def _can(can: list[str]) -> str:
    """What a machine can do beyond its files, in words."""
    return ", ".join(can) or "files only"


def _shown(value: Any) -> str:
    """A field of the machine as the fleet file would write it: yes/no, lists with commas,
    settings one `name: value` a line; nothing for none."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, list):
        return ", ".join(_shown(v) for v in value)
    if isinstance(value, dict):
        return "\n".join(f"{k}: {_shown(v)}" for k, v in value.items())
    return str(value)


@machines_app.command("check")
def machines_check(
    machine_id: Annotated[str | None, typer.Argument(metavar="ID")] = None,
    all_: Annotated[bool, typer.Option("--all", help="Every machine")] = False,
) -> None:
    """Connect to machines and show whether they answer, how fast, and what they can do."""
    if not (machine_id or all_):
        raise fail("give a machine id or --all", code=2)
    found = api_call("POST", "/api/machines/check",
                     json={"all": True} if all_ else {"ids": [machine_id]})
    # Two tables: what was measured, then what each machine can do. In one, its ten columns
    # left a few letters a line to the names, models and capabilities at 80 columns.
    measured = listing(*whole("id"), "name", "reachable", *whole("latency", "heartbeat"),
                       *whole("programs", "free"))
    abilities = listing(*whole("id"), "model", "transport", "can")
    for f in found:
        measured.add_row(f["id"], f["name"], _reachable_cell(f),
                         f"{f['latency_ms']} ms" if f["latency_ms"] is not None else "",
                         _link_cell(f.get("link")),
                         str(f["programs"] if f["programs"] is not None else ""),
                         _free_cell(f.get("free_bytes")))
        abilities.add_row(f["id"], f["model"], f["transport"], _can(f["can"]))
    out.print(measured)
    out.print()
    out.print(abilities)
    if not all(f["reachable"] or (f.get("busy") and f["reachable"] is None) for f in found):
        raise typer.Exit(1)


def _reachable_cell(found: dict[str, Any]) -> Text:
    """yes, no and why; for a machine busy with other work, what its last check said."""
    if found.get("busy"):
        if found["reachable"] is None:
            return Text("busy", style="yellow")
        last = "yes" if found["reachable"] else "no"
        checked = local_time(found["checked_at"], seconds=True)
        return Text.assemble(("busy", "yellow"), f", last check {checked}: {last}")
    return Text("yes", style="green") if found["reachable"] else \
        Text.assemble(("no", "red"), f" {found['error']}")


def _free_cell(free: int | None) -> str:
    """Free space in the units a person reads (GiB above 1 GiB, else MiB)."""
    if free is None:
        return ""
    return f"{free / 1024**3:.1f} GiB" if free >= 1024**3 else f"{free / 1024**2:.0f} MiB"


def _link_cell(link: dict[str, Any] | None) -> Text:
    """A kept link's heartbeat: answered and its round trip, or not; empty without a link."""
    if link is None:
        return Text("")
    if link["heartbeat"]:
        return Text.assemble(("ok", "green"), f" {link['round_trip_ms']} ms")
    return Text.assemble(("no", "red"), f" {link['error'] or ''}".rstrip())


@machines_app.command("rm")
def machines_rm(machine_id: Annotated[str, typer.Argument(metavar="ID")]) -> None:
    """Remove a machine from the registry (its files are not touched)."""
    api_call("DELETE", f"/api/machines/{segment(machine_id)}")
    out.print(f"Removed machine {machine_id}.", highlight=False)
