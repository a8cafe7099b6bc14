"""`dncq send FILE`: the file streamed into the job request, never held whole in memory."""

from __future__ import annotations

import base64
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from jobs.cli.json_body import BASE64_PIECE_BYTES, FileBody, FileChanged

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
