"""`dncq send FILE`: the file streamed into the job request, never held whole in memory."""

from __future__ import annotations

import base64
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from jobs import db
from jobs.api.app import create_app
from jobs.auth import audit
from jobs.cli import json_body
from jobs.cli.client import Client
from jobs.cli.json_body import BASE64_PIECE_BYTES, FileBody, FileChanged
from jobs.settings import get_settings
from tests.jobs.cli.runner import dncq
from tests.live_server import serving

LARGE_BYTES = 100 * 1024 * 1024  # five times the API's default limit of a JSON body
# What the command itself takes (Python, httpx, Rich): about 60 MB. Reading the file whole,
# then its Base64 as bytes, as text and as JSON took over 500 MB for LARGE_BYTES.
MAX_RSS_KB = 150 * 1024


@pytest.mark.parametrize("size_bytes", [0, 1, 2, 3, 4, BASE64_PIECE_BYTES + 1,
                                        2 * BASE64_PIECE_BYTES + 2])
def test_the_streamed_body_is_the_json_of_the_request_with_the_files_base64(
        tmp_path: Path, size_bytes: int) -> None:
    file = tmp_path / "P.nc"
    file.write_bytes(os.urandom(size_bytes))
    request = {"kind": "send", "fileName": "P\u00e9.nc", "machines": {"ids": ["m0"]}}

    body = FileBody(request, key="base64", file=file)
    sent = b"".join(body)

    assert len(sent) == body.length_bytes
    assert json.loads(sent) == {**request, "base64": base64.b64encode(file.read_bytes()).decode()}


def test_a_file_that_shrinks_while_it_is_sent_ends_the_body_with_an_error(tmp_path) -> None:
    file = tmp_path / "P.nc"
    file.write_bytes(b"x" * (BASE64_PIECE_BYTES + 10))
    body = iter(FileBody({}, key="base64", file=file))
    next(body), next(body)
    file.write_bytes(b"")

    with pytest.raises(FileChanged):
        list(body)


def test_a_file_that_grows_while_it_is_sent_ends_the_body_with_an_error_not_cut_short(
        tmp_path) -> None:
    """A post-processor still writing it: the bytes past its first size would be lost."""
    file = tmp_path / "P.nc"
    file.write_bytes(b"x" * (BASE64_PIECE_BYTES + 10))
    body = iter(FileBody({}, key="base64", file=file))
    next(body), next(body)
    with open(file, "ab") as more:
        more.write(b"G0 X0\nM30\n")

    with pytest.raises(FileChanged, match="grew"):
        list(body)


def test_send_of_a_file_whose_size_says_nothing_queues_nothing(elsewhere) -> None:
    """/proc's files say 0 bytes and hold more: dncq queued them empty."""
    done = subprocess.run([sys.executable, "-m", "jobs.cli", "send", "/proc/self/status",
                           "--to", "m0"], capture_output=True, text=True, timeout=120)

    assert done.returncode == 1
    assert "grew while it was sent; nothing was queued" in " ".join(done.stderr.split())


# Runs the command given and prints its peak memory (kB) and exit status. The command is
# forked from this small process: forked from the tests' own, it would count their memory.
PEAK_OF = ("import os, subprocess, sys\n"
           "command = subprocess.Popen(sys.argv[1:])\n"
           "_, status, usage = os.wait4(command.pid, 0)\n"
           "print(usage.ru_maxrss, os.waitstatus_to_exitcode(status))")


def test_send_of_a_file_over_the_limit_is_refused_in_little_memory(elsewhere) -> None:
    large = elsewhere / "LARGE.NC"
    with open(large, "wb") as f:
        f.truncate(LARGE_BYTES)  # sparse: read as zeros, written in no time

    done = subprocess.run([sys.executable, "-c", PEAK_OF, sys.executable, "-m", "jobs.cli",
                           "send", str(large), "--to", "m0"],
                          capture_output=True, text=True, timeout=120)
    peak_kb, status = map(int, done.stdout.split())
    said = " ".join(done.stderr.split())

    assert status == 1, said
    assert "20013" in said and "dncq library add FILE --folder FOLDER --approve" in said
    assert peak_kb < MAX_RSS_KB  # kilobytes, on Linux


SMALL_LIMIT_BYTES = 2048  # the JSON body's limit of the dncq these tests serve


@pytest.fixture
def small_limit(settings, env, monkeypatch):
    """The CLI against a dncq whose JSON bodies are limited to SMALL_LIMIT_BYTES; yields its
    settings."""
    small = settings.model_copy(update={"max_json_body_bytes": SMALL_LIMIT_BYTES})
    with serving(create_app(small)) as server:
        monkeypatch.setenv("DNCQ_URL", server.url)
        get_settings.cache_clear()
        yield small


def _refused(said: str) -> str:
    """The refusal's sentence of what `dncq send` said, on one line."""
    return " ".join(said.split()).partition("; a send job")[0]


def test_send_of_a_file_over_the_limit_is_refused_before_it_is_read_or_sent(
        small_limit, tmp_path, monkeypatch) -> None:
    # A file over the limit was sent whole (419 MB for a 300 MB file over a 1 MB limit), to
    # be refused from its length only once it had all come in.
    large = tmp_path / "LARGE.NC"
    large.write_bytes(b"G0 X0\n" * 1000)

    def unreadable(*_: object, **__: object) -> None:
        raise AssertionError("the file was read to be sent")

    monkeypatch.setattr(json_body, "open", unreadable, raising=False)
    result = dncq("send", str(large), "--to", "m0")

    assert result.exit_code == 1
    assert _refused(result.output) == (
        f"error: 20013 Request body is too large: request body over {SMALL_LIMIT_BYTES} bytes")
    assert "dncq library add FILE --folder FOLDER --approve" in " ".join(result.output.split())
    with db.session_scope(small_limit.resolved_database_url) as session:
        assert [e.path for e in audit.list_events(session=session)] == []  # no POST reached it


def test_send_to_a_dncq_that_names_no_limits_is_refused_by_it_in_the_same_words(
        small_limit, tmp_path, monkeypatch) -> None:
    large = tmp_path / "LARGE.NC"
    large.write_bytes(b"G0 X0\n" * 1000)
    before = _refused(dncq("send", str(large), "--to", "m0").output)
    call = Client.call

    def older_dncq(self: Client, method: str, path: str, **kwargs: object) -> object:
        answer = call(self, method, path, **kwargs)
        if path == "/api/health":
            answer.pop("limits")  # as a dncq before the limits were in its health answers
        return answer

    monkeypatch.setattr(Client, "call", older_dncq)
    result = dncq("send", str(large), "--to", "m0")

    assert result.exit_code == 1
    assert _refused(result.output) == before
    with db.session_scope(small_limit.resolved_database_url) as session:
        assert [(e.method, e.path, e.status) for e in audit.list_events(session=session)] == [
            ("POST", "/api/jobs", 413)]  # sent, and refused by dncq
