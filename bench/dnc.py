"""Benchmark of DNC links: N simulated controls drip-fed at once by one dncq worker, and a
single control's file transfer against a raw loopback copy of the same bytes.

Starts Redis, PostgreSQL, `dncq api`, one `dncq worker --pool gevent --concurrency N` and
the simulated controls (`Control` + `DncServer` pairs, several per process: bench/dnc_fleet.py),
registers the controls as `dnc` machines, stores one program of `--lines` lines
(`POST /api/programs`) and starts it on every machine as one `dnc_run` job. It prints the
lines per second delivered in all against the sum of the controls' block rates, the worst
feed hold at a control (every loaded line executed while more were due) and the longest
wait from the control offering room to the lines arriving, the requests the controls
answered per 1,000 lines (QUERY_FILE_DNC, SEND_FILE_DNC, SEND_DATA…), worker CPU per
1,000 lines and the worker's peak RSS. Then, on an idle host, a `--transfer-mb` program
written to and read from one simulated control (`dncq sim-cnc`, a process of its own)
through the `dnc` transport, against a plain loopback socket copy of the same bytes to a
process of its own.
Prints figures only; it asserts nothing.

    python bench/dnc.py [--machines 100] [--lines 200000] [--block-rate 1000]
                        [--per-process 25] [--transfer-mb 20] [--profile] [--keep]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import httpx  # noqa: E402

from bench.common import (  # noqa: E402
    HTTP_TIMEOUT_S,
    Process,
    bench_folder,
    child_env,
    cpu_s,
    postgres_cpu_s,
    print_table,
    profiled,
    tree_cpu_s,
    wait_for_api,
    wait_for_worker,
)
from tests.servers import RedisServer, free_port, postgres_server  # noqa: E402

MB = 1_000_000
POLL_S = 1.0  # how often the job is read while the runs go on
STOP_TIMEOUT_S = 20.0

# What the figures should reach.
TARGET_DELIVERED = 0.98  # lines/s delivered / sum of the block rates
TARGET_LAG_MS = 50.0
TARGET_RSS_MB = 300.0


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def program_lines(count: int, seed: int = 11) -> Iterator[bytes]:
    """A milling program of exactly `count` lines (each with its newline)."""
    rng = random.Random(seed)
    x = y = 0.0
    yield b"O0100 (BENCH DRIP)\n"
    for n in range(1, count - 1):
        x = min(max(x + rng.uniform(-5, 5), 0.0), 400.0)
        y = min(max(y + rng.uniform(-5, 5), 0.0), 300.0)
        yield f"N{n * 10} G1 X{x:.3f} Y{y:.3f} F1200\n".encode("ascii")
    yield b"M30\n"


# -- the simulated controls -------------------------------------------------------------


class Controls:
    """The bench's fleet processes (bench/dnc_fleet.py) and their ports."""

    def __init__(self, folder: Path, machines: int, per_process: int, block_rate: float
                 ) -> None:
        self.procs: list[subprocess.Popen[str]] = []
        self.ports: list[int] = []
        for k, first in enumerate(range(0, machines, per_process)):
            count = min(per_process, machines - first)
            with open(folder / f"controls{k}.log", "w") as log:
                proc = subprocess.Popen(
                    [sys.executable, str(REPO / "bench" / "dnc_fleet.py"), "--root",
                     str(folder / f"controls{k}"), "--machines", str(count),
                     "--block-rate", str(block_rate)],
                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log, text=True)
            self.procs.append(proc)
        for proc in self.procs:
            assert proc.stdout is not None
            line = proc.stdout.readline()
            if not line:
                raise RuntimeError("a fleet process exited; see its controls*.log")
            self.ports += json.loads(line)

    def stats(self) -> list[dict[str, Any]]:
        found: list[dict[str, Any]] = []
        for proc in self.procs:
            assert proc.stdin is not None and proc.stdout is not None
            proc.stdin.write("stats\n")
            proc.stdin.flush()
            found += json.loads(proc.stdout.readline())
        return found

    def cpu_s(self) -> float:
        return sum(cpu_s(p.pid) for p in self.procs)

    def stop(self) -> None:
        for proc in self.procs:
            with contextlib.suppress(OSError):
                assert proc.stdin is not None
                proc.stdin.close()
        for proc in self.procs:
            try:
                proc.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def fleet_yaml(ports: list[int]) -> str:
    rows = [f"  - {{id: dnc-{n:03d}, name: DNC {n:03d}, model: Fanuc 0i-F, transport: dnc, "
            f"options: {{host: 127.0.0.1, port: {port}}}}}" for n, port in enumerate(ports)]
    return "machines:\n" + "\n".join(rows) + "\n"


def register(url: str, ports: list[int], folder: Path) -> list[str]:
    from jobs.db import session_scope
    from jobs.fleet import fleet_file

    with session_scope(url) as session:
        fleet_file.import_fleet(session=session,
                                machines=fleet_file.parse_fleet(fleet_yaml(ports)),
                                data_dir=folder / "data")
    return [f"dnc-{n:03d}" for n in range(len(ports))]


# -- the drip-feed runs -----------------------------------------------------------------


def wait_job(client: httpx.Client, job_id: str, worker: Process) -> dict[str, Any]:
    while True:
        worker.check_alive()
        job = client.get(f"/api/jobs/{job_id}", params={"limit": 0}).json()
        if job["state"] not in ("queued", "running"):
            return job
        time.sleep(POLL_S)


def _at(text: str) -> float:
    return datetime.fromisoformat(text).timestamp()


def drip_rows(args: argparse.Namespace, client: httpx.Client, controls: Controls,
              worker: Process, api: Process, pgdata: Path, ids: list[str], folder: Path
              ) -> list[tuple[str, str, str, str]]:
    n = len(ids)
    say(f"storing a {args.lines}-line program ...")
    stored = client.post("/api/programs", content=b"".join(program_lines(args.lines)),
                         headers={"content-type": "application/octet-stream"}).json()
    say(f"  {stored['size'] / MB:.1f} MB, {stored['lines']} lines; {n} runs ...")
    before = (cpu_s(worker.pid), cpu_s(api.pid), postgres_cpu_s(pgdata), controls.cpu_s())
    started = time.monotonic()
    with profiled(folder, "drip", [worker], enabled=args.profile):
        answer = client.post("/api/jobs", json={
            "kind": "dnc_run", "machines": {"ids": ids}, "program": stored["id"],
            "fileName": "O0100"})
        answer.raise_for_status()
        job = wait_job(client, answer.json()["id"], worker)
    wall_s = time.monotonic() - started
    worker_s, api_s, pg_s, controls_s = (
        after - b for after, b in zip((cpu_s(worker.pid), cpu_s(api.pid),
                                       postgres_cpu_s(pgdata), controls.cpu_s()), before,
                                      strict=True))
    seen = controls.stats()
    runs = job["runs"]
    ok = [r for r in runs if r["state"] == "succeeded"]
    lines = sum(r["line"] for r in runs)
    first = min(_at(r["startedAt"]) for r in runs if r["startedAt"])
    last = max(_at(r["endedAt"]) for r in runs if r["endedAt"])
    span_s = last - first
    per_run = [r["line"] / (_at(r["endedAt"]) - _at(r["startedAt"])) for r in ok]
    capacity = n * args.block_rate
    delivered = lines / span_s
    starved = max(s["longest_starved_ms"] for s in seen)
    stalls = sum(s["starved_count"] or 0 for s in seen)
    ask = max(s["longest_ask_ms"] for s in seen)
    requests = sum(s.get("requests", 0) for s in seen)
    rss = worker.peak_rss_mb() or 0.0

    def verdict(good: bool) -> str:
        return "MET" if good else "MISSED"

    rows = [
        ("machines x lines x block rate", f"{n} x {args.lines} x {args.block_rate:g}/s", "", ""),
        ("runs succeeded", f"{len(ok)}/{n} (job {job['state']})", "", ""),
        ("job wall (POST -> final)", f"{wall_s:.1f} s (ideal {args.lines / args.block_rate:.1f}"
                                     " s per run)", "", ""),
        ("first start -> last end", f"{span_s:.1f} s", "", ""),
        ("lines/s delivered in all", f"{delivered:,.0f} of {capacity:,.0f} "
         f"= {delivered / capacity:.3f}", f">= {TARGET_DELIVERED}",
         verdict(delivered / capacity >= TARGET_DELIVERED)),
        ("  per run (median, worst)", f"{sorted(per_run)[len(per_run) // 2]:,.0f} / "
         f"{min(per_run):,.0f} lines/s" if per_run else "n/a", "", ""),
        ("worst feed hold at a control", f"{starved:.1f} ms ({stalls} holds in all)",
         f"< {TARGET_LAG_MS:g} ms", verdict(starved < TARGET_LAG_MS)),
        ("longest room offered -> lines in", f"{ask:.1f} ms", "", ""),
        ("requests to the controls per 1,000 lines", f"{requests / lines * 1000:.1f}", "", ""),
        ("worker CPU per 1,000 lines", f"{worker_s / lines * 1000 * 1000:.2f} ms "
         f"({worker_s:.1f} s in all)", "", ""),
        ("CPU api / PostgreSQL / controls", f"{api_s:.1f} / {pg_s:.1f} / {controls_s:.1f} s",
         "", ""),
        ("worker peak RSS (VmHWM)", f"{rss:.0f} MB", f"< {TARGET_RSS_MB:g} MB",
         verdict(rss < TARGET_RSS_MB)),
    ]
    return rows


# -- one control's file transfer ------------------------------------------------------------


@contextlib.contextmanager
def simulator(folder: Path) -> Iterator[int]:
    """`dncq sim-cnc` in a process of its own; yields its port."""
    proc = subprocess.Popen([sys.executable, "-m", "jobs.cli", "sim-cnc", "--port", "0",
                             "--root", str(folder / "sim-root")],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                            cwd=REPO)
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        if not first.startswith("listening tcp "):
            raise RuntimeError(f"the simulator did not start: {first!r}")
        yield int(first.split()[3])
    finally:
        proc.terminate()
        proc.wait(STOP_TIMEOUT_S)


# A plain socket peer for the baseline: `sink PATH` stores what it gets and answers one
# byte; `source PATH` sends the file. One connection, then it exits.
_PEER = """
import socket, sys
mode, path = sys.argv[1], sys.argv[2]
server = socket.create_server(("127.0.0.1", 0))
print(server.getsockname()[1], flush=True)
conn, _ = server.accept()
if mode == "sink":
    with open(path, "wb") as out:
        while data := conn.recv(1 << 20):
            out.write(data)
            if out.tell() >= int(sys.argv[3]):
                break
    conn.sendall(b"k")
else:
    with open(path, "rb") as src:
        while data := src.read(65536):
            conn.sendall(data)
conn.close()
"""


def raw_copy_s(folder: Path, data: bytes, mode: str) -> float:
    """Seconds to move `data` over a plain loopback socket to ("sink") or from ("source") a
    process of its own that writes or reads a file, as the control does with its programs."""
    path = folder / f"raw-{mode}.bin"
    if mode == "source":
        path.write_bytes(data)
    proc = subprocess.Popen([sys.executable, "-c", _PEER, mode, str(path), str(len(data))],
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    port = int(proc.stdout.readline())
    started = time.perf_counter()
    with socket.create_connection(("127.0.0.1", port)) as sock:
        if mode == "sink":
            view = memoryview(data)
            for at in range(0, len(data), 65536):
                sock.sendall(view[at:at + 65536])
            sock.recv(1)
        else:
            got = 0
            while part := sock.recv(1 << 20):
                got += len(part)
    elapsed = time.perf_counter() - started
    proc.wait(STOP_TIMEOUT_S)
    return elapsed


def transfer_rows(args: argparse.Namespace, folder: Path) -> list[tuple[str, str, str, str]]:
    from worker.transports.dnc import DncOptions, DncTransport

    size = args.transfer_mb * MB
    data = b"".join(program_lines(size // 28))[:size]
    rows: list[tuple[str, str, str, str]] = []
    with simulator(folder) as port:
        transport = DncTransport(DncOptions(host="127.0.0.1", port=port,
                                            transfer_timeout_s=600, timeout_s=60))
        try:
            started = time.perf_counter()
            transport.write("BIG.NC", iter([data]))
            write_s = time.perf_counter() - started
            started = time.perf_counter()
            got = sum(len(chunk) for chunk in transport.read("BIG.NC"))
            read_s = time.perf_counter() - started
        finally:
            transport.close()
    if got != len(data):
        raise RuntimeError(f"read back {got} bytes of {len(data)}")
    raw_write_s = raw_copy_s(folder, data, "sink")
    raw_read_s = raw_copy_s(folder, data, "source")
    for what, dnc_s, raw_s in (("write", write_s, raw_write_s), ("read", read_s, raw_read_s)):
        rows.append((f"{what} {size / MB:.0f} MB over dnc / raw socket",
                     f"{size / MB / dnc_s:.0f} / {size / MB / raw_s:.0f} MB/s "
                     f"({dnc_s:.2f} / {raw_s:.2f} s) = {raw_s / dnc_s:.2f} of the limit",
                     "", ""))
    return rows


def run(args: argparse.Namespace, folder: Path) -> list[tuple[str, str, str, str]]:
    from jobs import db

    with contextlib.ExitStack() as stack:
        redis = RedisServer(folder)
        redis.start()
        stack.callback(redis.kill)
        pg_folder = folder / "pg"
        pg_folder.mkdir()
        db_url = stack.enter_context(postgres_server(pg_folder)).url
        data_dir = folder / "data"
        data_dir.mkdir()
        db.upgrade(db_url)
        controls = Controls(folder, args.machines, args.per_process, args.block_rate)
        stack.callback(controls.stop)
        ids = register(db_url, controls.ports, folder)

        port = free_port()
        env = child_env(data_dir=data_dir, db_url=db_url, broker_url=redis.url, port=port)
        api = Process("api", ["api", "--host", "127.0.0.1", "--port", str(port)], env, folder)
        stack.callback(api.stop)
        worker = Process("worker", ["worker", "--pool", args.pool, "--concurrency",
                                    str(args.concurrency or args.machines), "--loglevel",
                                    "WARNING", "-n", "bench@%h", "--without-mingle",
                                    "--without-gossip"], env, folder)
        stack.callback(worker.stop)
        say(f"folder {folder}  api pid {api.pid}  worker pid {worker.pid}")
        client = stack.enter_context(httpx.Client(base_url=f"http://127.0.0.1:{port}",
                                                  timeout=HTTP_TIMEOUT_S))
        wait_for_api(client, api)
        wait_for_worker(redis.url, data_dir, worker)
        rows = drip_rows(args, client, controls, worker, api, pg_folder / "pgdata", ids, folder)
        say(f"worker tree CPU {tree_cpu_s(worker.pid):.1f} s")
    say(f"file transfer: {args.transfer_mb} MB ...")
    rows += transfer_rows(args, folder)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--machines", type=int, default=100)
    parser.add_argument("--lines", type=int, default=200_000)
    parser.add_argument("--block-rate", type=float, default=1000.0)
    parser.add_argument("--per-process", type=int, default=25,
                        help="simulated controls per fleet process")
    parser.add_argument("--pool", choices=("gevent", "threads"), default="gevent")
    parser.add_argument("--concurrency", type=int, default=0, help="default: --machines")
    parser.add_argument("--transfer-mb", type=int, default=20)
    parser.add_argument("--profile", action="store_true", help="py-spy the worker")
    parser.add_argument("--keep", action="store_true", help="Keep the folder (logs, data)")
    args = parser.parse_args()
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    with bench_folder(args.keep) as folder:
        rows = run(args, folder)
    print_table(rows)


if __name__ == "__main__":
    main()
