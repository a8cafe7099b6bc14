"""`dncq lockouts ...`: the client addresses locked out for wrong API keys or for failed
dashboard sign-ins as admin, listed and ended, through the HTTP API (an admin's key) or, on
dncq's host, in its database."""

from __future__ import annotations

import getpass
from typing import Annotated

import typer

from jobs.cli.common import (
    api_call,
    existing_database,
    fail,
    listing,
    local_time,
    out,
    segment,
    shown_database,
    whole,
)
from jobs.cli.help_names import Cli

lockouts_app = Cli(help="Client addresses locked out for wrong API keys or for failed "
                        "sign-ins as admin (admin).",
                   no_args_is_help=True)


@lockouts_app.command("list")
@lockouts_app.command("ls", hidden=True)
def list_lockouts() -> None:
    """The addresses locked out for wrong API keys or failed sign-ins as admin, and those
    with failures counted."""
    table = listing(*whole("address"), "counted", "failures", "since", "state")
    for e in api_call("GET", "/api/lockouts"):
        state = f"locked until {local_time(e['lockedUntil'])}" if e["lockedUntil"] else \
            "counting"
        table.add_row(e["address"], e["counted"], str(e["failures"]),
                      local_time(e["failedSince"]), state)
    out.print(table)


@lockouts_app.command("end")
def end_lockout(
    address: Annotated[str, typer.Argument(help="The address (an IPv6 one ends its /64's)")],
    local: Annotated[bool, typer.Option(
        "--local", help="Write dncq's database on its host instead of asking the API, "
        "which refuses every key from a locked address: the way when it is this one")
    ] = False,
) -> None:
    """End an address's lock-outs (wrong API keys, failed sign-ins as admin) and forget its
    failures."""
    if not local:
        ended = api_call("DELETE", f"/api/lockouts/{segment(address, 'address')}")
        out.print(f"Ended the lock-out of {ended['address']} "
                  f"({_of([e['counted'] for e in ended['ended']])}): it is taken again.",
                  highlight=False)
        return
    from jobs import db
    from jobs.auth import audit, lockouts
    from jobs.errors import ContractError

    url = existing_database()
    db.upgrade(url)
    with db.session_scope(url) as session:
        try:
            counts = lockouts.end(session=session, address=address)
        except ContractError as exc:
            raise fail(exc.status_msg or str(exc)) from None
        audit.record_local(session=session, by=f"local:{getpass.getuser()}",
                           command="dncq lockouts end --local", action="lockouts.end",
                           target=counts[0].address)
    out.print(f"Ended the lock-out of {counts[0].address} ({_of([c.counted for c in counts])}) "
              f"in the database {shown_database(url)}: every API process takes its keys "
              f"again within {lockouts.RECHECK_S} s, the dashboard its sign-ins at once.",
              highlight=False)


def _of(counted: list[str]) -> str:
    return " and ".join(counted)


def register(app: typer.Typer) -> None:
    """Add the lockouts commands to the top-level CLI."""
    app.add_typer(lockouts_app, name="lockouts")
