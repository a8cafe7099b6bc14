"""Benchmark of batchSendFile: one program to a fleet of mock machines, against its ideal.

Starts Redis, PostgreSQL, `dncq api` and one `dncq worker --pool gevent`, registers N mock
machines, and prints wall time, ideal time, the sequential baseline, per-target overhead and
peak memory, then the same batch as plain Celery tasks that only sleep (bench/plain_celery.py)
for reference. The measured batches run `--repeat` times and the median is reported, with
every run beside it. Prints figures only; it asserts nothing.

    python bench/batch_send.py [--machines 500] [--latency-ms 200] [--concurrency 64]
                               [--workers 1] [--targets-per-machine 1]
                               [--warmup-machines N] [--measured-machines N]
                               [--skip-plain]
                               [--pool gevent|threads|prefork] [--size-kb 100] [--repeat 3]
                               [--profile] [--keep]

`--workers W` starts W `dncq worker` processes of `--concurrency` each (and W plain Celery
workers for the reference); `--targets-per-machine K` sends K files to every machine in each
batch, which a machine takes one at a time: the ideal is then t1 x max(K, ceil(N x K / slots)).
For a fleet too large to send to three times and more, `--warmup-machines M` warms up on M
machines only, `--measured-machines M` sends the measured batches to the first M machines
only (the whole fleet stays registered, so what grows with the fleet is still paid),
`--latency-ms 0` makes the measured batches the latency-0 ones too, and `--skip-plain` leaves
out the plain Celery reference.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import math
import statistics
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import httpx  # noqa: E402

from bench import plain_celery, statements  # noqa: E402
from bench.common import (  # noqa: E402
    HTTP_TIMEOUT_S,
    Process,
    bench_folder,
    child_env,
    cpu_s,
    fleet_yaml,
    gcode,
    median_run,
    postgres_cpu_s,
    print_table,
    profiled,
    tree_cpu_s,
    wait_for_api,
    walls_text,
)
from bench.statements import STATEMENT_SETTINGS  # noqa: E402
from tests.servers import RedisServer, free_port, postgres_server  # noqa: E402
from worker.transports import mock_state  # noqa: E402

SEQUENTIAL_SAMPLE = 100  # targets the sequential baseline really runs; scaled to N
EMPTY_TASKS = 2000  # plain Celery's rate of tasks that do nothing

# What the figures should reach.
TARGET_IDEAL_RATIO = 1.15  # one worker (the speed issue's goal)
TARGET_IDEAL_RATIO_MANY = 1.2  # several workers: 10,000 targets on 4 (same issue)
TARGET_SPEEDUP = 25.0
TARGET_OVERHEAD_MS = 1.5


def register(url: str, ids: list[str], latency_ms: float, folder: Path) -> None:
    """Import (or update) the bench fleet through the registry service."""
    from jobs.db import session_scope
    from jobs.fleet import fleet_file

    path = folder / f"fleet-{latency_ms:g}ms.yaml"
    path.write_text(fleet_yaml(ids, latency_ms, trace=True))
    with session_scope(url) as session:
        fleet_file.import_fleet(session=session,
                                machines=fleet_file.parse_fleet(path.read_text()),
                                data_dir=folder / "data")


def batch_send(client: httpx.Client, content: str, targets: list[tuple[str, str]]
               ) -> tuple[float, list[dict[str, Any]], str]:
    """POST batchSendFile; returns wall seconds, the results and the job id."""
    body = {"content": content,
            "targets": [{"machineID": m, "fileName": name} for m, name in targets]}
    started = time.perf_counter()
    response = client.post("/api/cnc/batchSendFile", json=body)
    wall_s = time.perf_counter() - started
    response.raise_for_status()
    return wall_s, response.json(), response.headers.get("X-Dncq-Job", "")


def ok_count(results: list[dict[str, Any]]) -> int:
    return sum(1 for r in results if r.get("errorCode") == 0)


def target_spread(job: dict[str, Any]) -> dict[str, float]:
    """From the job's per-target times: first start to last finish, median and max target."""
    starts, ends, durations = [], [], []
    for t in job["targets"]:
        if t["startedAt"] and t["finishedAt"]:
            s, e = datetime.fromisoformat(t["startedAt"]), datetime.fromisoformat(t["finishedAt"])
            starts.append(s)
            ends.append(e)
            durations.append((e - s).total_seconds())
    if not starts:
        return {}
    created = datetime.fromisoformat(job["createdAt"])
    return {
        "created_to_first_start_s": (min(starts) - created).total_seconds(),
        "first_start_to_last_start_s": (max(starts) - min(starts)).total_seconds(),
        "first_start_to_last_finish_s": (max(ends) - min(starts)).total_seconds(),
        "median_target_s": statistics.median(durations),
        "max_target_s": max(durations),
    }


def peak_running(job: dict[str, Any]) -> int:
    """The most targets of the job running at the same moment (startedAt to finishedAt: from
    its claim, which a gevent worker makes while its operation still waits for a slot)."""
    when = datetime.fromisoformat
    return mock_state.most_at_once((when(t["startedAt"]), when(t["finishedAt"]))
                                   for t in job["targets"] if t["startedAt"] and t["finishedAt"])


def db_transactions(url: str) -> int:
    """Transactions the database committed or rolled back so far (all clients)."""
    from sqlalchemy import text

    from jobs.db import engine_for

    with engine_for(url).connect() as conn:
        conn.execute(text("SELECT pg_stat_force_next_flush()"))
        return int(conn.scalar(text(
            "SELECT xact_commit + xact_rollback FROM pg_stat_database "
            "WHERE datname = current_database()")))


class Meter:
    """CPU of worker, API and PostgreSQL, and DB transactions, over one batch."""

    def __init__(self, workers: list[Process], api: Process, pgdata: Path, url: str) -> None:
        self.workers, self.api, self.pgdata, self.url = workers, api, pgdata, url

    def read(self) -> tuple[float, float, float, int]:
        time.sleep(1.0)  # let the statistics collector catch up
        return (sum(tree_cpu_s(w.pid) for w in self.workers), cpu_s(self.api.pid),
                postgres_cpu_s(self.pgdata), db_transactions(self.url))

    @contextlib.contextmanager
    def measure(self, into: dict[str, float]) -> Iterator[None]:
        before = self.read()
        yield
        after = self.read()
        # The two 1 s pauses add a few reaper passes to the counts: a small overcount.
        for key, b, a in zip(("worker_cpu_s", "api_cpu_s", "pg_cpu_s", "db_xacts"),
                             before, after, strict=True):
            into[key] = a - b


@dataclass
class Batch:
    """One measured batch: its wall time and what the job and the meters recorded."""

    wall_s: float
    ok: int
    cost: dict[str, float]
    spread: dict[str, float]
    peak: int  # targets claimed (running in the database) at once
    operations: int  # machine operations at once, from the machines' traces


def targets_of(ids: list[str], file_name: str, per_machine: int) -> list[tuple[str, str]]:
    """`per_machine` targets on each machine: `file_name`, or `STEM_1.NC`, `STEM_2.NC`..."""
    if per_machine == 1:
        return [(m, file_name) for m in ids]
    stem, dot, ext = file_name.partition(".")
    return [(m, f"{stem}_{k}{dot}{ext}") for k in range(1, per_machine + 1) for m in ids]


def measured_batch(client: httpx.Client, meter: Meter, content: str, ids: list[str],
                   file_name: str, *, folder: Path, profile: bool,
                   per_machine: int = 1) -> Batch:
    """One batchSendFile of `file_name` to every machine, metered (and profiled if asked)."""
    targets = targets_of(ids, file_name, per_machine)
    print(f"measured: {len(targets)} targets, {file_name} ...", file=sys.stderr, flush=True)
    cost: dict[str, float] = {}
    since = time.time()
    with meter.measure(cost), profiled(folder, file_name.lower(), [*meter.workers, meter.api],
                                       enabled=profile):
        wall_s, results, job_id = batch_send(client, content, targets)
    job = whole_job(client, job_id)
    operations = mock_state.most_at_once(
        mock_state.traced([folder / "data" / "mock" / m for m in ids], since=since))
    return Batch(wall_s, ok_count(results), cost, target_spread(job), peak_running(job),
                 operations)


def whole_job(client: httpx.Client, job_id: str) -> dict[str, Any]:
    """The job with every target: its view's pages one after another."""
    job = client.get(f"/api/jobs/{job_id}", params={"limit": 1000}).raise_for_status().json()
    targets = list(job["targets"])
    while job.get("nextAfter") is not None:
        job = client.get(f"/api/jobs/{job_id}", params={
            "limit": 1000, "after": job["nextAfter"]}).raise_for_status().json()
        targets += job["targets"]
    return {**job, "targets": targets}


def transport_send(specs: list[Any], data: bytes, file_name: str, data_dir: Path) -> float:
    """The per-target operations, run in-process one after another; seconds in all."""
    from jobs.fleet import door
    from jobs.fleet.rules import FANUC_HEAD_BYTES

    started = time.perf_counter()
    for spec in specs:
        with door.open_files(spec, data_dir=data_dir) as files:
            ref = files.send_ref(file_name, None, None, data[:FANUC_HEAD_BYTES])
            files.send(ref, io.BytesIO(data))
    return time.perf_counter() - started


def run(args: argparse.Namespace, folder: Path) -> list[tuple[str, str, str, str]]:
    """The whole benchmark; returns the table rows (figure, value, target, verdict)."""
    from jobs import db
    from jobs.fleet import registry
    from jobs.settings import Settings

    n, conc, k, workers_n = (args.machines, args.concurrency, args.targets_per_machine,
                             args.workers)
    fleet = [f"bench-{i:04d}" for i in range(n)]
    ids = fleet[:args.measured_machines] if args.measured_machines else fleet
    total = len(ids) * k  # targets in each batch
    content = gcode(args.size_kb * 1024)
    data = content.encode("ascii")
    rows: list[tuple[str, str, str, str]] = []

    with contextlib.ExitStack() as stack:
        redis = RedisServer(folder)
        redis.start()
        stack.callback(redis.kill)
        pg_folder = folder / "pg"
        pg_folder.mkdir()
        db_url = stack.enter_context(postgres_server(
            pg_folder, STATEMENT_SETTINGS if args.statements else None)).url
        data_dir = folder / "data"
        data_dir.mkdir()
        db.upgrade(db_url)
        if args.statements:
            statements.install(db_url)
        register(db_url, fleet, args.latency_ms, folder)
        settings = Settings(data_dir=data_dir, database_url=db_url)

        port = free_port()
        env = child_env(data_dir=data_dir, db_url=db_url, broker_url=redis.url, port=port)
        api = Process("api", ["api", "--host", "127.0.0.1", "--port", str(port)], env, folder)
        stack.callback(api.stop)
        workers = []
        for i in range(workers_n):
            worker = Process(f"worker{i}" if workers_n > 1 else "worker",
                             ["worker", "--pool", args.pool, "--concurrency", str(conc),
                              "--loglevel", "WARNING", "-n", f"bench{i}@%h",
                              "--without-mingle", "--without-gossip"], env, folder)
            stack.callback(worker.stop)
            workers.append(worker)
        print(f"folder {folder}  api pid {api.pid}  worker pids "
              f"{' '.join(str(w.pid) for w in workers)}", flush=True)

        client = stack.enter_context(httpx.Client(base_url=f"http://127.0.0.1:{port}",
                                                  timeout=HTTP_TIMEOUT_S))
        wait_for_api(client, api)
        for worker in workers:
            worker.check_alive()

        say = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
        warm_ids = ids[:args.warmup_machines] if args.warmup_machines else ids
        say(f"warm-up: {len(warm_ids) * k} targets ...")
        warm_s, results, _ = batch_send(client, content, targets_of(warm_ids, "WARMUP.NC", k))
        say(f"  {warm_s:.2f} s, {ok_count(results)}/{len(warm_ids) * k} ok")

        meter = Meter(workers, api, pg_folder / "pgdata", db_url)
        if args.statements:
            statements.reset(db_url)
        measured = [measured_batch(client, meter, content, ids, f"BENCH{i}.NC", folder=folder,
                                   profile=args.profile, per_machine=k)
                    for i in range(args.repeat)]
        if args.statements:
            statements.report(db_url, top=args.statements,
                              targets=len(ids) * k * len(measured))
        mid = median_run(measured)
        wall_s, ok, cost, spread, peak = mid.wall_s, mid.ok, mid.cost, mid.spread, mid.peak
        operations = max(m.operations for m in measured)

        say("t1: one target alone ...")
        t1_api_s, t1_results, _ = batch_send(client, content, [(ids[0], "T1.NC")])
        with db.session_scope(db_url) as session:
            specs = [registry.get(session=session, machine_id=m)
                     for m in ids[:max(2, SEQUENTIAL_SAMPLE)]]
        t1_transport_s = transport_send(specs[1:2], data, "T1.NC", data_dir)
        slots = conc * workers_n
        ideal_s = t1_transport_s * max(k, math.ceil(total / slots))

        sample = specs[:SEQUENTIAL_SAMPLE]
        say(f"sequential baseline: {len(sample)} targets in-process ...")
        seq_sample_s = transport_send(sample, data, "SEQ.NC", settings.data_dir)
        seq_s = seq_sample_s * total / len(sample)

        if args.latency_ms == 0:  # the measured batches were these already
            zeros = measured
        else:
            say(f"overhead: {total} targets at latency 0, {args.repeat} times ...")
            register(db_url, fleet, 0, folder)
            zeros = [measured_batch(client, meter, content, ids, f"ZERO{i}.NC", folder=folder,
                                    profile=args.profile, per_machine=k)
                     for i in range(args.repeat)]
        zero = median_run(zeros)
        zero_s, zero_ok, zero_cost, zero_spread = zero.wall_s, zero.ok, zero.cost, zero.spread
        overhead_ms = zero_s / total * 1000

        worker_mbs = [w.peak_rss_mb() for w in workers]
        worker_mb = max((mb for mb in worker_mbs if mb is not None), default=None)
        api_mb = api.peak_rss_mb()

        for worker in workers:
            worker.stop()  # the reference runs alone, like dncq's workers did
        plain_s = empty_s = None
        if not args.skip_plain:
            say(f"plain Celery: {total} tasks that sleep {t1_transport_s * 1000:.0f} ms, "
                f"{EMPTY_TASKS} empty ...")
            with plain_celery.plain_worker(redis.url, pool=args.pool, concurrency=conc,
                                           folder=folder, workers=workers_n):
                plain_celery.run_batch(redis.url, tasks=total,
                                       ms=t1_transport_s * 1000)  # warm-up
                plain_s = plain_celery.run_batch(redis.url, tasks=total,
                                                 ms=t1_transport_s * 1000)
                empty_s = plain_celery.run_batch(redis.url, tasks=EMPTY_TASKS, ms=0)

        def verdict(good: bool) -> str:
            return "MET" if good else "MISSED"

        ratio = wall_s / ideal_s
        ideal_goal = TARGET_IDEAL_RATIO if workers_n == 1 else TARGET_IDEAL_RATIO_MANY
        speedup = seq_s / wall_s
        rows += [
            ("machines x latency x concurrency x workers",
             f"{n} x {args.latency_ms:g} ms x {conc} x {workers_n}", "", ""),
            ("machines the measured batches go to", f"{len(ids)} of {n}", "", ""),
            ("targets per batch", f"{total} ({k} per machine)", "", ""),
            ("payload", f"{len(data) / 1024:.1f} KB G-code, {content.count(chr(10))} lines",
             "", ""),
            (f"warm-up batch (discarded), {len(warm_ids) * k} targets", f"{warm_s:.2f} s",
             "", ""),
            (f"measured batch wall, median of {len(measured)}",
             f"{wall_s:.2f} s  ({ok}/{total} errorCode 0; runs {walls_text(measured)})", "", ""),
            ("  job created -> first target start", _s(spread, "created_to_first_start_s"),
             "", ""),
            ("  first start -> last start", _s(spread, "first_start_to_last_start_s"), "", ""),
            ("  first start -> last finish", _s(spread, "first_start_to_last_finish_s"), "", ""),
            ("  target duration median / max",
             f"{_s(spread, 'median_target_s')} / {_s(spread, 'max_target_s')}", "", ""),
            ("  most machine operations at once (mock traces, every run)",
             f"{operations} (concurrency {conc})", "", ""),
            ("  most targets claimed at once (database)", f"{peak} ({args.pool} pool)", "", ""),
            *_cost_rows(cost, total),
            ("t1 via API (1 target, batchSendFile)",
             f"{t1_api_s * 1000:.0f} ms ({ok_count(t1_results)}/1 ok)", "", ""),
            ("t1 transport (in-process, one send)", f"{t1_transport_s * 1000:.0f} ms", "", ""),
            (f"ideal = t1_transport x max({k}, ceil({total}/{slots}))", f"{ideal_s:.2f} s",
             "", ""),
            ("wall / ideal", f"{ratio:.2f}x", f"<= {ideal_goal}x",
             verdict(ratio <= ideal_goal)),
            (f"sequential baseline ({len(sample)} run, scaled to {total})",
             f"{seq_s:.1f} s  ({seq_sample_s:.2f} s measured)", "", ""),
            ("speed-up = baseline / wall", f"{speedup:.1f}x", f">= {TARGET_SPEEDUP:g}x",
             verdict(speedup >= TARGET_SPEEDUP)),
            (f"latency-0 batch wall, median of {len(zeros)}",
             f"{zero_s:.2f} s  ({zero_ok}/{total} errorCode 0; runs {walls_text(zeros)})", "", ""),
            ("  latency-0 target duration median",
             _s(zero_spread, "median_target_s", ms=True), "", ""),
            *_cost_rows(zero_cost, total),
            ("per-target overhead = wall / N", f"{overhead_ms:.1f} ms",
             f"< {TARGET_OVERHEAD_MS:g} ms", verdict(overhead_ms < TARGET_OVERHEAD_MS)),
            ("peak RSS worker (VmHWM" + (f", the largest of {workers_n})" if workers_n > 1
                                          else ")"), _mb(worker_mb), "", ""),
            ("peak RSS api (VmHWM)", _mb(api_mb), "", ""),
        ]
        if plain_s is not None and empty_s is not None:
            rows += [
                (f"plain Celery, {total} tasks sleeping t1 ({args.pool} x {conc} x "
                 f"{workers_n})", f"{plain_s:.2f} s = {plain_s / ideal_s:.2f}x ideal", "", ""),
                ("  what dncq adds per target",
                 f"{(wall_s - plain_s) / total * 1000:.1f} ms of wall", "", ""),
                ("plain Celery, empty tasks", f"{EMPTY_TASKS / empty_s:.0f} per second",
                 "", ""),
                # The overhead in this host's own unit: the goal of 1.5 ms was set where an
                # empty task took 0.8 ms; this host's speed moves by half from day to day.
                ("per-target overhead / one empty Celery task",
                 f"{overhead_ms / (empty_s / EMPTY_TASKS * 1000):.2f}x", "", ""),
            ]
    return rows


def _cost_rows(cost: dict[str, float], n: int) -> list[tuple[str, str, str, str]]:
    per = {k: v / n for k, v in cost.items()}
    return [
        ("  CPU per target: worker / api / postgres",
         f"{per['worker_cpu_s'] * 1000:.1f} / {per['api_cpu_s'] * 1000:.1f} / "
         f"{per['pg_cpu_s'] * 1000:.1f} ms", "", ""),
        ("  DB transactions per target", f"{per['db_xacts']:.1f}", "", ""),
    ]


def _s(spread: dict[str, float], key: str, *, ms: bool = False) -> str:
    if key not in spread:
        return "n/a"
    return f"{spread[key] * 1000:.1f} ms" if ms else f"{spread[key]:.2f} s"


def _mb(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.0f} MB"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--machines", type=int, default=500)
    parser.add_argument("--latency-ms", type=float, default=200.0)
    parser.add_argument("--concurrency", type=int, default=64)
    parser.add_argument("--workers", type=int, default=1,
                        help="dncq worker processes, each of --concurrency")
    parser.add_argument("--targets-per-machine", type=int, default=1,
                        help="files sent to every machine in each batch")
    parser.add_argument("--pool", default="gevent", choices=["gevent", "threads", "prefork"],
                        help="Celery pool of the worker (prefork: one process per slot)")
    parser.add_argument("--size-kb", type=int, default=100)
    parser.add_argument("--repeat", type=int, default=3,
                        help="Measured batches at each latency; the median one is reported")
    parser.add_argument("--warmup-machines", type=int, default=0,
                        help="warm up on the first N machines only (default: all)")
    parser.add_argument("--measured-machines", type=int, default=0,
                        help="send the measured batches to the first N machines (default: all)")
    parser.add_argument("--skip-plain", action="store_true",
                        help="leave out the plain Celery reference")
    parser.add_argument("--statements", type=int, default=0, metavar="N",
                        help="print the N SQL statements that took PostgreSQL the most time "
                             "during the measured batches (pg_stat_statements)")
    parser.add_argument("--keep", action="store_true", help="Keep the folder (logs, data)")
    parser.add_argument("--profile", action="store_true",
                        help="py-spy worker and API during the measured batches (implies --keep)")
    args = parser.parse_args()
    with bench_folder(args.keep or args.profile) as folder:
        rows = run(args, folder)
    print_table(rows)


if __name__ == "__main__":
    main()
