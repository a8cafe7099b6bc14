"""What every CLI module shares: consoles, errors, calls to the HTTP API."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable, Iterator
from datetime import datetime
from pathlib import Path
from typing import Annotated, Any, NoReturn
from urllib.parse import quote

import httpx
import typer
from rich import box
from rich.console import Console
from rich.table import Column, Table
from rich.text import Text

from jobs.cli.client import ApiError, Client, checked, refuse_a_page, refuse_another_api
from jobs.local_times import local_text
from jobs.settings import get_settings

# Names, paths and messages come from machines and users: printed as they are, never read as
# Rich markup (a controller folder such as PRG\USER\ would escape a closing tag) nor as emoji
# codes (a file named FIX:100:.nc was shown as FIX💯.nc). Styles are given as arguments instead.
# Piped into grep or a file, a table is laid out as wide as its cells, never cut to a width
# no terminal has (Rich's 80 columns, or the columns of the terminal the pipe starts in).
PIPED_WIDTH = 10_000  # characters


def reader_gone() -> NoReturn:
    """End the command quietly, exit 0, once what reads stdout has closed it (`| head -1`
    has its line), as a Unix tool does; Python's recipe for it (the signal module's note on
    SIGPIPE): stdout goes to /dev/null, so that the flush at exit fails no more. SIGPIPE
    itself stays ignored: it would also end the command on a connection dncq drops."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    raise SystemExit(0)


class _Stdout(Console):
    """The console of stdout: a closed pipe ends the command with exit 0, where Rich's
    own ends it with exit 1, said nowhere."""

    def on_broken_pipe(self) -> None:
        self.quiet = True
        reader_gone()


@contextlib.contextmanager
def writing_to_stdout() -> Iterator[None]:
    """Around writes to sys.stdout itself (a file's bytes, a CSV): flushed at the end, and a
    reader that closed the pipe ends the command as `reader_gone` says."""
    try:
        yield
        sys.stdout.flush()
    except BrokenPipeError:
        reader_gone()


out = _Stdout(markup=False, emoji=False,
              soft_wrap=True,  # a line too long wraps in the terminal, not in a log
              width=None if sys.stdout.isatty() else PIPED_WIDTH)
err = Console(stderr=True, markup=False, emoji=False, soft_wrap=True)


WHEN_FORMATS = ["%Y-%m-%d", "%Y-%m-%dT%H:%M", "%Y-%m-%d %H:%M", "%Y-%m-%dT%H:%M:%S",
                "%Y-%m-%d %H:%M:%S"]


def _when(option: str) -> Callable[[str], datetime]:
    """The parser of a WHEN option: a value in none of the formats is one line of error, as
    the CLI's others are, not Click's box listing the five formats."""
    def parse(value: str) -> datetime:
        for form in WHEN_FORMATS:
            with contextlib.suppress(ValueError):
                return datetime.strptime(value, form)
        raise fail(f"{option} {value!r} is no date or time: give 2026-11-24 or "
                   "2026-11-24 14:00 (local)", code=2)
    return parse


# WHEN as the metavar: Click's own lists the five formats, which took six lines of --help.
SinceOpt = Annotated[datetime | None, typer.Option(
    parser=_when("--since"), metavar="WHEN",
    help="From this local date or time on (2026-11-24, 2026-11-24 14:00)")]
UntilOpt = Annotated[datetime | None, typer.Option(
    parser=_when("--until"), metavar="WHEN", help="Before this local date or time")]


def existing_file(path: Path | None) -> Path | None:
    """The callback of a FILE argument: a file that is not there, a folder or a file that
    cannot be read is one line of error, as the CLI's others are, not Click's box."""
    if path is None:
        return None
    if not path.is_file():
        raise fail(f"no file {path}" if not path.exists() else f"{path} is a folder, not a file",
                   code=2)
    if not os.access(path, os.R_OK):
        raise fail(f"cannot read {path}: permission denied", code=2)
    return path


def listing(*headers: str | Column, **options: Any) -> Table:
    """A table for the terminal: a rule under its header, columns apart by spaces, no box.

    A box's borders took 22 of an 80-column terminal's characters in a seven-column list
    (`dncq jobs`), and its cells wrapped to a few letters a line.
    """
    return Table(*headers, box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False,
                 padding=(0, 1, 0, 0), **options)


def whole(*headers: str) -> list[Column]:
    """Columns of a `listing` never wrapped nor cut: ids, states, times, measured figures;
    the other columns share what the terminal leaves."""
    return [Column(header, no_wrap=True) for header in headers]


def folded(header: str) -> Column:
    """A column of a `listing` whose long words (a program's name, a job's id) go on over
    the next line instead of being cut with an ellipsis."""
    return Column(header, overflow="fold")


def local_time(stamp: str | None, *, seconds: bool = False) -> str:
    """A time the API gives (ISO, UTC) as the CLI shows it: in local time, the time
    `--since` and `--until` take, to the minute (`2026-12-06 03:40 CET`) or the second,
    with its zone: in the hour the clocks go back, 02:30 CEST and 02:30 CET are an hour
    apart."""
    if not stamp:
        return ""
    moment = datetime.fromisoformat(stamp)
    if moment.tzinfo is None:  # no zone to name (dncq's API gives every time in UTC)
        return moment.strftime("%Y-%m-%d %H:%M:%S" if seconds else "%Y-%m-%d %H:%M")
    return local_text(moment, seconds=seconds)


def counted(n: int, noun: str) -> str:
    """`1 target`, `3 targets`: a count with its noun, in the plural where it needs one."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def when(value: datetime | None) -> str | None:
    """A --since/--until value for the API: the user's local time, with its offset."""
    return value.astimezone().isoformat() if value is not None else None


def fail(message: str, code: int = 1) -> typer.Exit:
    """Print an error and return the exit to raise."""
    err.print(Text.assemble(("error:", "red"), f" {message}"), highlight=False)
    return typer.Exit(code)


def refused(exc: ApiError, more: str = "") -> typer.Exit:
    """Print the API's refusal (and `more` after it) and return the exit to raise: 1, or
    LOCKED_OUT_EXIT for an address locked out for wrong keys. Never retried: each retry
    from a locked address is one more refusal."""
    return fail(f"{exc}{more}", code=exc.exit_code)


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


# What a Ctrl-C before dncq answered a change (an approval, a removal, a new schedule, user
# or key) may have left done; the commands that start or stop work say more.
MAYBE_CHANGED = ("If it had the whole request, the change was made all the same: list or "
                 "show what it changed to check.")


def api_call(method: str, path: str, *, if_it_got_there: str = MAYBE_CHANGED,
             **kwargs: Any) -> Any:
    """One API call; a failure ends the command with its message and exit status 1 (75 from
    an address locked out for wrong keys: `refused`).

    A Ctrl-C before dncq answered a request that changes something says that it may have
    been done all the same (`if_it_got_there`), exit 130; one while reading ends as any."""
    with client() as c:
        return api_call_on(c, method, path, if_it_got_there=if_it_got_there, **kwargs)


def api_call_on(c: Client, method: str, path: str, *, if_it_got_there: str = MAYBE_CHANGED,
                **kwargs: Any) -> Any:
    """`api_call` through a client already open, on its connection."""
    try:
        return c.call(method, path, **kwargs)
    except ApiError as exc:
        raise refused(exc) from None
    except KeyboardInterrupt:
        if method.upper() in ("GET", "HEAD"):
            raise
        raise stopped_before_the_answer(if_it_got_there) from None


def stopped_before_the_answer(if_it_got_there: str) -> typer.Exit:
    """Say that a Ctrl-C cut the wait for dncq's answer, not the work it was asked for;
    the exit to raise (130, as for any Ctrl-C)."""
    err.print(f"\nStopped before dncq answered. {if_it_got_there}", highlight=False)
    return typer.Exit(130)


# A str, not a Path: a Path drops the trailing / that says the output is a folder to make.
OutputOpt = Annotated[str | None, typer.Option(
    "-o", "--output", metavar="PATH",
    help="Where to write (a file, or a folder: one ending in / is made); - for stdout")]


def saved_at(output: str | None, name: Callable[[], str]) -> Path:
    """Where a download given `-o output` is saved: that file, `-` (stdout), or a folder
    (one there, the current one, or one ending in /, which `download` makes once the
    answer is the file: a refusal makes none) under `name()`'s last part.

    `name` is asked only for a folder.
    """
    output = output or "."
    target = Path(output)
    if output != "-" and (target.is_dir() or output.endswith(("/", os.sep))):
        return target / Path(name()).name
    if output != "-" and not target.parent.is_dir():
        raise fail(f"no folder {target.parent} to save into", code=2)
    return target


UPLOAD_CHUNK_BYTES = 256 * 1024


def upload(path: str, file: Path, *, params: dict[str, Any] | None = None) -> Any:
    """POST a file as the raw body, streamed (any size), with a bar of its bytes; the answer.

    A file over the API's limit of a stream is refused before a byte of it is read. The
    limit is asked on the connection the file then goes on: one connection, not two."""
    size_bytes = file.stat().st_size
    with client() as c:
        try:
            c.refuse_over_the_limit(size_bytes, limit="maxStreamBodyBytes")
        except ApiError as exc:
            raise refused(exc) from None
        with _bar("upload", size_bytes) as shown:

            def chunks() -> Iterator[bytes]:
                done_bytes = 0
                with open(file, "rb") as source:
                    while chunk := source.read(UPLOAD_CHUNK_BYTES):
                        done_bytes += len(chunk)
                        shown(done_bytes)
                        yield chunk

            return api_call_on(c, "POST", path, content=chunks(), params=params,
                               headers={"content-type": "application/octet-stream"})


def download(path: str, target: Path, *, what: str, params: dict[str, Any] | None = None) -> None:
    """Stream a GET's body into `target` (`-`: stdout): whole, or not at all.

    The bytes go to `<target>.part` and are renamed into place once complete, so a broken
    download or a full disk leaves no half file; an error the API answers in JSON ends the
    command with its message.
    """
    with client() as c, _streamed(c, path, params) as response:
        try:
            refuse_a_page(response)
            refuse_another_api(response)
        except ApiError as exc:
            raise refused(exc) from None
        if response.headers.get("content-type", "").startswith("application/json"):
            response.read()
            try:
                checked(response, key_hint=c.key_hint)
            except ApiError as exc:
                raise refused(exc) from None
        if response.is_error:
            response.read()
            raise fail(f"HTTP {response.status_code}: {response.text[:200]}")
        if str(target) == "-":
            with writing_to_stdout():
                for chunk in response.iter_bytes():
                    sys.stdout.buffer.write(chunk)
            return
        part = target.with_name(target.name + ".part")
        try:
            target.parent.mkdir(parents=True, exist_ok=True)  # a folder -o named with a /
        except OSError as exc:  # a file of that name, no permission
            raise fail(f"cannot make the folder {target.parent}: {exc.strerror or exc}") from None
        try:
            with open(part, "wb") as f, _bar("download", _length(response)) as shown:
                for chunk in response.iter_bytes():
                    f.write(chunk)
                    shown(response.num_bytes_downloaded)
            part.replace(target)
        except OSError as exc:  # a full disk, a folder in the way: no half file left
            part.unlink(missing_ok=True)
            raise fail(f"cannot save {target}: {exc.strerror or exc}") from None
        except httpx.HTTPError as exc:  # the download was cut short: nothing saved
            part.unlink(missing_ok=True)
            raise fail(f"the download of {what} broke off: {exc}") from None
        except KeyboardInterrupt:  # Ctrl-C: nothing saved either, and said so
            part.unlink(missing_ok=True)
            err.print(f"\nStopped: {target} was not saved.", highlight=False)
            raise
    err.print(f"Saved {target}")


def _length(response: httpx.Response) -> int | None:
    """The body's size in bytes when the answer says it (a machine's file whose size its
    listing gives); else None, and the bar counts the bytes without an end."""
    length = response.headers.get("content-length", "")
    return int(length) if length.isdecimal() else None


@contextlib.contextmanager
def _bar(label: str, total_bytes: int | None) -> Iterator[Callable[[int], None]]:
    """A bar of a transfer's bytes on stderr, gone at its end; given the bytes done so far.

    On a terminal only: into a log or a pipe (stdout or stderr), a bar redrawn in place
    would leave its frames or a blank line behind.
    """
    from rich.progress import (
        BarColumn,
        DownloadColumn,
        Progress,
        TextColumn,
        TransferSpeedColumn,
    )

    with Progress(TextColumn(label), BarColumn(), DownloadColumn(), TransferSpeedColumn(),
                  console=err, transient=True,
                  disable=not (err.is_terminal and out.is_terminal)) as bar:
        task = bar.add_task(label, total=total_bytes)
        yield lambda done_bytes: bar.update(task, completed=done_bytes)


@contextlib.contextmanager
def _streamed(c: Client, path: str, params: dict[str, Any] | None) -> Iterator[httpx.Response]:
    """A streamed GET; dncq not answering ends the command naming where the CLI looked."""
    try:
        with c.stream("GET", path, params=params) as response:
            yield response
    except ApiError as exc:
        raise refused(exc) from None
