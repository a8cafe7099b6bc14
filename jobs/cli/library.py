"""`dncq library ...`: the program library from the command line, through the HTTP API.

Programs are written `FOLDER/NAME` (`VIPROS/0010`, `VIPROS/OLD/0010`).
"""

from __future__ import annotations

import getpass
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import quote

import typer
from rich.text import Text

from jobs.cli.common import (
    api_call,
    counted,
    download,
    existing_file,
    fail,
    listing,
    local_time,
    out,
    upload,
)
from jobs.cli.help_names import Cli

library_app = Cli(help="The program library: approved programs and their versions.",
                          no_args_is_help=True)

ProgramArg = Annotated[str, typer.Argument(metavar="FOLDER/NAME", help="e.g. VIPROS/0010")]
VersionArg = Annotated[int, typer.Argument(metavar="V", min=1, help="A version number")]


def _who() -> str:
    """Who runs the command, recorded with what it adds or decides."""
    try:
        return getpass.getuser()
    except (KeyError, OSError):  # no user name in a bare container
        return "cli"


def _path(program: str) -> str:
    """`FOLDER/NAME` as the URL path after a library route (each step quoted)."""
    folder, slash, name = program.strip().rpartition("/")
    if not slash or not folder or not name:
        raise fail(f"{program!r} is not FOLDER/NAME (such as VIPROS/0010)", code=2)
    return "/".join(quote(step, safe="") for step in program.split("/"))


def _state(state: str) -> Text:
    style = {"approved": "green", "pending": "yellow", "rejected": "red"}.get(state, "")
    return Text(state, style=style)


def _said(body: dict[str, Any], what: str) -> None:
    v = body["version"]
    if body.get("added", True):
        out.print(f"{body['program']['path']} v{v['version']} {what} ({v['state']}, "
                  f"{v['size']} bytes).", highlight=False)
    else:
        back = " back in the library," if body.get("restored") else ""
        out.print(f"{body['program']['path']}:{back} the same bytes as v{v['version']} "
                  f"({v['state']}); no new version.", highlight=False)


@library_app.command("add")
def add(
    file: Annotated[Path, typer.Argument(metavar="FILE", callback=existing_file)],
    folder: Annotated[str, typer.Option("--folder", "-f", help="Library folder (VIPROS)")],
    name: Annotated[str | None, typer.Option("--name", "-n", help="Default: the file's name")]
    = None,
    note: Annotated[str, typer.Option(help="Why this version")] = "",
    approve: Annotated[bool, typer.Option("--approve", help="Approve it at once")] = False,
) -> None:
    """Add a program to the library, or a new version of it (streamed, any size)."""
    body = upload("/api/library/programs", file, params={
        "folder": folder, "name": name or file.name, "note": note, "approve": approve,
        "by": _who()})
    _said(body, "added")


@library_app.command("list")
def list_programs(
    folder: Annotated[str | None, typer.Option("--folder", "-f", help="This folder and below")]
    = None,
    deleted: Annotated[bool, typer.Option("--deleted", help="Include deleted programs")]
    = False,
) -> None:
    """List the library's programs with their current and approved versions."""
    params: dict[str, Any] = {"deleted": deleted}
    if folder:
        params["folder"] = folder
    table = listing("program", "current", "state", "approved", "size", "added", "by")
    for p in api_call("GET", "/api/library/programs", params=params):
        cur, good = p["current"] or {}, p["approved"]
        name = p["path"] + (" (deleted)" if p["deleted"] else "")
        table.add_row(name, f"v{cur.get('version', '?')}", _state(cur.get("state", "")),
                      f"v{good['version']}" if good else "-", str(cur.get("size", "")),
                      local_time(cur.get("createdAt")), cur.get("createdBy", ""))
    out.print(table)


def _versions(title: str, versions: list[dict[str, Any]]) -> None:
    table = listing("v", "state", "size", "added", "by", "source", "note", "decided by",
                    title=title)
    for v in versions:
        table.add_row(str(v["version"]), _state(v["state"]), str(v["size"]),
                      local_time(v["createdAt"]), v["createdBy"], v["source"], v["note"],
                      v["decidedBy"] or "")
    out.print(table)


@library_app.command("show")
def show(program: ProgramArg) -> None:
    """Show a program and its versions."""
    p = api_call("GET", f"/api/library/programs/{_path(program)}")
    good = p["approved"]
    state = " (deleted)" if p["deleted"] else ""
    _versions(f"{p['path']}{state}: approved v{good['version'] if good else '-'}",
              p["versions"])
    found = p.get("analysis")
    if found:
        tools = ", ".join(f"T{t['tool']} (lines {t['firstLine']}-{t['lastLine']})"
                          for t in found["tools"]) or "none"
        out.print(f"Estimated cycle time {found['estimatedTime']}; tools {tools}"
                  + (f"; {found['programNumber']}" if found["programNumber"] else "")
                  + (f" {found['firstComment']}" if found["firstComment"] else ""),
                  highlight=False)
    for machine, ran in sorted(p.get("runs", {}).items()):
        last = ran["last"]
        out.print(f"Ran on {machine}: {ran['success']} succeeded, {ran['failure']} failed; "
                  f"last {local_time(last['date'])} {last['state']}",
                  highlight=False)
    for machine, count in sorted(p.get("sends", {}).items()):
        out.print(f"Sent to {machine}: {count} time{'s' if count != 1 else ''}",
                  highlight=False)


@library_app.command("history")
def history(program: ProgramArg) -> None:
    """Every version of a program, newest first, with who added it and why."""
    _versions(program, api_call("GET", f"/api/library/history/{_path(program)}"))


@library_app.command("diff")
def diff(program: ProgramArg,
         old: Annotated[int, typer.Argument(metavar="OLD", min=1, help="The version before")],
         new: Annotated[int, typer.Argument(metavar="NEW", min=1, help="The version after")]
         ) -> None:
    """A unified diff between two versions."""
    download(f"/api/library/diff/{_path(program)}", Path("-"), what=f"the diff of {program}",
             params={"old": old, "new": new})


@library_app.command("restore")
def restore(program: ProgramArg, version: VersionArg,
            approve: Annotated[bool, typer.Option("--approve", help="Approve it at once")]
            = False) -> None:
    """Make a new version with the bytes of an old one (noted "restore of vN")."""
    _said(api_call("POST", f"/api/library/restore/{_path(program)}",
                   params={"version": version, "approve": approve, "by": _who()}), "added")


@library_app.command("rm")
def remove(program: ProgramArg) -> None:
    """Delete a program from the library (its history is kept; adding it again goes on)."""
    p = api_call("DELETE", f"/api/library/programs/{_path(program)}")
    out.print(f"Deleted {p['path']}; its {p['current']['version']} versions are kept.",
              highlight=False)


@library_app.command("approve")
def approve(program: ProgramArg,
            version: Annotated[int | None, typer.Argument(
                metavar="V", min=1, help="Default: the current version")] = None) -> None:
    """Approve a version: the highest approved one is what rollouts and listings use."""
    params: dict[str, Any] = {"by": _who()}
    if version is not None:
        params["version"] = version
    _said(api_call("POST", f"/api/library/approve/{_path(program)}", params=params),
          "approved")


@library_app.command("reject")
def reject(program: ProgramArg, version: VersionArg) -> None:
    """Reject a version (kept for the record; sent only when asked for by number)."""
    _said(api_call("POST", f"/api/library/reject/{_path(program)}",
                   params={"version": version, "by": _who()}), "rejected")


@library_app.command("assign")
def assign(
    folder: Annotated[str, typer.Argument(metavar="FOLDER")],
    to: Annotated[str, typer.Option(
        "--to", metavar="IDS", help="Machine ids, comma-separated")],
    remove_: Annotated[bool, typer.Option("--remove", help="Take the folder from them")]
    = False,
) -> None:
    """Give machines the programs of a library folder (their `local` listing)."""
    ids = [m.strip() for m in to.split(",") if m.strip()]
    if not ids:
        raise fail("say which machines: --to ID[,ID...]", code=2)
    request = {"folder": folder, "machines": ids}
    if remove_:
        n = api_call("POST", "/api/library/assignments/remove", json=request)["removed"]
        out.print(f"Took {folder} from {counted(n, 'machine')}.", highlight=False)
        return
    made = api_call("POST", "/api/library/assignments", json=request)
    out.print(f"{folder} assigned to {', '.join(a['machineID'] for a in made)}.",
              highlight=False)


@library_app.command("assignments")
def assignments(machine: Annotated[str | None, typer.Option(help="Only this machine")]
                = None) -> None:
    """Which library folders each machine takes."""
    table = listing("machine", "folder", "since")
    for a in api_call("GET", "/api/library/assignments",
                      params={"machine": machine} if machine else None):
        table.add_row(a["machineID"], a["folder"], local_time(a["createdAt"]))
    out.print(table)
