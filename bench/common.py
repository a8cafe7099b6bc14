"""What the benchmarks share: G-code, mock fleets, dncq processes, CPU and memory readings,
the median of repeated runs."""

from __future__ import annotations

import contextlib
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol, TypeVar

import httpx

REPO = Path(__file__).resolve().parent.parent
HTTP_TIMEOUT_S = 3600.0
START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 20.0


def gcode(size_bytes: int, seed: int = 7) -> str:
    """A realistic milling program of about `size_bytes` ASCII bytes."""
    rng = random.Random(seed)
    lines = ["%", "O4711 (BENCH POCKET)", "G21 G90 G17 G40 G49 G80", "T1 M6", "S8000 M3",
             "G0 Z5.000", "G43 H1 Z5.000 M8"]
    size = sum(len(line) + 1 for line in lines)
    n = 10
    x = y = 0.0
    tail = ["G0 Z50.000 M9", "M5", "M30", "%"]
    tail_bytes = sum(len(line) + 1 for line in tail)
    while size + tail_bytes < size_bytes:
        x = min(max(x + rng.uniform(-5, 5), 0.0), 400.0)
        y = min(max(y + rng.uniform(-5, 5), 0.0), 300.0)
        if n % 50 == 0:
            line = f"N{n} G1 Z{-rng.uniform(0.5, 3):.3f} F300"
        elif n % 17 == 0:
            line = f"N{n} G2 X{x:.3f} Y{y:.3f} I{rng.uniform(-3, 3):.3f} " \
                   f"J{rng.uniform(-3, 3):.3f} F900"
        else:
            line = f"N{n} G1 X{x:.3f} Y{y:.3f} F1200"
        lines.append(line)
        size += len(line) + 1
        n += 10
    return "\n".join(lines + tail) + "\n"


def fleet_yaml(ids: list[str], latency_ms: float, *, trace: bool = False) -> str:
    """A fleet file of mock machines (tracing their operations if asked)."""
    traced = ", trace: true" if trace else ""
    rows = [f"  - {{id: {m}, name: Bench {m}, model: Mock, transport: mock, "
            f"options: {{latency_ms: {latency_ms:g}{traced}}}}}" for m in ids]
    return "machines:\n" + "\n".join(rows) + "\n"


class Process:
    """A dncq subprocess with its log file."""

    def __init__(self, name: str, args: list[str], env: dict[str, str], folder: Path) -> None:
        self.name = name
        self.log_path = folder / f"{name}.log"
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "jobs.cli", *args], env=env,
                                         stdout=log, stderr=subprocess.STDOUT, cwd=folder)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def check_alive(self) -> None:
        if self.proc.poll() is not None:
            tail = self.log_path.read_text(errors="replace")[-2000:]
            raise RuntimeError(f"{self.name} exited ({self.proc.returncode}):\n{tail}")

    def peak_rss_mb(self) -> float | None:
        """VmHWM of the process (the largest of it and its pool children), in MB."""
        peaks = []
        pids = [self.pid] + [int(p) for p in _children(self.pid)]
        for pid in pids:
            with contextlib.suppress(OSError):
                for line in Path(f"/proc/{pid}/status").read_text().splitlines():
                    if line.startswith("VmHWM:"):
                        peaks.append(int(line.split()[1]) / 1024)
        return max(peaks) if peaks else None

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _children(pid: int) -> list[str]:
    with contextlib.suppress(OSError):
        return Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    return []


def wait_for_api(client: httpx.Client, api: Process) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while True:
        api.check_alive()
        with contextlib.suppress(httpx.HTTPError):
            if client.get("/api/health").status_code == 200:
                return
        if time.monotonic() > deadline:
            raise TimeoutError("the API did not answer /api/health in time")
        time.sleep(0.1)


def migrated_postgres(stack: contextlib.ExitStack, folder: Path) -> str:
    """A PostgreSQL of its own in `folder`/pg, dncq's schema made, stopped with `stack`;
    its URL."""
    from jobs import db
    from tests.servers import postgres_server

    pg_folder = folder / "pg"
    pg_folder.mkdir()
    url: str = stack.enter_context(postgres_server(pg_folder)).url
    db.upgrade(url)
    return url


def api_alone(stack: contextlib.ExitStack, folder: Path, *, db_url: str,
              broker_url: str) -> tuple[Process, httpx.Client]:
    """`dncq api` with its data in `folder`/data and no worker, answering; stopped with
    `stack`. The process (for its RSS) and a client of it."""
    from tests.servers import free_port

    data_dir = folder / "data"
    data_dir.mkdir()
    port = free_port()
    env = child_env(data_dir=data_dir, db_url=db_url, broker_url=broker_url, port=port)
    api = Process("api", ["api", "--host", "127.0.0.1", "--port", str(port)], env, folder)
    stack.callback(api.stop)
    client = stack.enter_context(httpx.Client(base_url=f"http://127.0.0.1:{port}",
                                              timeout=HTTP_TIMEOUT_S))
    wait_for_api(client, api)
    return api, client


def wait_for_worker(broker_url: str, data_dir: Path, *workers: Process) -> None:
    """Block until every worker answers a ping over the broker: they consume their queue, so
    a measured job does not wait for one to start."""
    from jobs.run.queue import workers_answering
    from jobs.settings import Settings

    settings = Settings(data_dir=data_dir, broker_url=broker_url)
    deadline = time.monotonic() + START_TIMEOUT_S
    while workers_answering(settings, timeout_s=0.5) < len(workers):
        for worker in workers:
            worker.check_alive()
        if time.monotonic() > deadline:
            raise TimeoutError("the workers did not answer a ping in time")


CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int, *, with_children: bool = False) -> float:
    """CPU seconds (user + system) a process used so far; reaped children too if asked."""
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    ticks = int(fields[11]) + int(fields[12])  # utime, stime
    if with_children:
        ticks += int(fields[13]) + int(fields[14])  # cutime, cstime
    return ticks / CLOCK_TICKS


def main_thread_cpu_s(pid: int) -> float:
    """CPU seconds of a process's main thread alone: where a gevent worker runs its Python
    (its other threads are native ones, such as those that deflate)."""
    fields = Path(f"/proc/{pid}/task/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def host_busy_s() -> float:
    """CPU seconds every core of the host spent on anything but idling, so far."""
    fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = fields[3] + fields[4]  # idle, iowait
    return (sum(fields[:8]) - idle) / CLOCK_TICKS  # guest time is already in user


def tree_cpu_s(parent: int) -> float:
    """CPU seconds of a process, its exited children and its live children."""
    total = cpu_s(parent, with_children=True)
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            fields = stat.read_text().rpartition(")")[2].split()
            if int(fields[1]) == parent:
                total += (int(fields[11]) + int(fields[12])) / CLOCK_TICKS
    return total


def postgres_cpu_s(pgdata: Path) -> float:
    """CPU seconds of the PostgreSQL server: postmaster, its exited and its live backends."""
    return tree_cpu_s(int((pgdata / "postmaster.pid").read_text().split()[0]))


def child_env(*, data_dir: Path, db_url: str, broker_url: str, port: int) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("DNCQ_")}
    env.update({
        "PYTHONUNBUFFERED": "1",
        "PYTHONPATH": str(REPO),
        "DNCQ_DATA_DIR": str(data_dir),
        "DNCQ_DATABASE_URL": db_url,
        "DNCQ_BROKER_URL": broker_url,
        "DNCQ_AUTH": "none",
        "DNCQ_HOST": "127.0.0.1",
        "DNCQ_PORT": str(port),
        "DNCQ_BATCH_WAIT_S": str(HTTP_TIMEOUT_S),
        # The workers' own machine checks (the first 5 s after they start, then every 300 s)
        # would land inside the measured runs: 1000 checks in a 1000-machine rollout's
        # first seconds tripled its CPU per target.
        "DNCQ_MACHINE_CHECK_INTERVAL_S": "0",
    })
    return env


class Timed(Protocol):
    wall_s: float


T = TypeVar("T", bound=Timed)


def median_run(runs: list[T]) -> T:
    """The run of median wall time (the upper one of an even count): a real run, whole."""
    return sorted(runs, key=lambda run: run.wall_s)[len(runs) // 2]


def walls_text(runs: list[T]) -> str:
    """Every run's wall time, in the order they ran: `2.64 / 2.84 / 2.67`."""
    return " / ".join(f"{run.wall_s:.2f}" for run in runs)


def print_table(rows: list[tuple[str, str, str, str]]) -> None:
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    head = ("figure", "value", "target", "")
    widths = [max(w, len(h)) for w, h in zip(widths, head, strict=True)]
    line = "  ".join("-" * w for w in widths)
    print(line)
    print("  ".join(h.ljust(w) for h, w in zip(head, widths, strict=True)).rstrip())
    print(line)
    for row in rows:
        print("  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip())
    print(line)


@contextlib.contextmanager
def bench_folder(keep: bool) -> Iterator[Path]:
    folder = Path(tempfile.mkdtemp(prefix="dncq-bench-"))
    folder.chmod(0o755)  # PostgreSQL runs as `postgres` below it
    try:
        yield folder
    finally:
        if keep:
            print(f"kept {folder}", file=sys.stderr)
        else:
            shutil.rmtree(folder, ignore_errors=True)


PY_SPY_FLAGS = ["--gil", "--rate", "250"]


@contextlib.contextmanager
def profiled(folder: Path, name: str, processes: list[Process], *, enabled: bool,
             flags: list[str] | None = None) -> Iterator[None]:
    """py-spy records the processes for the block into the folder, as raw stacks.

    `flags` default to samples of the thread holding the GIL, at 250 Hz.
    """
    if not enabled or shutil.which("py-spy") is None:
        yield
        return
    spies = [subprocess.Popen(["py-spy", "record", "--pid", str(p.pid),
                               *(PY_SPY_FLAGS if flags is None else flags),
                               "--format", "raw", "-o", str(folder / f"{name}-{p.name}.txt")],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
             for p in processes]
    time.sleep(1.0)  # py-spy attaches
    try:
        yield
    finally:
        for spy in spies:
            spy.send_signal(signal.SIGINT)  # py-spy writes its file on SIGINT
            spy.wait(60)
