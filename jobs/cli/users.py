"""`dncq users ...`, `dncq keys ...`, `dncq audit`: users, named API keys and the audit
trail, through the HTTP API (an admin's key)."""

from __future__ import annotations

import getpass
import sys
import warnings
from typing import Annotated, Any

import typer

from jobs.auth.roles import Role
from jobs.cli.client import ApiError
from jobs.cli.common import (
    SinceOpt,
    UntilOpt,
    api_call,
    client,
    err,
    existing_database,
    fail,
    folded,
    listing,
    local_time,
    out,
    refused,
    segment,
    shown_database,
    when,
    whole,
    writing_to_stdout,
)
from jobs.cli.help_names import Cli

users_app = Cli(help="Users of the dashboard, each with a role (admin).",
                        no_args_is_help=True)
keys_app = Cli(help="Named API keys, each with a role (admin).", no_args_is_help=True)


RoleOpt = Annotated[Role, typer.Option(
    "--role", "-r", metavar="ROLE", help="viewer, operator, programmer or admin",
    case_sensitive=False)]
MachinesOpt = Annotated[str | None, typer.Option(
    "--machines", "-m", metavar="IDS", help="May change only these machines (comma-separated ids); "
    "`all` for every machine")]


def _machines(value: str | None) -> list[str] | None:
    """The --machines value for the API: a list of ids, or None for all."""
    if value is None or value.strip().lower() == "all":
        return None
    return [m.strip() for m in value.split(",") if m.strip()]


def _shown_machines(machines: list[str] | None) -> str:
    return "all" if machines is None else (", ".join(machines) or "none")


def _password(from_stdin: bool) -> str:
    """A password from the first line of stdin, or typed twice without an echo."""
    if from_stdin:
        password = sys.stdin.readline().rstrip("\r\n")
    else:
        try:  # without a terminal, getpass would read it from stdin, echoed, with a warning
            with warnings.catch_warnings():
                warnings.simplefilter("error", getpass.GetPassWarning)
                password = typer.prompt("Password", hide_input=True, confirmation_prompt=True)
        except getpass.GetPassWarning:
            typer.echo()  # the prompt's line ends before the error is said
            raise fail("no terminal to type the password in: give it on stdin with "
                       "--password-stdin", code=2) from None
    if not password:
        raise fail("the password is empty", code=2)
    return password


PasswordStdinOpt = Annotated[bool, typer.Option(
    "--password-stdin", help="Read the password from the first line of stdin")]


@users_app.command("add")
def add_user(name: str, role: RoleOpt, machines: MachinesOpt = None,
             password_stdin: PasswordStdinOpt = False) -> None:
    """Add a user; the password is asked twice (or read from stdin)."""
    password = _password(password_stdin)
    user = api_call("POST", "/api/users", json={
        "name": name, "password": password, "role": role.value,
        "machines": _machines(machines)})
    out.print(f"User {user['name']}: {user['role']}, machines "
              f"{_shown_machines(user['machines'])}.")


@users_app.command("list")
@users_app.command("ls", hidden=True)  # as it was first spelled
def list_users() -> None:
    """Every user with its role and machines."""
    table = listing("name", "role", "machines", "state", "last sign-in")
    for u in api_call("GET", "/api/users"):
        state = "disabled" if u["disabled"] else (
            f"locked until {local_time(u['lockedUntil'])}" if u["lockedUntil"] else "active")
        table.add_row(u["name"], u["role"], _shown_machines(u["machines"]), state,
                      local_time(u["lastSignIn"]))
    out.print(table)


@users_app.command("set")
def set_user(
    name: str,
    role: Annotated[Role | None, typer.Option(
        "--role", "-r", metavar="ROLE", help="A new role: viewer, operator, programmer or admin",
        case_sensitive=False)] = None,
    machines: MachinesOpt = None,
    password: Annotated[bool, typer.Option(
        "--password", help="Set a new password (asked twice; ends a lock-out)")] = False,
    password_stdin: PasswordStdinOpt = False,
    disable: Annotated[bool, typer.Option("--disable", help="Refuse its sign-ins")] = False,
    enable: Annotated[bool, typer.Option("--enable", help="Allow its sign-ins again")] = False,
) -> None:
    """Change a user's role, machines or password; disable or enable it."""
    change: dict[str, Any] = {}
    if role is not None:
        change["role"] = role.value
    if machines is not None:
        change["machines"] = _machines(machines)
    if password or password_stdin:
        change["password"] = _password(password_stdin)
    if disable and enable:
        raise fail("--disable or --enable, not both", code=2)
    if disable or enable:
        change["disabled"] = disable
    if not change:
        raise fail("nothing to change: give --role, --machines, --password, --disable or "
                   "--enable", code=2)
    user = api_call("PATCH", f"/api/users/{segment(name, 'name')}", json=change)
    state = "disabled" if user["disabled"] else "enabled"
    out.print(f"User {user['name']}: {user['role']}, machines "
              f"{_shown_machines(user['machines'])}, {state}.")


@users_app.command("rm")
def remove_user(name: str) -> None:
    """Remove a user (the audit trail keeps what it did)."""
    api_call("DELETE", f"/api/users/{segment(name, 'name')}")
    out.print(f"Removed user {name}.")


@keys_app.command("add")
def add_key(name: str, role: RoleOpt, machines: MachinesOpt = None) -> None:
    """Make a named key; it is printed this once, and cannot be shown again."""
    key = api_call("POST", "/api/keys", json={"name": name, "role": role.value,
                                              "machines": _machines(machines)})
    err.print(f"Key {key['name']}: {key['role']}, machines {_shown_machines(key['machines'])}. "
              "Keep it now: it is not shown again.")
    print(key["key"])  # alone on stdout, for a script to take


@keys_app.command("list")
@keys_app.command("ls", hidden=True)
def list_keys(
    revoked: Annotated[bool, typer.Option("--revoked/--no-revoked",
                                          help="Show revoked keys too")] = True,
) -> None:
    """Every named key: its first characters, role, machines, last use (never the key)."""
    table = listing("name", "key", "role", "machines", "made by", "last used", "state")
    for k in api_call("GET", "/api/keys", params={"revoked": revoked}):
        state = f"revoked {local_time(k['revoked'])}" if k["revoked"] else "active"
        table.add_row(k["name"], k["prefix"] + "...", k["role"], _shown_machines(k["machines"]),
                      k["createdBy"] or "", local_time(k["lastUsed"]), state)
    out.print(table)


@keys_app.command("revoke")
def revoke_key(name: str) -> None:
    """Revoke a key: refused from now on."""
    api_call("DELETE", f"/api/keys/{segment(name, 'name')}")
    out.print(f"Revoked key {name}.")


audit_app = Cli(help="Who changed what, when, from where (admin).",
                        invoke_without_command=True, no_args_is_help=False)


AUDIT_SHOWN = 100  # events the table shows unless told


@audit_app.callback()
def audit(
    ctx: typer.Context,
    who: Annotated[str | None, typer.Option(
        help="Only this user, key (`key:NAME`), `admin-key` or `anonymous`")] = None,
    action: Annotated[str | None, typer.Option(
        help="Only this action (machines.put) or group (machines)")] = None,
    since: SinceOpt = None, until: UntilOpt = None,
    limit: Annotated[int | None, typer.Option(
        min=1, max=10_000, help="At most this many (default: 100; with --csv, every one)")
    ] = None,
    csv: Annotated[bool, typer.Option("--csv", help="Print CSV (all columns) instead")] = False,
) -> None:
    """Who changed what, when, from where: the audit trail, newest first (admin)."""
    if ctx.invoked_subcommand is not None:
        return
    params: dict[str, Any] = {}
    if limit is not None or not csv:  # the CSV is for keeping: every event unless told
        params["limit"] = limit or AUDIT_SHOWN
    for name, value in (("who", who), ("action", action), ("since", when(since)),
                        ("until", when(until))):
        if value is not None:
            params[name] = value
    if csv:
        with client() as c:
            try:
                answer = c.call_text("GET", "/api/audit.csv", params=params)
            except ApiError as exc:
                raise refused(exc) from None
        with writing_to_stdout():
            sys.stdout.write(answer)
        return
    # The action whole; a job's id folds onto the next line rather than be cut.
    table = listing(*whole("when"), "who", "from", *whole("action"),
                    folded("target"), *whole("status"))
    for e in api_call("GET", "/api/audit", params=params):
        table.add_row(local_time(e["at"], seconds=True), e["who"], e["address"] or "",
                      e["action"], e["target"] or "", str(e["status"]))
    out.print(table)


@audit_app.command("prune")
def audit_prune(older_than_days: Annotated[int | None, typer.Option(
        "--older-than-days", min=1, max=36500,
        help="Default: the audit_retention_days setting")] = None) -> None:
    """Remove audit events older than the retention period (local database).

    The pruning is itself recorded, with the system user who ran it.
    """
    import getpass
    from datetime import timedelta

    from jobs import db
    from jobs.auth import audit as trail
    from jobs.settings import get_settings

    days = older_than_days if older_than_days is not None else \
        get_settings().audit_retention_days
    url = existing_database()
    db.upgrade(url)
    with db.session_scope(url) as session:
        n = trail.prune(session=session, older_than=timedelta(days=days),
                        by=f"local:{getpass.getuser()}")
    out.print(f"Pruned {n} audit events older than {days} days from the database "
              f"{shown_database(url)}.", highlight=False)


def register(app: typer.Typer) -> None:
    """Add the users, keys and audit commands to the top-level CLI."""
    app.add_typer(users_app, name="users")
    app.add_typer(keys_app, name="keys")
    app.add_typer(audit_app, name="audit")
