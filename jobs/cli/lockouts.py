"""`dncq lockouts ...`: the client addresses locked out for wrong API keys, listed and
ended, through the HTTP API (an admin's key) or, on dncq's host, in its database."""

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

RECHECK_SHOWN_S = 10  # jobs.api.key_lockout.RECHECK_S, whose module loads the API

lockouts_app = Cli(help="Client addresses locked out for wrong API keys (admin).",
                   no_args_is_help=True)


@lockouts_app.command("list")
@lockouts_app.command("ls", hidden=True)
def list_lockouts() -> None:
    """The addresses locked out for wrong API keys, and those with wrong keys counted."""
    table = listing(*whole("address"), "wrong keys", "since", "state")
    for e in api_call("GET", "/api/lockouts"):
        state = f"locked until {local_time(e['lockedUntil'])}" if e["lockedUntil"] else \
            "counting"
        table.add_row(e["address"], str(e["failures"]), local_time(e["failedSince"]), state)
    out.print(table)


@lockouts_app.command("end")
def end_lockout(
    address: Annotated[str, typer.Argument(help="The address (an IPv6 one ends its /64's)")],
    local: Annotated[bool, typer.Option(
        "--local", help="Write dncq's database on its host instead of asking the API, "
        "which refuses every key from a locked address: the way when it is this one")
    ] = False,
) -> None:
    """End an address's lock-out for wrong API keys and forget its wrong keys."""
    if not local:
        ended = api_call("DELETE", f"/api/lockouts/{segment(address, 'address')}")
        out.print(f"Ended the lock-out of {ended['address']}: its keys are taken again.",
                  highlight=False)
        return
    from jobs import db
    from jobs.auth import audit, wrong_keys
    from jobs.errors import ContractError

    url = existing_database()
    db.upgrade(url)
    with db.session_scope(url) as session:
        try:
            ended = wrong_keys.end_lockout(session=session, address=address)
        except ContractError as exc:
            raise fail(exc.status_msg or str(exc)) from None
        audit.record_local(session=session, by=f"local:{getpass.getuser()}",
                           command="dncq lockouts end --local", action="lockouts.end",
                           target=ended.address)
    out.print(f"Ended the lock-out of {ended.address} in the database {shown_database(url)}: "
              f"every API process takes its keys again within {RECHECK_SHOWN_S} s.",
              highlight=False)


def register(app: typer.Typer) -> None:
    """Add the lockouts commands to the top-level CLI."""
    app.add_typer(lockouts_app, name="lockouts")
