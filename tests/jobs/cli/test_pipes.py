"""The `dncq` command writing into a pipe its reader closes early (`| head -1`)."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator

import pytest

from jobs.api.app import create_app
from jobs.settings import get_settings
from tests.jobs.helpers import on_machine
from tests.live_server import LiveServer, serving

# More than a pipe holds (64 KiB on Linux): dncq is still writing when `head` leaves.
LINES = 4000


@pytest.fixture
def live(settings, demo_fleet, env, monkeypatch) -> Iterator[LiveServer]:
    """The demo fleet served on loopback, its machine 1016 holding a long program and a
    folder of many, and the CLI pointed at it."""
    on_machine(settings, "1016", "LONG.nc").write_text(
        "".join(f"N{n} G1 X{n}.000 Y{n}.000 F1000\n" for n in range(LINES)))
    for n in range(LINES):
        on_machine(settings, "1016", f"MANY/PROGRAM_WITH_A_LONG_NAME_{n}.nc").write_text("M30\n")
    with serving(create_app(settings)) as server:
        monkeypatch.setenv("DNCQ_URL", server.url)
        get_settings.cache_clear()
        yield server


@pytest.mark.parametrize(("args", "first_line"), [
    (("get", "1016", "LONG.nc", "-o", "-"), "N0 G1 X0.000 Y0.000 F1000"),  # a file's bytes
    (("ls", "1016", "MANY"), "/MANY"),  # a long listing
], ids=["get", "ls"])
def test_a_command_whose_reader_closes_the_pipe_ends_quietly_with_status_0(
        live, args, first_line):
    # `dncq get 1016 LONG.nc -o - | head -1` printed its line, and dncq exited 1.
    dncq = subprocess.Popen([sys.executable, "-m", "jobs.cli", *args], stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert dncq.stdout is not None and dncq.stderr is not None
    head = subprocess.run(["head", "-1"], stdin=dncq.stdout, capture_output=True, timeout=120)
    dncq.stdout.close()  # head's end alone holds the pipe: its exit closes it
    said = dncq.stderr.read().decode()

    assert dncq.wait(timeout=120) == 0, said
    assert said == ""
    assert head.stdout.decode() == f"{first_line}\n"
