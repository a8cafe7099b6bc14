"""What is in a machine's spool folder that dncq did not write there (a FIFO named like a
kept program, the folder itself replaced by a file) or could not write whole (a disk
full) or flush to the disk: the listener goes on hearing the machine, and recording what it
sends, once."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from pathlib import Path

from jobs.requests import spool
from tests.jobs.requests.conftest import wait_for_jobs
from tests.jobs.requests.test_on_links import tcp_control  # noqa: F401

REPO = Path(__file__).resolve().parents[3]
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


def test_a_program_the_disk_has_no_room_for_leaves_no_part_of_it_behind(
        settings) -> None:
    """The file size limit (RLIMIT_FSIZE) refuses the write as a full disk would, midway."""
    script = (
        "import resource, signal, sys\n"
        "from jobs.requests import spool\n"
        "from jobs.settings import Settings\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, 64 * 1024))\n"
        f"settings = Settings(data_dir={str(settings.data_dir)!r})\n"
        "try:\n"
        "    spool.put(settings, '2001', b'G1 X1\\n' * 100_000)\n"
        "except OSError as exc:\n"
        "    print('refused', exc.errno)\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60, env={**os.environ, "PYTHONPATH": str(REPO)})

    assert done.stdout.startswith("refused"), done.stdout + done.stderr
    assert list(spool_folder(settings).iterdir()) == []


def test_a_spool_folder_that_cannot_be_flushed_leaves_the_program_recorded_once(
        settings, tcp_control, monkeypatch) -> None:  # noqa: F811
    """The folder's fsync after the rename refused (no way was found to make a real one fail
    here, so the call is made to): the program, in the folder all the same, is recorded
    under the id it was kept under and removed, not left for a later listener to record
    again under that id while it was recorded under another."""
    def refused(folder: Path) -> None:
        raise OSError(5, "Input/output error", str(folder))

    monkeypatch.setattr(spool, "_sync_folder", refused)
    server = tcp_control()
    server.punch_text(PROGRAM)

    [job] = wait_for_jobs(settings, 1)
    assert job["state"] == "succeeded" and job["fileName"] == "1234"
    deadline = time.monotonic() + 10  # removed just after its job is recorded
    while spool.pending(settings, "2001") and time.monotonic() < deadline:
        time.sleep(0.05)
    assert spool.pending(settings, "2001") == []
