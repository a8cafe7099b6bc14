"""What every CLI module shares: consoles, errors, calls to the HTTP API."""

from __future__ import annotations

from pathlib import Path
from typing import Any
from urllib.parse import quote

import typer
from rich.console import Console
from rich.text import Text

from jobs.cli.client import ApiError, Client
from jobs.settings import get_settings

# Names, paths and messages come from machines and users: printed as they are, never read as
# Rich markup (a controller folder such as PRG\USER\ would escape a closing tag). Styles are
# given as arguments instead.
out = Console(markup=False, soft_wrap=True)  # a line too long wraps in the terminal, not in a log
err = Console(stderr=True, markup=False, soft_wrap=True)


def fail(message: str, code: int = 1) -> typer.Exit:
    """Print an error and return the exit to raise."""
    err.print(Text.assemble(("error:", "red"), f" {message}"), highlight=False)
    return typer.Exit(code)


def segment(value: str, what: str = "id") -> str:
    """An id as one path segment of an API URL: never empty, never a path of its own."""
    if not value.strip():
        raise fail(f"the {what} is empty", code=2)
    return quote(value, safe="")


def shown_database(url: str) -> str:
    """A database URL as the CLI prints it: its password hidden."""
    from sqlalchemy.engine import make_url

    return make_url(url).render_as_string(hide_password=True)


def existing_database() -> str:
    """The configured database's URL; refuses a SQLite file that is not there, as a command
    run in the wrong folder would otherwise make a new empty one."""
    url = get_settings().resolved_database_url
    path = url.removeprefix("sqlite:///")
    if url.startswith("sqlite:///") and not Path(path).is_file():
        raise fail(f"no dncq database at {path}: run this where dncq keeps its data, or set "
                   "DNCQ_DATA_DIR or DNCQ_DATABASE_URL")
    return url


def client() -> Client:
    """A client of the API at the configured URL, with the configured key."""
    return Client(get_settings())


def api_call(method: str, path: str, **kwargs: Any) -> Any:
    """One API call; a failure ends the command with its message and exit status 1."""
    with client() as c:
        try:
            return c.call(method, path, **kwargs)
        except ApiError as exc:
            raise fail(str(exc)) from None
