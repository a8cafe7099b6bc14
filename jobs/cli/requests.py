"""`dncq requests ...`: what machines' operators may ask from the control, through the API."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer
import yaml

from jobs.cli.common import api_call, existing_file, fail, listing, out, segment
from jobs.cli.help_names import Cli

requests_app = Cli(help="Requests operators send from the control (and auto-receive).",
                           no_args_is_help=True)

MachineArg = Annotated[str, typer.Argument(metavar="MACHINE", help="Machine id")]


@requests_app.command("show")
def show(machine: MachineArg) -> None:
    """Show the machine's request settings: its controller's preset with its own over it."""
    body = api_call("GET", f"/api/machines/{segment(machine)}/requests")
    out.print(yaml.safe_dump(body["settings"], sort_keys=False, allow_unicode=True).rstrip(),
              highlight=False)
    if not body["given"]:
        out.print("# none given: the preset as it is (off until `enabled: true`)",
                  highlight=False)


@requests_app.command("set")
def set_(machine: MachineArg,
         file: Annotated[Path, typer.Argument(metavar="FILE", callback=existing_file,
                                              help="YAML or JSON of the settings to give")],
         ) -> None:
    """Give the machine request settings (over its controller's preset); replaces earlier ones."""
    try:
        given = yaml.safe_load(file.read_text()) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise fail(f"{file}: not YAML or JSON: {exc}", code=2) from None
    if not isinstance(given, dict):
        raise fail(f"{file}: the settings are a mapping (enabled: true, sources: [...])", code=2)
    body = api_call("PUT", f"/api/machines/{segment(machine)}/requests", json=given)
    state = "on" if body["settings"]["enabled"] else "off"
    out.print(f"machine {body['machineID']}: requests {state}.", highlight=False)


@requests_app.command("test")
def test(machine: MachineArg,
         file: Annotated[Path, typer.Argument(metavar="FILE", callback=existing_file,
                                              help="A program as the control would send it")],
         as_json: Annotated[bool, typer.Option("--json", help="The rows as JSON")] = False,
         ) -> None:
    """Show what a received text would trigger: command, body, file name, action (nothing done)."""
    text = file.read_bytes().decode("latin-1")
    body = api_call("POST", f"/api/machines/{segment(machine)}/requests/test",
                    json={"text": text})
    rows: list[dict[str, Any]] = body["rows"]
    if as_json:
        out.print(json.dumps(rows, indent=2, default=str), highlight=False)
        return
    if not body["enabled"]:  # the rows alone read as if the request would run
        out.print(f"requests are off on machine {body['machineID']} (enabled: false): what it "
                  "sends triggers none of this. Turn them on with enabled: true in its "
                  f"settings (dncq requests set {body['machineID']} FILE.yaml, or the fleet "
                  "file's requests:).", style="yellow", highlight=False)
    if not rows:
        out.print("nothing: the text holds no request and no program", highlight=False)
        return
    columns = list(dict.fromkeys(k for row in rows for k in row))
    table = listing(*columns)
    for row in rows:
        table.add_row(*("" if row.get(c) is None else str(row.get(c)) for c in columns))
    out.print(table)
