"""`dncq sim-cnc` stops on SIGTERM whichever of its threads the kernel hands the signal to."""

from __future__ import annotations

import ctypes
import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest

from tests.worker.simulator.sim_process import Sim, running_sim


def _tgkill(pid: int, tid: int, signum: int) -> None:
    """Send `signum` to one thread of a process, as the kernel may pick any of them."""
    libc = ctypes.CDLL(None, use_errno=True)
    if not hasattr(libc, "tgkill"):
        pytest.skip("this C library has no tgkill (glibc 2.30 or later has)")
    if libc.tgkill(pid, tid, signum) != 0:
        raise OSError(ctypes.get_errno(), "tgkill")


def _other_threads(sim: Sim) -> list[int]:
    pid = sim.process.pid
    return sorted(int(t) for t in os.listdir(f"/proc/{pid}/task") if int(t) != pid)


def _stops_on_sigterm_to(tmp_path: Path, index: int) -> bool | None:
    """Start a simulator with a client connected, send SIGTERM to its `index`th thread other
    than the main one: True if it exits within 5 s, None if it has no such thread."""
    with running_sim(tmp_path / f"sim{index}") as sim, \
            socket.create_connection(("127.0.0.1", sim.port)):
        deadline = time.monotonic() + 5
        while len(_other_threads(sim)) < 4 and time.monotonic() < deadline:
            time.sleep(0.02)  # the client's own thread starts
        threads = _other_threads(sim)
        if index >= len(threads):
            return None
        _tgkill(sim.process.pid, threads[index], signal.SIGTERM)
        try:
            sim.process.wait(5)
        except subprocess.TimeoutExpired:
            return False  # stopped by the SIGTERM that running_sim sends at its end
        return True


def test_a_sigterm_to_any_thread_stops_the_simulator(tmp_path: Path) -> None:
    stopped: list[bool] = []
    while (result := _stops_on_sigterm_to(tmp_path, len(stopped))) is not None:
        stopped.append(result)
    # Its other threads: the run's, the listener's, the ping checks' and the client's.
    assert stopped == [True] * 4
