"""Benchmark of backup jobs: a fleet's programs fetched and assembled into one stored ZIP.

Starts Redis, PostgreSQL, `dncq api` and `--workers` `dncq worker --pool gevent` processes,
writes G-code into the mock machines' storage, registers them with `dncq machines import`,
and times `POST /api/jobs {"kind": "backup", "machines": {"all": true}}` until the backup
appears in `GET /api/backups`. Run 1 (a fleet with latency) compares the wall time with a
sequential in-process script and with the limit (ideal fetch, or deflate spread over the
cores): the median of `--repeat` runs, each against the limit timed just before it, then
the same backups with the machines answering at once (the host's CPU floor); run 2
(about 1 GiB, no latency) gives throughput and peak memory. Prints figures; asserts nothing.

    python bench/backup.py [--machines 50] [--files 20] [--size-kb 40] [--latency-ms 20]
                           [--level 3] [--concurrency 64] [--workers 1]
                           [--pool gevent|threads]
                           [--large-machines 100] [--large-files 20] [--large-size-kb 512]
                           [--skip-large] [--repeat 3] [--profile] [--trace] [--keep]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import statistics
import struct
import subprocess
import sys
import time
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
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
    fleet_yaml,
    gcode,
    host_busy_s,
    main_thread_cpu_s,
    median_run,
    print_table,
    profiled,
    wait_for_api,
    wait_for_worker,
    walls_text,
)
from jobs.settings import Settings  # noqa: E402
from tests.servers import RedisServer, free_port, postgres_server  # noqa: E402

MIB = 1024 * 1024
WAIT_S = 0.5  # each GET /api/backups?job= waits this long for the backup (as the CLI asks)
BACKUP_TIMEOUT_S = 3600.0
API_START_ATTEMPTS = 3  # a free port can be taken by another process before the API binds it
LARGE_MIN_FREE_BYTES = 5 * 1024**3  # below this, run 2 is scaled down
MOCK_COUNTERS = struct.Struct("<qqq")  # the mock's counters file: in progress, peak, begun
# Between two asks the bench asks the database whether the job stalled with every target
# final (concurrent `targets.finish` calls can each see the others still running); this
# many such answers in a row make it settle the job.
STALL_CHECKS = 2
BLOCKS = 8  # distinct G-code blocks run 2's files are built from

# What the figures should reach.
TARGET_SPEEDUP = 30.0
TARGET_LIMIT_RATIO = 1.3  # wall / the limit with dncq's own deflate (jobs.backup.deflate)
TARGET_RSS_MB = 300.0

DEFAULT_LEVEL = Settings.model_fields["backup_zip_level"].default  # what dncq deflates at


@dataclass
class Stack:
    """Redis, PostgreSQL, the API and the workers, with a fleet of mock machines."""

    folder: Path
    data_dir: Path
    db_url: str
    client: httpx.Client
    api: Process
    workers: list[Process]
    ids: list[str]
    broker_url: str


@dataclass
class BackupRun:
    """One backup job, from the POST until the backup is listed."""

    wall_s: float
    job: dict[str, Any]
    backup: dict[str, Any]
    worker_cpu_s: float
    api_cpu_s: float
    host_cpu_s: float  # every process on the host, the benchmark's own polling too
    worker_main_cpu_s: float  # the worker's main thread: its Python (under gevent, all of it)
    settled_by_bench: bool = False  # the job stalled with every target final
    phases: dict[str, float] = field(default_factory=dict)
    traced: dict[str, float] = field(default_factory=dict)  # with --trace: the machines' view


# -- the fleet's programs -----------------------------------------------------------------


def machine_files(data_dir: Path, machine_id: str) -> Path:
    """Where a mock machine's storage lives (the Mock model's root is the folder itself)."""
    return data_dir / "mock" / machine_id / "files"


def write_distinct(data_dir: Path, ids: list[str], files: int, size_bytes: int) -> list[bytes]:
    """Every file a program of its own (P000.nc ...); returns their bytes."""
    written = []
    for m, machine_id in enumerate(ids):
        folder = machine_files(data_dir, machine_id)
        folder.mkdir(parents=True)
        for k in range(files):
            data = gcode(size_bytes, seed=m * files + k).encode("ascii")
            (folder / f"P{k:03d}.nc").write_bytes(data)
            written.append(data)
    return written


def gcode_blocks(count: int, block_bytes: int) -> list[bytes]:
    """`count` distinct runs of cutting moves (no header or end), about `block_bytes` each."""
    blocks = []
    for seed in range(count):
        body = gcode(block_bytes + 512, seed=1000 + seed).splitlines()[7:-4]
        text, size = [], 0
        for line in body:
            if size >= block_bytes:
                break
            text.append(line)
            size += len(line) + 1
        blocks.append(("\n".join(text) + "\n").encode("ascii"))
    return blocks


def write_repeated(data_dir: Path, ids: list[str], files: int, size_bytes: int) -> int:
    """Cheap large programs: a header of their own, then shared blocks in a rotated order."""
    blocks = gcode_blocks(BLOCKS, 64 * 1024)
    total = 0
    for m, machine_id in enumerate(ids):
        folder = machine_files(data_dir, machine_id)
        folder.mkdir(parents=True)
        for k in range(files):
            turn = m * files + k
            parts = [f"%\nO{turn % 9000 + 1000:04d} ({machine_id} P{k:03d})\n"
                     f"G21 G90 G17\nT{turn % 12 + 1} M6\nS{6000 + turn % 4000} M3\n".encode()]
            size = len(parts[0])
            n = turn
            while size < size_bytes - 32:
                block = blocks[n % BLOCKS][: size_bytes - 32 - size]
                parts.append(block)
                size += len(block)
                n += 3  # a different order in every file
            parts.append(b"G0 Z50.000 M9\nM5\nM30\n%\n")
            data = b"".join(parts)
            (folder / f"P{k:03d}.nc").write_bytes(data)
            total += len(data)
    return total


def ops_begun(data_dir: Path, machine_id: str) -> int:
    """Primitive operations the mock machine has begun so far (from its counters file)."""
    raw = (data_dir / "mock" / machine_id / "counters").read_bytes()
    return MOCK_COUNTERS.unpack(raw[:MOCK_COUNTERS.size])[2] if len(raw) >= 24 else 0


def tracing(s: Stack, *, enabled: bool) -> None:
    """With --trace, every mock machine notes the start and end of each of its operations
    (a line appended to a file: a few microseconds more per operation)."""
    if not enabled:
        return
    from worker.transports.mock import MockOptions, MockTransport

    for machine_id in s.ids:  # run-time options, removed by answering_at_once
        MockTransport(MockOptions(), folder=s.data_dir / "mock" / machine_id
                      ).set_options(trace=True)


def machines_view(s: Stack, since: float) -> dict[str, float]:
    """Where a machine's time went in the run since `since`, from its traced operations, in
    s: an operation's median (its latency and the mock's own work), the median wait
    between two of one machine's operations and its sum per machine (dncq's work between
    them), and how far apart the machines' first operations began."""
    from worker.transports.mock_state import traced

    ops, gaps, firsts = [], [], []
    for machine_id in s.ids:
        mine = sorted(traced([s.data_dir / "mock" / machine_id], since=since))
        if not mine:
            continue
        ops += [end - start for start, end in mine]
        gaps.append([mine[i + 1][0] - mine[i][1] for i in range(len(mine) - 1)])
        firsts.append(mine[0][0])
    between = [gap for machine in gaps for gap in machine]
    if not ops or not between:
        return {}
    return {"op": statistics.median(ops), "gap": statistics.median(between),
            "gaps_per_machine": statistics.median(sum(machine) for machine in gaps),
            "first_spread": max(firsts) - min(firsts)}


# -- the service --------------------------------------------------------------------------


@contextlib.contextmanager
def stack(folder: Path, *, ids: list[str], latency_ms: float, level: int, concurrency: int,
          pool: str, worker_count: int, write: Any) -> Iterator[Stack]:
    """Servers, programs written by `write(data_dir)`, the fleet imported, API and workers."""
    from jobs import db

    with contextlib.ExitStack() as exits:
        redis = RedisServer(folder)
        redis.start()
        exits.callback(redis.kill)
        pg_folder = folder / "pg"
        pg_folder.mkdir()
        db_url = exits.enter_context(postgres_server(pg_folder)).url
        data_dir = folder / "data"
        data_dir.mkdir()
        db.upgrade(db_url)
        write(data_dir)

        env = child_env(data_dir=data_dir, db_url=db_url, broker_url=redis.url, port=0)
        env["DNCQ_BACKUP_ZIP_LEVEL"] = str(level)
        fleet = folder / "fleet.yaml"
        fleet.write_text(fleet_yaml(ids, latency_ms))
        subprocess.run([sys.executable, "-m", "jobs.cli", "machines", "import", "--direct",
                        str(fleet)], env=env, cwd=folder, check=True, capture_output=True)

        api, client = exits.enter_context(api_server(env, folder))
        workers = []
        for n in range(worker_count):  # the slots shared out between the workers
            slots = concurrency // worker_count + (n < concurrency % worker_count)
            worker = Process(f"worker{n + 1}" if worker_count > 1 else "worker", [
                "worker", "--pool", pool, "--concurrency", str(slots), "--loglevel", "WARNING",
                "-n", f"bench{n + 1}@%h", "--without-mingle", "--without-gossip"], env, folder)
            exits.callback(worker.stop)
            workers.append(worker)
        print(f"folder {folder}  api pid {api.pid}  worker pids "
              f"{' '.join(str(w.pid) for w in workers)}", file=sys.stderr, flush=True)
        wait_for_worker(redis.url, data_dir, *workers)
        yield Stack(folder, data_dir, db_url, client, api, workers, ids, redis.url)


@contextlib.contextmanager
def api_server(env: dict[str, str], folder: Path) -> Iterator[tuple[Process, httpx.Client]]:
    """`dncq api` on a free port, tried again on another when the port was taken meanwhile."""
    for attempt in range(API_START_ATTEMPTS):
        port = free_port()
        env = {**env, "DNCQ_PORT": str(port)}
        api = Process("api", ["api", "--host", "127.0.0.1", "--port", str(port)], env, folder)
        client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=BACKUP_TIMEOUT_S)
        try:
            wait_for_api(client, api)
        except RuntimeError:
            client.close()
            api.stop()
            if attempt + 1 == API_START_ATTEMPTS or "address already in use" not in \
                    api.log_path.read_text(errors="replace"):
                raise
            continue
        try:
            yield api, client
        finally:
            client.close()
            api.stop()
        return


def run_backup(s: Stack) -> BackupRun:
    """POST a backup of all machines; wait until `GET /api/backups` lists it."""
    cpu_before = cpu_readings(s)
    started, posted_at = time.perf_counter(), datetime.now().astimezone()
    response = s.client.post("/api/jobs", json={"kind": "backup", "machines": {"all": True}})
    response.raise_for_status()
    answered_s = time.perf_counter() - started
    job_id = response.json()["id"]
    deadline = time.monotonic() + BACKUP_TIMEOUT_S
    stalled_checks, settled = 0, False
    while True:
        found = s.client.get("/api/backups", params={"job": job_id, "wait_s": WAIT_S}
                             ).raise_for_status().json()
        if found:
            break
        if not settled:
            stalled_checks = stalled_checks + 1 if stalled(s, job_id) else 0
        if stalled_checks >= STALL_CHECKS:
            settle(s, job_id)
            settled = True
        for worker in s.workers:
            worker.check_alive()
        s.api.check_alive()
        if time.monotonic() > deadline:
            raise TimeoutError(f"backup of job {job_id} not listed after {BACKUP_TIMEOUT_S} s")
    wall_s, listed_at = time.perf_counter() - started, datetime.now().astimezone()
    cpu_after = cpu_readings(s)
    job = s.client.get(f"/api/jobs/{job_id}").raise_for_status().json()
    run = BackupRun(wall_s, job, found[0], cpu_after[0] - cpu_before[0],
                    cpu_after[1] - cpu_before[1], cpu_after[2] - cpu_before[2],
                    cpu_after[3] - cpu_before[3], settled)
    run.phases = phases(job, found[0])
    run.phases.update(answered=answered_s, posted=(
        datetime.fromisoformat(job["createdAt"]) - posted_at).total_seconds(), listed=(
        listed_at - datetime.fromisoformat(found[0]["createdAt"])).total_seconds())
    return run


def answering_at_once(s: Stack, repeat: int) -> list[BackupRun]:
    """`repeat` backups with every machine's latency at 0 (a run-time option of the mock),
    then their latency as the fleet file gives it.

    Nothing to wait for: the wall is the host's CPU doing the backup's work, the floor
    under any backup of these files here, whatever the machines' latency.
    """
    from worker.transports.mock import MockOptions, MockTransport

    for machine_id in s.ids:  # as the tests change a mock at run time (tests/jobs/helpers)
        MockTransport(MockOptions(), folder=s.data_dir / "mock" / machine_id
                      ).set_options(latency_ms=0)
    try:
        return [run_backup(s) for _ in range(repeat)]
    finally:  # no run-time options left: the fleet file's again
        for machine_id in s.ids:
            (s.data_dir / "mock" / machine_id / "options.json").unlink(missing_ok=True)


def cpu_readings(s: Stack) -> tuple[float, float, float, float]:
    """CPU seconds so far: the workers, the API, the host, the workers' main threads."""
    return (sum(cpu_s(w.pid) for w in s.workers), cpu_s(s.api.pid), host_busy_s(),
            sum(main_thread_cpu_s(w.pid) for w in s.workers))


def peak_rss_mb(workers: list[Process]) -> float | None:
    """The highest peak RSS of the workers."""
    peaks = [p for p in (w.peak_rss_mb() for w in workers) if p is not None]
    return max(peaks) if peaks else None


def stalled(s: Stack, job_id: str) -> bool:
    """Every target of the job is final, yet the job is not finished."""
    from sqlalchemy import select

    from jobs.db import session_scope
    from jobs.models import Job, Target, TargetState

    with session_scope(s.db_url) as session:
        if session.scalar(select(Job.finished_at).where(Job.id == job_id)) is not None:
            return False
        return session.scalar(select(Target.id).where(
            Target.job_id == job_id,
            Target.state.in_([TargetState.PENDING, TargetState.RUNNING])).limit(1)) is None


def settle(s: Stack, job_id: str) -> None:
    """Do what the last runner should have done: settle the job and queue its assembly."""
    from jobs.db import session_scope
    from jobs.run import queue, settle

    say(f"  job {job_id} stalled with every target final: the bench settles it")
    with session_scope(s.db_url) as session:
        settle.update_job_state(session=session, job_id=job_id)
    queue.enqueue_assembly(Settings(data_dir=s.data_dir, database_url=s.db_url,
                                    broker_url=s.broker_url), job_id)


def _late(runs: list[BackupRun], round_s: float) -> str:
    """How many backups' fetch took two rounds or more: a machine waited a round for a slot
    (with several workers, one held more machines than its slots while another had room; a
    target claimed ahead counts as started while it waits)."""
    late = sum(r.phases.get("fetch", 0.0) >= 2 * round_s for r in runs)
    return f"{late} of {len(runs)}"


def _traced_rows(run: BackupRun, latency_ms: float) -> list[tuple[str, str, str, str]]:
    """The machines' own view of the median run, with --trace."""
    t = run.traced
    if not t:
        return []
    return [("    a machine's operation, median (--trace)",
             f"{t['op'] * 1000:.1f} ms (latency {latency_ms:g} ms)", "", ""),
            ("    between its operations: median / sum per machine",
             f"{t['gap'] * 1000:.2f} ms / {t['gaps_per_machine'] * 1000:.0f} ms", "", ""),
            ("    first operations of the machines, spread", f"{t['first_spread'] * 1000:.0f} ms",
             "", "")]


def phases(job: dict[str, Any], backup: dict[str, Any]) -> dict[str, float]:
    """Job created -> first fetch start -> last fetch finish -> backup registered, in s."""
    starts = [datetime.fromisoformat(t["startedAt"]) for t in job["targets"] if t["startedAt"]]
    ends = [datetime.fromisoformat(t["finishedAt"]) for t in job["targets"] if t["finishedAt"]]
    if not starts or not ends:
        return {}
    created = datetime.fromisoformat(job["createdAt"])
    registered = datetime.fromisoformat(backup["createdAt"])
    durations = sorted(
        (datetime.fromisoformat(t["finishedAt"]) - datetime.fromisoformat(t["startedAt"]))
        .total_seconds() for t in job["targets"] if t["startedAt"] and t["finishedAt"])
    return {"queue": (min(starts) - created).total_seconds(),
            "starts": (max(starts) - min(starts)).total_seconds(),
            "target_median": durations[len(durations) // 2], "target_max": durations[-1],
            "fetch": (max(ends) - min(starts)).total_seconds(),
            "assemble": (registered - max(ends)).total_seconds(),
            "created_to_registered": (registered - created).total_seconds()}


# -- the comparisons ------------------------------------------------------------------------


def baseline_script(s: Stack, out: Path, level: int) -> float:
    """What a script would do: every machine, every file, in turn, into Python's zipfile."""
    from jobs import db
    from jobs.fleet import door, registry
    from jobs.fleet.paths import Place
    from jobs.fleet.rules import FileRef

    with db.session_scope(s.db_url) as session:
        specs = registry.list_all(session=session)
    started = time.perf_counter()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED, compresslevel=level) as archive:
        for spec in specs:
            with door.open_files(spec, data_dir=s.data_dir) as files:
                start = files.paths.resolve(None, None)
                for found in files.walk(start):
                    ref = FileRef(Place(start.root, start.parts + found.parts), found.entry.name)
                    with archive.open(f"{spec.id}/{found.storage}", "w") as member:
                        for chunk in files.open(ref):
                            member.write(chunk)
    return time.perf_counter() - started


def deflate_s(contents: list[bytes], level: int) -> float:
    """Seconds one thread takes to deflate every file with zlib (raw deflate, as ZIP members
    are)."""
    started = time.perf_counter()
    for data in contents:
        deflater = zlib.compressobj(level, zlib.DEFLATED, -zlib.MAX_WBITS)
        deflater.compress(data)
        deflater.flush()
    return time.perf_counter() - started


def dncq_deflate_s(contents: list[bytes], level: int) -> float:
    """The same with dncq's own deflate at that level (ISA-L at 1-3, zlib-ng else)."""
    from jobs.backup import deflate

    started = time.perf_counter()
    for data in contents:
        deflate.whole(data, level)
    return time.perf_counter() - started


# -- the two runs -------------------------------------------------------------------------


def run_latency(args: argparse.Namespace, folder: Path) -> list[tuple[str, str, str, str]]:
    """Run 1: a fleet with latency, warm, against a script and against the limit."""
    n, files, latency_s = args.machines, args.files, args.latency_ms / 1000
    ids = [f"bench-{i:03d}" for i in range(n)]
    contents: list[bytes] = []

    def write(data_dir: Path) -> None:
        say(f"run 1: writing {n} x {files} programs of {args.size_kb} KiB ...")
        contents.extend(write_distinct(data_dir, ids, files, args.size_kb * 1024))

    with stack(folder, ids=ids, latency_ms=args.latency_ms, level=args.level,
               concurrency=args.concurrency, pool=args.pool, worker_count=args.workers,
               write=write) as s:
        total = sum(len(c) for c in contents)
        say("run 1: warm-up backup (discarded) ...")
        warm = run_backup(s)
        before = {m: ops_begun(s.data_dir, m) for m in ids}
        runs, zlib_s = [], []
        tracing(s, enabled=args.trace)
        for i in range(args.repeat):
            # The limit is timed beside every run, and each run set against its own: this
            # host's speed drifts from one minute to the next, and the limit with it.
            zlib_s.append(deflate_s(contents, args.level))
            say(f"run 1: measured backup {i + 1} of {args.repeat} ...")
            since = time.time()
            with profiled(s.folder, f"run1-{i + 1}", [*s.workers, s.api], enabled=args.profile):
                runs.append(run_backup(s))
            if args.trace:
                runs[-1].traced = machines_view(s, since)
        ops = [(ops_begun(s.data_dir, m) - before[m]) / args.repeat for m in ids]
        run = median_run(runs)
        say("run 1: the same backups with the machines answering at once ...")
        floor_runs = answering_at_once(s, args.repeat)
        floor = median_run(floor_runs)
        say("run 1: baseline A (sequential script) ...")
        baseline_s = baseline_script(s, folder / "baseline.zip", args.level)
        baseline_zip = (folder / "baseline.zip").stat().st_size
        worker_mb, api_mb = peak_rss_mb(s.workers), s.api.peak_rss_mb()

    # A stored backup of one flat folder: the walk lists it once (the check before it does
    # not probe the machine), then one read per file.
    ops_per_machine = 1 + files
    serial_s = ops_per_machine * latency_s
    spread_s = n * ops_per_machine * latency_s / args.concurrency
    fetch_ideal_s = max(serial_s, spread_s)
    cores = os.cpu_count() or 1
    limits = [max(fetch_ideal_s, one_s / cores) for one_s in zlib_s]
    ratios = [r.wall_s / limit for r, limit in zip(runs, limits, strict=True)]
    one_thread_s = statistics.median(zlib_s)
    deflate_ideal_s = one_thread_s / cores
    limit_s = max(fetch_ideal_s, deflate_ideal_s)
    ng_one_thread_s = statistics.median(  # what dncq's workers use
        dncq_deflate_s(contents, args.level) for _ in range(args.repeat))
    ng_limit_s = max(fetch_ideal_s, ng_one_thread_s / cores)
    floor_ratio = floor.wall_s / ng_limit_s
    speedup = baseline_s / run.wall_s
    ratio = statistics.median(ratios)
    p = run.phases
    return [
        ("RUN 1", f"{n} machines x {files} files x {args.size_kb} KiB, "
                  f"latency {args.latency_ms:g} ms, level {args.level}", "", ""),
        ("uncompressed bytes", f"{total / MIB:.1f} MiB", "", ""),
        ("warm-up backup (discarded)", f"{warm.wall_s:.2f} s"
         + (", settled by the bench" if warm.settled_by_bench else ""), "", ""),
        (f"wall (POST -> listed in /api/backups), median of {len(runs)}",
         f"{run.wall_s:.2f} s  (runs {walls_text(runs)})", "", ""),
        ("  POST sent -> job created / POST answered", f"{_s(p, 'posted')} / "
                                                        f"{_s(p, 'answered')}", "", ""),
        ("  job created -> first fetch start", _s(p, "queue"), "", ""),
        ("  first fetch start -> last fetch end", _s(p, "fetch"), "", ""),
        ("    first start -> last start", _s(p, "starts"), "", ""),
        ("    backups whose fetch took two rounds", _late(runs, fetch_ideal_s), "", ""),
        ("    target duration median / max", f"{_s(p, 'target_median')} / "
                                             f"{_s(p, 'target_max')}", "", ""),
        *_traced_rows(run, args.latency_ms),
        ("  last fetch end -> backup registered", _s(p, "assemble"), "", ""),
        ("  backup registered -> listed (its GET answered)", _s(p, "listed"), "", ""),
        ("job counts", _counts(run.job), "", ""),
        ("job settled by", _settled(run), "", ""),
        ("backup", f"{run.backup['status']}, {run.backup['files']} files", "", ""),
        ("throughput", f"{total / MIB / run.wall_s:.1f} MiB/s", "", ""),
        ("ZIP size", f"{run.backup['size'] / MIB:.1f} MiB "
                     f"({run.backup['size'] / total:.1%} of input)", "", ""),
        ("CPU during the run: worker / api",
         f"{run.worker_cpu_s:.2f} / {run.api_cpu_s:.2f} s", "", ""),
        ("  worker's main thread / its other threads", _threads(run), "", ""),
        ("  the whole host, every core (busy / available)", _host(run), "", ""),
        ("peak RSS worker / api (VmHWM)", f"{_mb(worker_mb)} / {_mb(api_mb)}", "", ""),
        ("baseline A: sequential script", f"{baseline_s:.2f} s "
                                          f"(ZIP {baseline_zip / MIB:.1f} MiB)", "", ""),
        ("speed-up = baseline A / wall", f"{speedup:.1f}x", f">= {TARGET_SPEEDUP:g}x",
         _verdict(speedup >= TARGET_SPEEDUP)),
        ("primitive ops per machine", f"{ops_per_machine} (1 list_dir + {files} read); "
                                      f"mock counted {min(ops):g}-{max(ops):g} per run", "", ""),
        ("  slowest machine serial", f"{serial_s:.3f} s", "", ""),
        (f"  all ops x latency / {args.concurrency} slots", f"{spread_s:.3f} s", "", ""),
        ("(a) ideal fetch", f"{fetch_ideal_s:.3f} s", "", ""),
        (f"  zlib level {args.level}, one thread, before each run", " / ".join(
            f"{t:.3f}" for t in zlib_s) + f" s (median {total / MIB / one_thread_s:.1f} MiB/s)",
         "", ""),
        (f"(b) deflate over {cores} cores", f"{deflate_ideal_s:.3f} s", "", ""),
        ("limit = max(a, b), median", f"{limit_s:.3f} s", "", ""),
        ("each run's wall / its limit", " / ".join(f"{r:.2f}x" for r in ratios), "", ""),
        ("wall / limit (median of those)", f"{ratio:.2f}x", "", ""),
        ("  median wall / median limit (unpaired)", f"{run.wall_s / limit_s:.2f}x", "", ""),
        (f"  dncq's deflate at level {args.level}, one thread", f"{ng_one_thread_s:.3f} s", "", ""),
        ("wall / limit with dncq's deflate", f"{run.wall_s / ng_limit_s:.2f}x "
                                                f"(limit {ng_limit_s:.3f} s)",
         f"<= {TARGET_LIMIT_RATIO:g}x", _verdict(run.wall_s / ng_limit_s <= TARGET_LIMIT_RATIO)),
        (f"the same backup at latency 0, median of {len(floor_runs)}",
         f"{floor.wall_s:.2f} s  (runs {walls_text(floor_runs)}; worker's main thread / "
         f"other threads {_threads(floor)})", "", ""),
        ("  its wall / the limit with dncq's deflate", f"{floor_ratio:.2f}x "
         + ("(the host's CPU alone is over the goal: no overlap with the machines' "
            "waits can meet it here)" if floor_ratio > TARGET_LIMIT_RATIO else
            "(the CPU's own floor, with nothing to wait for)"), "", ""),
    ]


def run_large(args: argparse.Namespace, folder: Path) -> list[tuple[str, str, str, str]]:
    """Run 2: about 1 GiB from many machines, no latency: throughput and peak memory."""
    n, files, size = args.large_machines, args.large_files, args.large_size_kb * 1024
    free = shutil.disk_usage(folder).free
    note = ""
    if free < LARGE_MIN_FREE_BYTES:
        scale = free / LARGE_MIN_FREE_BYTES
        files = max(1, int(files * scale))
        note = (f"scaled down to {files} files per machine: {free / 1024**3:.1f} GiB free, "
                f"{LARGE_MIN_FREE_BYTES / 1024**3:.0f} GiB wanted")
        print(f"note: run 2 {note}", file=sys.stderr)
    ids = [f"large-{i:03d}" for i in range(n)]
    written: list[int] = []

    def write(data_dir: Path) -> None:
        say(f"run 2: writing {n} x {files} programs of {size // 1024} KiB ...")
        written.append(write_repeated(data_dir, ids, files, size))

    with stack(folder, ids=ids, latency_ms=0, level=args.level, concurrency=args.concurrency,
               pool=args.pool, worker_count=args.workers, write=write) as s:
        total = written[0]
        say("run 2: measured backup ...")
        with profiled(s.folder, "run2", [*s.workers, s.api], enabled=args.profile):
            run = run_backup(s)
        worker_mb, api_mb = peak_rss_mb(s.workers), s.api.peak_rss_mb()
    p = run.phases
    mb = total / MIB
    return [
        ("RUN 2", f"{n} machines x {files} files x {size // 1024} KiB, latency 0, "
                  f"level {args.level}", "", ""),
        *([("  note", note, "", "")] if note else []),
        ("uncompressed bytes", f"{mb:.1f} MiB", "", ""),
        ("wall (POST -> listed in /api/backups)", f"{run.wall_s:.2f} s", "", ""),
        ("  POST sent -> job created / POST answered", f"{_s(p, 'posted')} / "
                                                        f"{_s(p, 'answered')}", "", ""),
        ("  job created -> first fetch start", _s(p, "queue"), "", ""),
        ("  first fetch start -> last fetch end", _s(p, "fetch"), "", ""),
        ("    first start -> last start", _s(p, "starts"), "", ""),
        ("    target duration median / max", f"{_s(p, 'target_median')} / "
                                             f"{_s(p, 'target_max')}", "", ""),
        ("  last fetch end -> backup registered", _s(p, "assemble"), "", ""),
        ("  backup registered -> listed (its GET answered)", _s(p, "listed"), "", ""),
        ("job counts", _counts(run.job), "", ""),
        ("job settled by", _settled(run), "", ""),
        ("backup", f"{run.backup['status']}, {run.backup['files']} files", "", ""),
        ("throughput", f"{mb / run.wall_s:.1f} MiB/s", "", ""),
        ("  fetch phase / assembly phase",
         f"{_rate(mb, p, 'fetch')} / {_rate(mb, p, 'assemble')}", "", ""),
        ("ZIP size", f"{run.backup['size'] / MIB:.1f} MiB "
                     f"({run.backup['size'] / total:.1%} of input)", "", ""),
        ("CPU during the run: worker / api",
         f"{run.worker_cpu_s:.2f} / {run.api_cpu_s:.2f} s", "", ""),
        ("  worker's main thread / its other threads", _threads(run), "", ""),
        ("  the whole host, every core (busy / available)", _host(run), "", ""),
        ("peak RSS worker (VmHWM)", _mb(worker_mb), f"< {TARGET_RSS_MB:g} MB",
         _verdict(worker_mb is not None and worker_mb < TARGET_RSS_MB)),
        ("peak RSS api (VmHWM)", _mb(api_mb), f"< {TARGET_RSS_MB:g} MB",
         _verdict(api_mb is not None and api_mb < TARGET_RSS_MB)),
    ]


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _host(run: BackupRun) -> str:
    available = run.wall_s * (os.cpu_count() or 1)
    return f"{run.host_cpu_s:.2f} / {available:.2f} s ({run.host_cpu_s / available:.0%})"


def _threads(run: BackupRun) -> str:
    return f"{run.worker_main_cpu_s:.2f} / {run.worker_cpu_s - run.worker_main_cpu_s:.2f} s"


def _counts(job: dict[str, Any]) -> str:
    counts = ", ".join(f"{k} {v}" for k, v in sorted(job["counts"].items()) if v)
    return f"job {job['state']}; targets {counts}"


def _settled(run: BackupRun) -> str:
    return "the bench (stalled: every target final, job running)" if run.settled_by_bench \
        else "its last runner"


def _s(p: dict[str, float], key: str) -> str:
    return f"{p[key]:.2f} s" if key in p else "n/a"


def _rate(mb: float, p: dict[str, float], key: str) -> str:
    return f"{mb / p[key]:.1f} MiB/s" if p.get(key) else "n/a"


def _mb(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.0f} MB"


def _verdict(good: bool) -> str:
    return "MET" if good else "MISSED"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--machines", type=int, default=50)
    parser.add_argument("--files", type=int, default=20, help="Programs per machine")
    parser.add_argument("--size-kb", type=int, default=40, help="KiB per program")
    parser.add_argument("--latency-ms", type=float, default=20.0)
    parser.add_argument("--level", type=int, default=DEFAULT_LEVEL,
                        help="Deflate level of the ZIP (dncq's default)")
    parser.add_argument("--concurrency", type=int, default=64)
    parser.add_argument("--workers", type=int, default=1,
                        help="Worker processes sharing the --concurrency slots")
    parser.add_argument("--pool", default="gevent", choices=["gevent", "threads"],
                        help="Celery pool of the worker")
    parser.add_argument("--large-machines", type=int, default=100)
    parser.add_argument("--large-files", type=int, default=20)
    parser.add_argument("--large-size-kb", type=int, default=512)
    parser.add_argument("--skip-large", action="store_true", help="Run 1 only")
    parser.add_argument("--repeat", type=int, default=3,
                        help="Measured backups of run 1 (and timings of its limit); medians")
    parser.add_argument("--profile", action="store_true",
                        help="py-spy the worker and API during measured runs (implies --keep)")
    parser.add_argument("--trace", action="store_true",
                        help="The mock machines note each operation's start and end during "
                             "run 1's measured backups: how long one takes, and the waits "
                             "between one machine's operations")
    parser.add_argument("--keep", action="store_true", help="Keep the folders (logs, data)")
    args = parser.parse_args()
    keep = args.keep or args.profile
    with bench_folder(keep) as folder:
        print_table(run_latency(args, folder))
    if not args.skip_large:
        with bench_folder(keep) as folder:
            print_table(run_large(args, folder))


if __name__ == "__main__":
    main()
