"""`dncq inbox ...`: programs machines sent, reviewed from the command line through the HTTP
API, and approved into the library or rejected."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.text import Text

from jobs.cli.common import api_call, download, fail, folded, listing, local_time, out, whole
from jobs.cli.help_names import Cli
from jobs.cli.library import _who

inbox_app = Cli(help="The inbox: programs machines sent, waiting for review.",
                        no_args_is_help=True)

ItemArg = Annotated[int, typer.Argument(metavar="ID", min=1, help="An inbox item's id")]
STATES = ("pending", "approved", "rejected", "failed")


def _state(state: str) -> Text:
    style = {"approved": "green", "pending": "yellow", "rejected": "red",
             "failed": "red"}.get(state, "")
    return Text(state, style=style)


@inbox_app.command("list")
def list_items(
    machine: Annotated[str | None, typer.Option("--machine", "-m", help="Only this machine")]
    = None,
    state: Annotated[str | None, typer.Option(
        "--state", "-s", help=f"Only in this state: {', '.join(STATES)}")] = None,
    limit: Annotated[int, typer.Option(min=1, max=1000, help="At most this many")] = 100,
) -> None:
    """List received programs, newest first."""
    if state is not None and state not in STATES:
        raise fail(f"--state is one of {', '.join(STATES)}", code=2)
    params: dict[str, Any] = {"limit": limit}
    if machine:
        params["machine"] = machine
    if state:
        params["state"] = state
    # Ids and times whole; a long program name folds onto the next line rather than be cut.
    table = listing(*whole("id", "machine", "received"), folded("program"),
                    "comment", "state", "outcome")
    for i in api_call("GET", "/api/inbox", params=params):
        became = f"v{i['libraryVersion']}" if i["libraryVersion"] else i["reason"]
        table.add_row(str(i["id"]), i["machineID"], local_time(i["receivedAt"]), i["path"],
                      i["comment"] or "", _state(i["state"]), became)
    out.print(table)


@inbox_app.command("show")
def show(item_id: ItemArg) -> None:
    """Show a received program: where and when it came from, and the library's copy."""
    i = api_call("GET", f"/api/inbox/{item_id}")
    out.print(Text.assemble(f"Inbox item {i['id']}: {i['path']} ", _state(i["state"])),
              highlight=False)
    rows = [("machine", i["machineID"]), ("received", local_time(i["receivedAt"])),
            ("program number", i["programNumber"] or "-"), ("comment", i["comment"] or "-"),
            ("size", f"{i['size']} bytes"), ("sha256", i["sha256"]),
            ("request job", i["jobID"] or "-")]
    if i["reason"]:
        rows.append(("reason", i["reason"]))
    if i["decidedBy"]:
        rows.append(("decided", f"{local_time(i['decidedAt'])} by {i['decidedBy']}"))
    if i["libraryVersion"]:
        rows.append(("became", f"{i['path']} v{i['libraryVersion']}"))
    good = i["approved"]
    rows.append(("library", f"approved v{good['version']} ({good['size']} bytes)" if good
                 else "no approved copy"))
    for label, value in rows:
        out.print(f"  {label:<15} {value}", highlight=False)


@inbox_app.command("diff")
def diff(item_id: ItemArg) -> None:
    """A unified diff from the library's approved copy to the received program."""
    download(f"/api/inbox/{item_id}/diff", Path("-"), what=f"the diff of inbox item {item_id}")


@inbox_app.command("approve")
def approve(
    item_id: ItemArg,
    as_: Annotated[str | None, typer.Option(
        "--as", metavar="FOLDER/NAME", help="Into this library program instead")] = None,
    note: Annotated[str, typer.Option(help="The version's note (default: its comment)")]
    = "",
) -> None:
    """Approve a received program: a new approved version in the library (the previous kept)."""
    request: dict[str, Any] = {"note": note}
    if as_ is not None:
        folder, slash, name = as_.strip().rpartition("/")
        if not slash or not folder or not name:
            raise fail(f"--as {as_!r} is not FOLDER/NAME (such as VIPROS/0010)", code=2)
        request.update(folder=folder, name=name)
    body = api_call("POST", f"/api/inbox/{item_id}/approve", params={"by": _who()},
                    json=request)
    number = body["version"]["version"]
    kept = f"; v1 to v{number - 1} kept" if number > 2 else "; v1 kept" if number == 2 else ""
    out.print(f"Inbox item {item_id} approved as {body['program']['path']} v{number}{kept}.",
              highlight=False)


@inbox_app.command("reject")
def reject(item_id: ItemArg,
           reason: Annotated[str, typer.Option(help="Why it is refused")] = "") -> None:
    """Refuse a received program; it is kept until pruned (inbox_rejected_keep_days)."""
    body = api_call("POST", f"/api/inbox/{item_id}/reject", params={"by": _who()},
                    json={"reason": reason})
    out.print(f"Inbox item {item_id} ({body['item']['path']}) rejected; kept until pruned.",
              highlight=False)


@inbox_app.command("prune")
def prune() -> None:
    """Remove programs rejected longer ago than inbox_rejected_keep_days."""
    body = api_call("POST", "/api/inbox/prune")
    out.print(f"Pruned {body['pruned']} programs rejected more than {body['keepDays']} days "
              "ago.", highlight=False)
