"""Benchmark of the ftp transport through the HTTP API, against a `curl` + `xargs -P16` script.

Starts Redis, PostgreSQL, a fleet of pyftpdlib servers (one separate process, one IOLoop),
`dncq api` and one `dncq worker --pool gevent` per core (`--workers`; docs/deployment.md),
registers the servers with `dncq machines import`, and times (1) one batchSendFile of a 200 KB
program to every machine and (2) a backup of every program into one ZIP, both the stored backup job
(`POST /api/jobs` until `GET /api/backups` lists it) and the streaming `POST
/api/cnc/backupFiles`. The baseline, measured in the same run, is what an administrator would
script: `xargs -P16` running `curl -T` per machine, and a listing plus one `curl` per program.
Prints figures only; it asserts nothing.

    python bench/transports.py [--machines 50] [--files 20] [--size-kb 40] [--send-kb 200]
                               [--parallel 16] [--concurrency 64] [--workers CORES] [--rounds 3]
                               [--keep-connection-s 30] [--profile] [--keep]

The machines keep their FTP connections between jobs for `--keep-connection-s` (their
`keep_connection_s`); 0 makes every job log in again, as before connections were kept.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time
import zipfile
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import httpx  # noqa: E402

from bench.common import (  # noqa: E402
    Process,
    bench_folder,
    child_env,
    cpu_s,
    gcode,
    host_busy_s,
    main_thread_cpu_s,
    print_table,
    profiled,
    wait_for_api,
    wait_for_worker,
)
from tests.servers import RedisServer, free_port, postgres_server  # noqa: E402

MB = 1_000_000  # MB/s figures are decimal megabytes
USER = "cnc"
PASSWORD = "bench-Pa55"
HTTP_TIMEOUT_S = 3600.0
WAIT_S = 0.5  # each GET /api/backups?job= waits this long for the backup (as the CLI asks)
BACKUP_TIMEOUT_S = 600.0
FLEET_START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 20.0
CURL_TIMEOUT_S = 600.0
PASSIVE_PORTS = range(10_000, 32_000)  # shared out between the servers, below 32,768

# What the figures should reach: dncq wall / curl wall (a send; a stored backup against one
# curl per machine, which is what an administrator's script does), and the streamed
# backupFiles against the stored backup job.
TARGET_RATIO = 0.8
TARGET_STREAM_RATIO = 1.2


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


# -- the FTP fleet (its own process) --------------------------------------------------------


def serve_fleet(root: Path, count: int) -> None:
    """Serve `count` FTP servers (homes root/m000 ...) on one IOLoop; print their ports."""
    from pyftpdlib.authorizers import DummyAuthorizer
    from pyftpdlib.handlers import FTPHandler
    from pyftpdlib.ioloop import IOLoop
    from pyftpdlib.servers import FTPServer

    logging.getLogger("pyftpdlib").setLevel(logging.WARNING)
    servers = []
    for n in range(count):
        authorizer = DummyAuthorizer()
        authorizer.add_user(USER, PASSWORD, str(root / f"m{n:03d}"), perm="elradfmwMT")
        # The authorizer is a class attribute: one handler class per server. Passive ports
        # of its own, below the kernel's ephemeral range: a data connection's port stays
        # in TIME_WAIT for a minute on the server's side, and a bench run opens some 10,000
        # of them. Left to the kernel (port 0) they used up the ephemeral range that every
        # client's connections come from: each bind and connect searched longer (the
        # servers' process took 1.7 s of CPU for a backup instead of 0.25 s) until one
        # failed ("Address already in use") and the targets were tried again.
        each = len(PASSIVE_PORTS) // count
        first = PASSIVE_PORTS.start + n * each
        handler = type(f"Handler{n:03d}", (FTPHandler,),
                       {"authorizer": authorizer, "auth_failed_timeout": 0,
                        "passive_ports": range(first, first + each)})
        servers.append(FTPServer(("127.0.0.1", 0), handler))
    print(json.dumps([s.address[1] for s in servers]), flush=True)

    def stop(signum: int, frame: Any) -> None:
        raise SystemExit(0)

    signal.signal(signal.SIGTERM, stop)
    try:
        IOLoop.instance().loop(timeout=1.0, blocking=True)  # every server shares this loop
    except (KeyboardInterrupt, SystemExit):
        pass
    finally:
        for server in servers:
            server.close_all()


@dataclass
class Fleet:
    """The FTP servers' process, their homes and ports."""

    proc: subprocess.Popen[str]
    root: Path
    ports: list[int]

    def home(self, n: int) -> Path:
        return self.root / f"m{n:03d}"

    def url(self, n: int, name: str = "") -> str:
        return f"ftp://{USER}:{PASSWORD}@127.0.0.1:{self.ports[n]}/{name}"


@contextlib.contextmanager
def ftp_fleet(folder: Path, count: int) -> Iterator[Fleet]:
    root = folder / "ftp"
    for n in range(count):
        (root / f"m{n:03d}").mkdir(parents=True, exist_ok=True)
    with open(folder / "ftp.log", "w") as log:
        proc = subprocess.Popen([sys.executable, __file__, "--serve-ftp", str(root),
                                 "--machines", str(count)],
                                stdout=subprocess.PIPE, stderr=log, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()  # blocks until the servers listen (or the process died)
        if not line:
            raise RuntimeError(f"the FTP fleet exited: {(folder / 'ftp.log').read_text()[-2000:]}")
        yield Fleet(proc, root, json.loads(line))
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def write_programs(fleet: Fleet, files: int, size_bytes: int) -> int:
    """Every machine gets `files` distinct programs (P000.NC ...); returns the bytes written."""
    total = 0
    for n in range(len(fleet.ports)):
        for k in range(files):
            data = gcode(size_bytes, seed=n * files + k).encode("ascii")
            (fleet.home(n) / f"P{k:03d}.NC").write_bytes(data)
            total += len(data)
    return total


def remove_except_programs(fleet: Fleet) -> None:
    """Drop what the send runs left (WARMUP.NC ...), so every backup sees the same programs."""
    for n in range(len(fleet.ports)):
        for path in fleet.home(n).iterdir():
            if not path.name.startswith("P"):
                path.unlink()


def fleet_yaml(ids: list[str], ports: list[int], keep_connection_s: float) -> str:
    rows = [f"  - {{id: {m}, name: FTP {m}, model: FTP server, transport: ftp, options: "
            f"{{host: 127.0.0.1, port: {p}, user: {USER}, password: {PASSWORD}, "
            f"keep_connection_s: {keep_connection_s:g}}}}}"
            for m, p in zip(ids, ports, strict=True)]
    return "machines:\n" + "\n".join(rows) + "\n"


# -- dncq through the HTTP API --------------------------------------------------------------


@dataclass
class Timed:
    """One measured operation: wall seconds, CPU of worker and API (and of the worker's main
    thread, where a gevent worker runs its Python), every core's busy time, what came back."""

    wall_s: float
    worker_cpu_s: float = 0.0
    api_cpu_s: float = 0.0
    worker_main_cpu_s: float = 0.0
    host_busy_s: float = 0.0
    ok: int = 0
    detail: str = ""
    job_id: str = ""


@contextlib.contextmanager
def metered(timed_holder: list[Timed], workers: list[Process], api: Process) -> Iterator[None]:
    """Time the block; the workers' CPU (and their main threads') summed."""
    def workers_cpu_s() -> tuple[float, float]:
        return (sum(cpu_s(w.pid) for w in workers),
                sum(main_thread_cpu_s(w.pid) for w in workers))

    before = workers_cpu_s(), cpu_s(api.pid), host_busy_s()
    started = time.perf_counter()
    yield
    wall_s = time.perf_counter() - started
    after = workers_cpu_s()
    timed_holder.append(Timed(wall_s, after[0] - before[0][0], cpu_s(api.pid) - before[1],
                              after[1] - before[0][1], host_busy_s() - before[2]))


def batch_send(client: httpx.Client, content: str, ids: list[str], name: str
               ) -> tuple[list[dict[str, Any]], str]:
    body = {"content": content, "targets": [{"machineID": m, "fileName": name} for m in ids]}
    response = client.post("/api/cnc/batchSendFile", json=body)
    response.raise_for_status()
    return response.json(), response.headers.get("X-Dncq-Job", "")


def backup_job(client: httpx.Client, api: Process, workers: list[Process]
               ) -> tuple[str, dict[str, Any]]:
    """POST a backup job of all machines; the job id and its backup once listed."""
    response = client.post("/api/jobs", json={"kind": "backup", "machines": {"all": True}})
    response.raise_for_status()
    job_id = response.json()["id"]
    deadline = time.monotonic() + BACKUP_TIMEOUT_S
    while True:
        found = client.get("/api/backups", params={"job": job_id, "wait_s": WAIT_S}
                           ).raise_for_status().json()
        if found:
            return job_id, found[0]
        for proc in (api, *workers):
            proc.check_alive()
        if time.monotonic() > deadline:
            raise TimeoutError(f"backup of job {job_id} not listed after {BACKUP_TIMEOUT_S} s")


def backup_stream(client: httpx.Client, ids: list[str], out: Path) -> tuple[int, float]:
    """POST backupFiles for every machine, the ZIP written to `out`; its size, and the
    seconds until the answer began (every target checked)."""
    started = time.perf_counter()
    with client.stream("POST", "/api/cnc/backupFiles",
                       json=[{"machineID": m} for m in ids]) as response:
        response.raise_for_status()
        checked_s = time.perf_counter() - started
        with open(out, "wb") as sink:
            for chunk in response.iter_bytes(1024 * 1024):
                sink.write(chunk)
    return out.stat().st_size, checked_s


def zip_programs(path: Path) -> int:
    """Program members in a ZIP (the manifest and folders left out)."""
    with zipfile.ZipFile(path) as archive:
        return sum(1 for i in archive.infolist()
                   if not i.is_dir() and i.filename.upper().endswith(".NC"))


def job_phases(client: httpx.Client, job_id: str, registered: str | None = None
               ) -> dict[str, float]:
    """Job created -> first target start -> last target finish (-> backup registered), in s."""
    job = client.get(f"/api/jobs/{job_id}").raise_for_status().json()
    starts = [datetime.fromisoformat(t["startedAt"]) for t in job["targets"] if t["startedAt"]]
    ends = [datetime.fromisoformat(t["finishedAt"]) for t in job["targets"] if t["finishedAt"]]
    if not starts or not ends:
        return {}
    created = datetime.fromisoformat(job["createdAt"])
    phases = {"queue": (min(starts) - created).total_seconds(),
              "targets": (max(ends) - min(starts)).total_seconds()}
    if registered:
        phases["assemble"] = (datetime.fromisoformat(registered) - max(ends)).total_seconds()
    phases["attempts"] = float(sum(t.get("attempts", 1) or 1 for t in job["targets"]))
    return phases


# -- the curl script ------------------------------------------------------------------------


# curl 7.88 (Debian 12) now and then connects an FTP data connection only once its poll of
# one second runs out ("ftp_perform ends with SECONDARY: 0", then a second of nothing before
# "Trying"), with or without EPSV. A transfer of a few KB on loopback that takes this long
# waited for that, not for the server; whole runs of the script differ by seconds with it.
CURL_STALL_S = 0.9
CURL = 'curl -sS --fail -w "%{time_total}\\n"'  # each transfer's time on a line of stdout


@dataclass
class CurlRun:
    """One run of a curl script: wall seconds, lines that failed, transfers that stalled,
    every core's busy time."""

    wall_s: float
    failed: int
    stalled: int
    host_busy_s: float = 0.0

    def text(self) -> str:
        return f"{self.wall_s:.2f}" + (f" ({self.stalled} stalled)" if self.stalled else "")


def xargs_curl(lines: list[str], command: str, parallel: int, cwd: Path) -> CurlRun:
    """`xargs -P parallel -L1 sh -c COMMAND` over `lines` (COMMAND made with `CURL`)."""
    script = f'{command} || echo FAIL "$@" >&2'
    started, busy = time.perf_counter(), host_busy_s()
    done = subprocess.run(["xargs", "-P", str(parallel), "-L", "1", "sh", "-c", script, "sh"],
                          input="\n".join(lines) + "\n", text=True, cwd=cwd,
                          capture_output=True, timeout=CURL_TIMEOUT_S)
    wall_s = time.perf_counter() - started
    stalled = sum(1 for line in done.stdout.split() if float(line) >= CURL_STALL_S)
    return CurlRun(wall_s, done.stderr.count("FAIL"), stalled, host_busy_s() - busy)


def curl_send(fleet: Fleet, program: Path, name: str, parallel: int, cwd: Path) -> CurlRun:
    """16 parallel `curl -T program ftp://.../NAME`, one per machine."""
    lines = [fleet.url(n, name) for n in range(len(fleet.ports))]
    return xargs_curl(lines, f'{CURL} -T {program} "$1"', parallel, cwd)


def curl_list(fleet: Fleet, out: Path, parallel: int) -> CurlRun:
    """`curl -l` of every machine into out/mNNN.list."""
    out.mkdir()
    lines = [f"{fleet.url(n)} m{n:03d}.list" for n in range(len(fleet.ports))]
    return xargs_curl(lines, f'{CURL} -l "$1" -o "$2"', parallel, out)


def curl_backup(fleet: Fleet, listed: Path, out: Path, parallel: int) -> tuple[CurlRun, int]:
    """One `curl` per program (`listed` names) into out/mNNN/; the run and the files."""
    out.mkdir()
    lines = []
    for n in range(len(fleet.ports)):
        (out / f"m{n:03d}").mkdir()
        names = (listed / f"m{n:03d}.list").read_text().split()
        lines += [f"{fleet.url(n, name)} m{n:03d}/{name}" for name in names]
    return xargs_curl(lines, f'{CURL} "$1" -o "$2"', parallel, out), len(lines)


def curl_backup_reusing(fleet: Fleet, listed: Path, out: Path, parallel: int
                        ) -> tuple[CurlRun, int]:
    """One `curl` per machine fetching all its programs on one connection (`listed` names);
    the run and the files it wrote."""
    out.mkdir()
    lines = []
    for n in range(len(fleet.ports)):
        (out / f"m{n:03d}").mkdir()
        names = (listed / f"m{n:03d}.list").read_text().split()
        lines.append(" ".join([f"m{n:03d}", *(fleet.url(n, name) for name in names)]))
    run = xargs_curl(lines, f'cd "$1" && shift && {CURL} --remote-name-all "$@"', parallel, out)
    return run, sum(1 for _ in out.glob("m*/*"))


# -- py-spy ---------------------------------------------------------------------------------


# Non-blocking, at 50 Hz, so that the figures of a profiled run stay near the plain ones.
PY_SPY_LIGHT = ["--gil", "--nonblocking", "--rate", "50"]


def top_frames(path: Path, count: int = 6) -> tuple[int, list[tuple[str, float]]]:
    """GIL samples, and the deepest frames of ours (jobs/, worker/) with the most of them.

    A sample with no frame of ours counts under its top frame (Celery, kombu, uvicorn ...).
    """
    ours: Counter[str] = Counter()
    total = 0
    if not path.exists():
        return 0, []
    for line in path.read_text().splitlines():
        stack, _, samples = line.rpartition(" ")
        if not samples.isdigit():
            continue
        frames = stack.split(";")
        mine = [f for f in frames if "(jobs/" in f or "(worker/" in f]
        ours[(mine[-1] if mine else frames[-1])[:80]] += int(samples)
        total += int(samples)
    return total, [(f, k / total) for f, k in ours.most_common(count)] if total else []


# -- the run --------------------------------------------------------------------------------


def run(args: argparse.Namespace, folder: Path) -> list[tuple[str, str, str, str]]:
    """The whole benchmark; returns the table rows (figure, value, target, verdict)."""
    from jobs import db

    n = args.machines
    ids = [f"ftp-{i:03d}" for i in range(n)]
    content = gcode(args.send_kb * 1024, seed=99)
    program = folder / "SEND.NC"
    program.write_text(content)
    send_bytes = len(content) * n

    with contextlib.ExitStack() as stack:
        fleet = stack.enter_context(ftp_fleet(folder, n))
        program_bytes = write_programs(fleet, args.files, args.size_kb * 1024)
        redis = RedisServer(folder)
        redis.start()
        stack.callback(redis.kill)
        pg_folder = folder / "pg"
        pg_folder.mkdir()
        db_url = stack.enter_context(postgres_server(pg_folder)).url
        data_dir = folder / "data"
        data_dir.mkdir()
        db.upgrade(db_url)

        port = free_port()
        env = child_env(data_dir=data_dir, db_url=db_url, broker_url=redis.url, port=port)
        fleet_file = folder / "fleet.yaml"
        fleet_file.write_text(fleet_yaml(ids, fleet.ports, args.keep_connection_s))
        subprocess.run([sys.executable, "-m", "jobs.cli", "machines", "import", "--direct",
                        str(fleet_file)], env=env, cwd=folder, check=True, capture_output=True)
        api = Process("api", ["api", "--host", "127.0.0.1", "--port", str(port)], env, folder)
        stack.callback(api.stop)
        workers = []
        for w in range(args.workers):  # the slots shared out between the workers
            slots = args.concurrency // args.workers + (w < args.concurrency % args.workers)
            worker = Process(f"worker{w + 1}" if args.workers > 1 else "worker", [
                "worker", "--pool", args.pool, "--concurrency", str(slots), "--loglevel",
                "WARNING", "-n", f"bench{w + 1}@%h", "--without-mingle", "--without-gossip"],
                env, folder)
            stack.callback(worker.stop)
            workers.append(worker)
        say(f"folder {folder}  api pid {api.pid}  worker pids "
            f"{' '.join(str(w.pid) for w in workers)}  ftp pid {fleet.proc.pid}")
        client = stack.enter_context(httpx.Client(base_url=f"http://127.0.0.1:{port}",
                                                  timeout=HTTP_TIMEOUT_S))
        wait_for_api(client, api)
        wait_for_worker(redis.url, data_dir, *workers)
        procs = [*workers, api]

        say(f"warm-up: batchSendFile to {n} machines (discarded) ...")
        started = time.perf_counter()
        warm_results, _ = batch_send(client, content, ids, "WARMUP.NC")
        warm_s = time.perf_counter() - started
        warm_ok = sum(1 for r in warm_results if r.get("errorCode") == 0)

        timings: list[Timed] = []
        curl_sends: list[CurlRun] = []
        sends: list[Timed] = []
        server_cpu: dict[str, list[float]] = {"curl": [], "dncq": []}
        for r in range(args.rounds):  # alternated, so that a busy moment hits both
            say(f"send round {r + 1}/{args.rounds}: curl -T via xargs, then batchSendFile ...")
            before = cpu_s(fleet.proc.pid)
            curl_sends.append(curl_send(fleet, program, f"CURL{r}.NC", args.parallel, folder))
            server_cpu["curl"].append(cpu_s(fleet.proc.pid) - before)
            before = cpu_s(fleet.proc.pid)
            with profiled(folder, f"send{r}", procs, enabled=args.profile, flags=PY_SPY_LIGHT), \
                    metered(timings, workers, api):
                results, send_job = batch_send(client, content, ids, f"SEND{r}.NC")
            server_cpu["dncq"].append(cpu_s(fleet.proc.pid) - before)
            timings[-1].ok = sum(1 for res in results if res.get("errorCode") == 0)
            timings[-1].job_id = send_job
            sends.append(timings[-1])
        # The baseline is the script's fastest run in which no transfer stalled (curl's own
        # one-second waits); with none, its fastest run, and no verdict.
        clean_sends = [c for c in curl_sends if not c.stalled]
        curl_send_best = min(clean_sends or curl_sends, key=lambda c: c.wall_s)
        send = sorted(sends, key=lambda t: t.wall_s)[len(sends) // 2]
        send_phases = job_phases(client, send.job_id)
        sent_right = sum(1 for i in range(n) for r in range(args.rounds)
                         if (fleet.home(i) / f"SEND{r}.NC").read_text() == content)

        remove_except_programs(fleet)
        say("backup: curl listing + one download per program via xargs ...")
        listing = curl_list(fleet, folder / "curl-list", args.parallel)
        per_program, curl_files = curl_backup(fleet, folder / "curl-list",
                                              folder / "curl-backup", args.parallel)
        curl_backups: list[tuple[CurlRun, CurlRun, int, float]] = []  # + the servers' CPU
        jobs: list[tuple[Timed, str, dict[str, Any], float]] = []
        streams: list[tuple[Timed, int, int, float]] = []
        for r in range(args.rounds):  # alternated, as the sends are
            say(f"backup round {r + 1}/{args.rounds}: curl listing + one curl per machine "
                f"(connection reused), a dncq stored backup job, a streamed backupFiles ...")
            before = cpu_s(fleet.proc.pid)
            listed = curl_list(fleet, folder / f"curl-list{r}", args.parallel)
            reused, reused_files = curl_backup_reusing(
                fleet, folder / f"curl-list{r}", folder / f"curl-reuse{r}", args.parallel)
            curl_backups.append((listed, reused, reused_files, cpu_s(fleet.proc.pid) - before))
            before = cpu_s(fleet.proc.pid)
            with profiled(folder, f"job{r}", procs, enabled=args.profile, flags=PY_SPY_LIGHT), \
                    metered(timings, workers, api):
                job_id, stored = backup_job(client, api, workers)
            jobs.append((timings[-1], job_id, stored, cpu_s(fleet.proc.pid) - before))
            zip_path = folder / f"stream{r}.zip"
            with profiled(folder, f"stream{r}", procs, enabled=args.profile,
                          flags=PY_SPY_LIGHT), metered(timings, workers, api):
                zip_bytes, checked_s = backup_stream(client, ids, zip_path)
            streams.append((timings[-1], zip_bytes, zip_programs(zip_path), checked_s))
        clean_backups = [c for c in curl_backups if not c[0].stalled + c[1].stalled]
        best_list, best_reuse, reuse_files, curl_servers_s = min(
            clean_backups or curl_backups, key=lambda c: c[0].wall_s + c[1].wall_s)
        curl_reuse_s = best_list.wall_s + best_reuse.wall_s
        curl_reuse_busy_s = best_list.host_busy_s + best_reuse.host_busy_s
        job, job_id, stored, job_servers_s = sorted(
            jobs, key=lambda j: j[0].wall_s)[len(jobs) // 2]
        job_phase = job_phases(client, job_id, stored.get("createdAt"))
        stream, zip_bytes, stream_files, stream_checked_s = sorted(
            streams, key=lambda x: x[0].wall_s)[len(streams) // 2]

    def ratio_row(label: str, dncq_s: float, curl_s: float, goal: float = TARGET_RATIO,
                  trusted: bool = True) -> tuple[str, str, str, str]:
        ratio = dncq_s / curl_s
        verdict = ("MET" if ratio <= goal else "MISSED") if trusted else \
            "n/a: every curl run stalled"
        return (label, f"{ratio:.2f}x", f"<= {goal:g}x", verdict)

    def mbs(nbytes: int, wall_s: float) -> str:
        return f"{nbytes / MB / wall_s:.1f} MB/s"

    expected = n * args.files
    cores = os.cpu_count() or 1
    rows = [
        ("fleet", f"{n} pyftpdlib servers (1 process), {args.files} x {args.size_kb} KB "
                  f"programs each, keep_connection_s {args.keep_connection_s:g}", "", ""),
        ("host", f"{os.cpu_count()} CPUs; {args.workers} worker(s) {args.pool}, "
                 f"{args.concurrency} slots in all, "
                 f"curl xargs -P{args.parallel}", "", ""),
        ("SEND", f"{args.send_kb} KB program to {n} machines = {send_bytes / MB:.1f} MB",
         "", ""),
        ("warm-up batchSendFile (discarded)", f"{warm_s:.2f} s ({warm_ok}/{n} ok)", "", ""),
        (f"curl -T x xargs -P16, fastest of {args.rounds} with no stall (the baseline)",
         f"{curl_send_best.wall_s:.2f} s  {mbs(send_bytes, curl_send_best.wall_s)}  "
         f"({n - curl_send_best.failed}/{n} ok; all: "
         f"{', '.join(c.text() for c in curl_sends)} s)", "", ""),
        ("  curl transfers that stalled (>= 0.9 s: curl's own wait, not the server)",
         " / ".join(str(c.stalled) for c in curl_sends), "", ""),
        (f"dncq batchSendFile (median of {args.rounds})",
         f"{send.wall_s:.2f} s  {mbs(send_bytes, send.wall_s)}  ({send.ok}/{n} errorCode 0; "
         f"all: {', '.join(f'{t.wall_s:.2f}' for t in sends)} s)", "", ""),
        ("  files verified on the servers", f"{sent_right}/{n * args.rounds}", "", ""),
        ("  job created -> first target start", _s(send_phases, "queue"), "", ""),
        ("  first target start -> last finish", _s(send_phases, "targets"), "", ""),
        ("  attempts (retries included)", _n(send_phases, "attempts"), "", ""),
        ("  CPU worker / api", f"{send.worker_cpu_s:.2f} / {send.api_cpu_s:.2f} s", "", ""),
        ("  CPU of the FTP servers' process, curl / dncq (medians)",
         f"{statistics.median(server_cpu['curl']):.2f} / "
         f"{statistics.median(server_cpu['dncq']):.2f} s", "", ""),
        ratio_row("send dncq / curl's baseline", send.wall_s, curl_send_best.wall_s,
                  trusted=bool(clean_sends)),
        ("BACKUP", f"{expected} programs = {program_bytes / MB:.1f} MB", "", ""),
        ("curl -l + curl per program, -P16 (once, for information)",
         f"{listing.wall_s + per_program.wall_s:.2f} s  "
         f"{mbs(program_bytes, listing.wall_s + per_program.wall_s)}  (list {listing.text()} s "
         f"+ fetch {per_program.text()} s; {curl_files} files, "
         f"{listing.failed + per_program.failed} failed)", "", ""),
        (f"curl -l + one curl per machine, -P16, fastest of {len(curl_backups)} with no stall "
         f"(the baseline)",
         f"{curl_reuse_s:.2f} s  {mbs(program_bytes, curl_reuse_s)}  (list "
         f"{best_list.text()} s + fetch {best_reuse.text()} s; {reuse_files} files, "
         f"{best_list.failed + best_reuse.failed} failed; all: "
         f"{', '.join(f'{a.wall_s + b.wall_s:.2f}' for a, b, _, _ in curl_backups)} s)", "", ""),
        ("  curl transfers that stalled, each run (list + fetch)",
         " / ".join(f"{a.stalled} + {b.stalled}" for a, b, _, _ in curl_backups), "", ""),
        (f"dncq backup job (POST -> listed, median of {len(jobs)})",
         f"{job.wall_s:.2f} s  {mbs(program_bytes, job.wall_s)}  "
         f"({stored.get('status')}, {stored.get('files')} files, "
         f"ZIP {stored.get('size', 0) / MB:.1f} MB; all: "
         f"{', '.join(f'{t.wall_s:.2f}' for t, _, _, _ in jobs)} s)", "", ""),
        ("  job created -> first target start", _s(job_phase, "queue"), "", ""),
        ("  first target start -> last finish", _s(job_phase, "targets"), "", ""),
        ("  last finish -> backup registered", _s(job_phase, "assemble"), "", ""),
        ("  attempts (retries included)", _n(job_phase, "attempts"), "", ""),
        ("  CPU worker (its main thread) / api",
         f"{job.worker_cpu_s:.2f} ({job.worker_main_cpu_s:.2f}) / {job.api_cpu_s:.2f} s", "", ""),
        ("  every core's busy time / cores: no wall below it",
         f"{job.host_busy_s:.2f} s / {cores} = {job.host_busy_s / cores:.2f} s, "
         f"{job.host_busy_s / cores / curl_reuse_s:.2f}x curl's baseline (curl's own "
         f"{curl_reuse_busy_s:.2f} s / {cores} = {curl_reuse_busy_s / cores:.2f} s)", "", ""),
        ("  CPU of the FTP servers' process, curl's baseline / this job",
         f"{curl_servers_s:.2f} / {job_servers_s:.2f} s", "", ""),
        ratio_row("backup job dncq / one curl per machine's baseline", job.wall_s,
                  curl_reuse_s, trusted=bool(clean_backups)),
        (f"dncq backupFiles (streamed ZIP, median of {len(streams)})",
         f"{stream.wall_s:.2f} s  {mbs(program_bytes, stream.wall_s)}  "
         f"({stream_files}/{expected} programs, ZIP {zip_bytes / MB:.1f} MB; all: "
         f"{', '.join(f'{t.wall_s:.2f}' for t, _, _, _ in streams)} s)", "", ""),
        ("  POST -> the answer begins (every target checked)", f"{stream_checked_s:.2f} s",
         "", ""),
        ("  CPU worker / api", f"{stream.worker_cpu_s:.2f} / {stream.api_cpu_s:.2f} s", "", ""),
        ("  every core's busy time / cores: no wall below it",
         f"{stream.host_busy_s:.2f} s / {cores} = {stream.host_busy_s / cores:.2f} s", "", ""),
        ratio_row("backupFiles streamed / the stored backup job", stream.wall_s, job.wall_s,
                  TARGET_STREAM_RATIO),
    ]
    if args.profile:
        rows.append(("PY-SPY (GIL holder, 50 Hz)", "deepest frame of ours; share of samples",
                     "", ""))
        for name in (*(f"send{r}" for r in range(args.rounds)),
                     *(f"{kind}{r}" for r in range(args.rounds) for kind in ("job", "stream"))):
            for proc in (*(w.name for w in workers), "api"):
                total, frames = top_frames(folder / f"{name}-{proc}.txt")
                rows.append((f"{name} {proc}", f"{total} samples", "", ""))
                rows += [("", f"{share:5.1%} {frame}", "", "") for frame, share in frames]
    return rows


def _s(phases: dict[str, float], key: str) -> str:
    return f"{phases[key]:.2f} s" if key in phases else "n/a"


def _n(phases: dict[str, float], key: str) -> str:
    return f"{phases[key]:.0f}" if key in phases else "n/a"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--machines", type=int, default=50)
    parser.add_argument("--files", type=int, default=20)
    parser.add_argument("--size-kb", type=int, default=40)
    parser.add_argument("--send-kb", type=int, default=200)
    parser.add_argument("--parallel", type=int, default=16, help="xargs -P of the curl script")
    parser.add_argument("--concurrency", type=int, default=64)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="worker processes, the slots shared out between them (default: "
                             "one per core, as docs/deployment.md advises)")
    parser.add_argument("--pool", default="gevent", choices=["gevent", "threads"],
                        help="the worker's pool")
    parser.add_argument("--rounds", type=int, default=3,
                        help="send and backup rounds; the median counts")
    parser.add_argument("--keep-connection-s", type=float, default=30.0,
                        help="the machines' keep_connection_s (0: log in for every job)")
    parser.add_argument("--profile", action="store_true",
                        help="py-spy the worker and the API during the measured runs")
    parser.add_argument("--keep", action="store_true", help="Keep the folder (logs, data)")
    parser.add_argument("--serve-ftp", type=Path, help=argparse.SUPPRESS)  # the fleet process
    args = parser.parse_args()
    if args.serve_ftp:
        serve_fleet(args.serve_ftp, args.machines)
        return
    # SIGTERM (timeout, kill) unwinds like Ctrl-C, so that every server started is stopped.
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    if shutil.which("curl") is None:
        sys.exit("curl is not installed (apt-get install -y curl)")
    with bench_folder(args.keep or args.profile) as folder:
        rows = run(args, folder)
    print_table(rows)


if __name__ == "__main__":
    main()
