"""What is in a machine's spool folder that dncq did not write there (a FIFO named like a
kept program, the folder itself replaced by a file): the listener goes on hearing the
machine, and recording what it sends."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from jobs.requests import spool
from tests.jobs.requests.conftest import wait_for_jobs
from tests.jobs.requests.test_on_links import tcp_control  # noqa: F401

PROGRAM = b"%\nO1234 (BRACKET)\nG0 X1 Y1\nM30\n%\n"


def spool_folder(settings) -> Path:
    return settings.data_dir / "requests" / "spool" / "2001"


def test_a_fifo_named_as_a_kept_program_leaves_the_listener_hearing_the_machine(
        settings, tcp_control) -> None:  # noqa: F811
    folder = spool_folder(settings)
    folder.mkdir(parents=True)
    fifo = folder / f"{1:020d}-0123456789abcdef{spool.SUFFIX}"
    os.mkfifo(fifo)
    try:
        server = tcp_control()
        server.punch_text(PROGRAM)

        [job] = wait_for_jobs(settings, 1)
        assert job["state"] == "succeeded" and job["fileName"] == "1234"
        assert fifo.exists()  # not dncq's: left where it is
    finally:  # a listener blocked opening it is let go
        with contextlib.suppress(OSError):
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))


def test_a_spool_folder_that_cannot_be_listed_leaves_what_the_machine_sends_recorded(
        settings, tcp_control) -> None:  # noqa: F811
    """As one made by another user (root, for a worker run once by hand) would be."""
    folder = spool_folder(settings)
    folder.parent.mkdir(parents=True)
    folder.write_text("not a folder")
    server = tcp_control()
    server.punch_text(PROGRAM)

    [job] = wait_for_jobs(settings, 1)
    assert job["state"] == "succeeded" and job["fileName"] == "1234"

