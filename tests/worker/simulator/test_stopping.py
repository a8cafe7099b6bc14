"""`dncq sim-cnc` stops on SIGTERM whichever of its threads the kernel hands the signal to."""

from __future__ import annotations

import ctypes
import os
import signal
import socket
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


# Its threads besides the main one: the run's, the listener's, the ping checks' and, with a
# client connected, the client's.
OTHER_THREADS = 4


@pytest.mark.parametrize("index", range(OTHER_THREADS))
def test_a_sigterm_to_any_thread_stops_the_simulator(tmp_path: Path, index: int) -> None:
    with running_sim(tmp_path) as sim, socket.create_connection(("127.0.0.1", sim.port)):
        deadline = time.monotonic() + 5
        while len(_other_threads(sim)) < OTHER_THREADS and time.monotonic() < deadline:
            time.sleep(0.02)  # the client's own thread starts
        threads = _other_threads(sim)
        assert len(threads) == OTHER_THREADS, threads

        _tgkill(sim.process.pid, threads[index], signal.SIGTERM)

        # Hung, it is stopped by the SIGTERM that running_sim sends at its end.
        assert sim.process.wait(5) in (0, -signal.SIGTERM)
