"""The bar of a file's bytes as `dncq get` saves it: on a terminal only, the file the same."""

from __future__ import annotations

import os
import pty
import subprocess
import sys
from collections.abc import Iterator

import pytest

from jobs.api.app import create_app
from jobs.settings import get_settings
from tests.jobs.helpers import on_machine
from tests.live_server import LiveServer, serving

BIG = b"N10 G1 X1.0 Y2.0 F600\n" * 300_000  # 6.6 MB: a few hundred chunks


@pytest.fixture
def live(settings, demo_fleet, env, monkeypatch) -> Iterator[LiveServer]:
    """The demo fleet served on loopback, machine 1016 holding BIG.NC, the CLI pointed at it."""
    on_machine(settings, "1016", "BIG.NC").write_bytes(BIG)
    with serving(create_app(settings)) as server:
        monkeypatch.setenv("DNCQ_URL", server.url)
        get_settings.cache_clear()
        yield server


def _dncq_on_a_terminal(*args: str) -> tuple[int, str]:
    """`dncq args...` run as a user at a terminal runs it (stdout and stderr a pseudo-terminal
    100 columns wide): its exit status and what the terminal showed."""
    terminal, its_end = pty.openpty()
    command = subprocess.Popen([sys.executable, "-m", "jobs.cli", *args], stdin=its_end,
                               stdout=its_end, stderr=its_end,
                               env={**os.environ, "COLUMNS": "100", "TERM": "xterm"})
    os.close(its_end)
    shown = b""
    while True:
        try:
            data = os.read(terminal, 65536)
        except OSError:  # EIO: the command ended, and its end of the terminal with it
            break
        if not data:
            break
        shown += data
    os.close(terminal)
    return command.wait(timeout=60), shown.decode(errors="replace")


def test_get_on_a_terminal_shows_a_bar_of_the_bytes_and_saves_the_file_whole(live, env):
    status, shown = _dncq_on_a_terminal("get", "1016", "BIG.NC", "-o", "copy.nc")

    assert status == 0, shown
    assert "download" in shown and "6.6 MB" in shown  # the bar, and the size it counts to
    assert "Saved copy.nc" in shown
    assert (env / "copy.nc").read_bytes() == BIG


def test_get_into_a_log_shows_no_bar_and_saves_the_same_file(live, env):
    done = subprocess.run([sys.executable, "-m", "jobs.cli", "get", "1016", "BIG.NC", "-o",
                           "copy.nc"], capture_output=True, timeout=60)

    assert done.returncode == 0, done.stderr
    assert (done.stdout, done.stderr) == (b"", b"Saved copy.nc\n")
    assert (env / "copy.nc").read_bytes() == BIG


def test_get_to_stdout_gives_the_bytes_alone_and_no_bar(live, env):
    done = subprocess.run([sys.executable, "-m", "jobs.cli", "get", "1016", "BIG.NC", "-o",
                           "-"], capture_output=True, timeout=60)

    assert done.returncode == 0, done.stderr
    assert done.stdout == BIG and done.stderr == b""
