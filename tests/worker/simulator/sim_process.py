"""Starts `dncq sim-cnc` as a process of its own on a free loopback port, for tests."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from worker.transports.dnc import DncOptions, DncTransport


@dataclass
class Sim:
    """A running simulator: its port, its program folder and its logs."""

    process: subprocess.Popen[str]
    port: int
    root: Path
    log_dir: Path

    def executed(self) -> list[str]:
        """Every line the control executed, in order."""
        path = self.log_dir / "executed.log"
        return path.read_text(encoding="latin-1").splitlines() if path.exists() else []

    def runs(self) -> list[dict[str, Any]]:
        """The runs that ended, as in runs.jsonl."""
        path = self.log_dir / "runs.jsonl"
        return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() \
            else []

    def transport(self, port: int | None = None, **options: Any) -> DncTransport:
        """A `dnc` transport to it (or to `port`: a proxy in front of it)."""
        settings = {"host": "127.0.0.1", "port": port or self.port, "timeout_s": 10.0,
                    "heartbeat_interval_s": 0.5, "ping_checks": 3, "grace_s": 10.0,
                    "poll_interval_s": 0.002} | options
        return DncTransport(DncOptions.model_validate(settings))


@contextmanager
def running_sim(folder: Path, *args: str) -> Iterator[Sim]:
    """A simulator serving `folder`/root with extra `args`; stopped at the end."""
    root, log_dir = folder / "root", folder / "log"
    command = [sys.executable, "-m", "jobs.cli", "sim-cnc", "--port", "0", "--root", str(root),
               "--log-dir", str(log_dir), *args]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True,
                               env=os.environ | {"PYTHONUNBUFFERED": "1"})
    try:
        assert process.stdout is not None
        first = process.stdout.readline()  # "listening tcp HOST PORT"
        if not first.startswith("listening tcp "):
            pytest.fail(f"the simulator did not start: {first!r}")
        yield Sim(process, int(first.split()[3]), root, log_dir)
    finally:
        process.terminate()
        try:
            ended = process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()  # not left running after the test
            process.wait()
            pytest.fail("the simulator did not stop within 10 s of SIGTERM")
        if ended not in (0, -15):
            pytest.fail(f"the simulator ended with {ended}")


SimFactory = Callable[..., Sim]


@pytest.fixture
def start_sim(tmp_path: Path) -> Iterator[SimFactory]:
    """Factory: start_sim(*args) starts a simulator; every one is stopped after the test."""
    with contextlib.ExitStack() as stack:
        count = iter(range(1000))

        def start(*args: str) -> Sim:
            return stack.enter_context(running_sim(tmp_path / f"sim{next(count)}", *args))

        yield start


