"""Benchmark of a worker's memory after faults: the same send job with and without outages.

Starts Redis and PostgreSQL of its own, registers mock machines with `latency_ms`, and runs
one send job (`--targets` over `--machines`) on two fresh `dncq worker --pool gevent`
processes without faults, then the same job on two more while PostgreSQL is stopped
(immediate) and started again `--outages` times and Redis is killed and started once. It
prints each worker's VmRSS and VmHWM before the job, at its peak and at the end, and what
`bench/memory_probe` reads inside it at the end (glibc's heap, Python's blocks, objects,
greenlets, pools) before and after `malloc_trim(0)`. Prints figures only; asserts nothing.

    python bench/fault_memory.py [--machines 60] [--targets 300] [--latency-ms 3000]
                                 [--concurrency 16] [--outage-s 30 20 40] [--tracemalloc N]
                                 [--env NAME=VALUE ...] [--keep]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from bench.common import (  # noqa: E402
    Process,
    bench_folder,
    child_env,
    fleet_yaml,
    gcode,
    print_table,
    wait_for_worker,
)
from tests.servers import PostgresServer, RedisServer, free_port, postgres_of_its_own  # noqa: E402

PROBE = REPO / "bench" / "memory_probe"
PROBE_TIMEOUT_S = 120.0
SETTLE_S = 10.0  # after the job ends, before the end figures: follow-ups and reaper passes
BETWEEN_FAULTS_S = 10.0
JOB_TIMEOUT_S = 1800.0


def status_kb(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM of a process, in kB."""
    found = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            found[key] = int(value.split()[0])
    return found


def probe(folder: Path, worker: Process, label: str) -> dict[str, Any]:
    """Ask the worker's probe for its figures under `label` and wait for the answer."""
    out = folder / f"{worker.pid}-{label}.json"
    (folder / f"{worker.pid}.ask").write_text(label)
    deadline = time.monotonic() + PROBE_TIMEOUT_S
    while not out.exists():
        worker.check_alive()
        if time.monotonic() > deadline:
            raise TimeoutError(f"{worker.name} did not answer the probe {label}")
        time.sleep(0.2)
    return dict(json.loads(out.read_text()))


def register(db_url: str, ids: list[str], latency_ms: float, folder: Path) -> None:
    from jobs.db import session_scope
    from jobs.fleet import fleet_file

    path = folder / "fleet.yaml"
    path.write_text(fleet_yaml(ids, latency_ms))
    with session_scope(db_url) as session:
        fleet_file.import_fleet(session=session,
                                machines=fleet_file.parse_fleet(path.read_text()),
                                data_dir=folder / "data")


def submit(settings: Any, ids: list[str], n: int, prefix: str, content: bytes) -> str:
    """A send job of `n` targets going round the machines, queued as the API does it."""
    from jobs import db, rollout, service
    from jobs.job_options import JobOptions
    from jobs.models import JobKind

    raw = [{"machineID": ids[i % len(ids)], "fileName": f"{prefix}{i // len(ids)}.NC"}
           for i in range(n)]
    with db.session_scope(settings.resolved_database_url) as session:
        payload_id = service.store_payload(session=session, data=content)
        return rollout.submit(session=session, settings=settings, kind=JobKind.SEND,
                              targets=[service.TargetIn.parse(t) for t in raw],
                              options=JobOptions(), payload_id=payload_id).id


def states(db_url: str, job_id: str) -> dict[str, int] | None:
    """Targets by state, or None while the database cannot be reached."""
    from sqlalchemy import func, select

    from jobs import db
    from jobs.models import Target

    try:
        with db.session_scope(db_url) as session:
            rows = session.execute(select(Target.state, func.count()).where(
                Target.job_id == job_id).group_by(Target.state)).all()
    except Exception as exc:
        if db.unreachable(exc):
            return None
        raise
    return {str(state.value): int(n) for state, n in rows}


FINAL = ("succeeded", "failed", "skipped", "cancelled")


class Watch:
    """Samples the workers' RSS every second while waiting; keeps the highest seen."""

    def __init__(self, workers: list[Process]) -> None:
        self.workers = workers
        self.peak_rss_kb = {w.name: 0 for w in workers}

    def sleep(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            for w in self.workers:
                w.check_alive()
                rss = status_kb(w.pid)["VmRSS"]
                self.peak_rss_kb[w.name] = max(self.peak_rss_kb[w.name], rss)
            time.sleep(min(1.0, max(0.0, deadline - time.monotonic())))

    def until_final(self, db_url: str, job_id: str, n: int) -> dict[str, int]:
        deadline = time.monotonic() + JOB_TIMEOUT_S
        while True:
            counts = states(db_url, job_id)
            if counts is not None and sum(counts.get(s, 0) for s in FINAL) == n:
                return counts
            if time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} not final: {counts}")
            self.sleep(1.0)


def faults(watch: Watch, pg: PostgresServer, redis: RedisServer, outages_s: list[float],
           running: Callable[[], bool], say: Callable[[str], None],
           at_outage_end: Callable[[int], object]) -> list[str]:
    """PostgreSQL stopped and started for each outage, Redis killed and started after the
    first; each only while the job still runs. Returns what was done."""
    done: list[str] = []
    for i, outage_s in enumerate(outages_s):
        if not running():
            break
        say(f"  PostgreSQL stopped for {outage_s:g} s")
        pg.stop()
        watch.sleep(outage_s)
        at_outage_end(i + 1)
        pg.start()
        done.append(f"PostgreSQL {outage_s:g} s")
        watch.sleep(BETWEEN_FAULTS_S)
        if i == 0 and running():
            say("  Redis killed and started")
            redis.kill()
            watch.sleep(2.0)
            redis.start()
            done.append("Redis")
            watch.sleep(BETWEEN_FAULTS_S)
    return done


def run_job(args: argparse.Namespace, *, label: str, folder: Path, env: dict[str, str],
            settings: Any, ids: list[str], content: bytes, pg: PostgresServer,
            redis: RedisServer, with_faults: bool) -> list[dict[str, Any]]:
    """Two fresh workers run one job (with faults if asked); each worker's figures."""
    say = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    probes = folder / "probes"
    probes.mkdir(exist_ok=True)
    env = {**env, "PYTHONPATH": f"{PROBE}:{env['PYTHONPATH']}",
           "DNCQ_BENCH_PROBE_DIR": str(probes)}
    if args.tracemalloc:
        env["DNCQ_BENCH_TRACEMALLOC"] = str(args.tracemalloc)
    workers = [Process(f"{label}-{i}", ["worker", "--pool", "gevent", "--concurrency",
                                        str(args.concurrency), "--loglevel", "INFO",
                                        "-n", f"{label}-{i}@%h", "--without-mingle",
                                        "--without-gossip"], env, folder)
               for i in (1, 2)]
    try:
        wait_for_worker(redis.url, settings.data_dir, *workers)
        before = {w.name: probe(probes, w, "before") for w in workers}
        watch = Watch(workers)
        say(f"{label}: {args.targets} targets ...")
        started = time.monotonic()
        job_id = submit(settings, ids, args.targets, label.upper()[:4], content)
        done: list[str] = []
        if with_faults:
            watch.sleep(args.first_fault_s)
            done = faults(watch, pg, redis, args.outage_s, lambda: not _final(
                settings.resolved_database_url, job_id, args.targets), say,
                lambda i: [probe(probes, w, f"outage-{i}") for w in workers])
        counts = watch.until_final(settings.resolved_database_url, job_id, args.targets)
        wall_s = time.monotonic() - started
        say(f"  final after {wall_s:.0f} s: {counts}")
        watch.sleep(SETTLE_S)
        rows = []
        for w in workers:
            end = probe(probes, w, "end")
            trimmed = probe(probes, w, "trim-end")
            rows.append({"worker": w.name, "faults": ", ".join(done) or "none",
                         "wall_s": wall_s, "states": counts, "before": before[w.name],
                         "peak_rss_kb": watch.peak_rss_kb[w.name],
                         "hwm_kb": status_kb(w.pid)["VmHWM"], "end": end, "trim": trimmed})
        return rows
    finally:
        for w in workers:
            w.stop()


def _final(db_url: str, job_id: str, n: int) -> bool:
    counts = states(db_url, job_id)
    return counts is not None and sum(counts.get(s, 0) for s in FINAL) == n


def mb(kb: int | float) -> str:
    return f"{kb / 1024:.0f}"


def table(rows: list[dict[str, Any]]) -> list[tuple[str, str, str, str]]:
    out: list[tuple[str, str, str, str]] = []
    for r in rows:
        name = r["worker"]
        end, trim = r["end"], r["trim"]
        heap, after = trim["heap"], trim["heap_after_trim"]
        out += [
            (f"{name}: faults", r["faults"], "", f"{r['wall_s']:.0f} s, {r['states']}"),
            (f"{name}: RSS before / peak seen / end, MB",
             f"{mb(r['before']['memory']['VmRSS_kb'])} / {mb(r['peak_rss_kb'])} / "
             f"{mb(end['memory']['VmRSS_kb'])}", "", ""),
            (f"{name}: VmHWM, MB", mb(r["hwm_kb"]), "", ""),
            (f"{name}: anonymous at end, MB", mb(end["memory"]["smaps_Anonymous_kb"]), "", ""),
            (f"{name}: glibc heap in use / free, MB",
             f"{heap['in_use_bytes'] / 2**20:.0f} / {heap['free_bytes'] / 2**20:.0f}", "",
             f"arena {heap['arena_bytes'] / 2**20:.0f} MB, mmapped "
             f"{heap['mmapped_bytes'] / 2**20:.0f} MB"),
            (f"{name}: RSS after malloc_trim(0), MB",
             mb(trim["memory_after_trim"]["VmRSS_kb"]), "",
             f"heap free {after['free_bytes'] / 2**20:.0f} MB after"),
            (f"{name}: Python blocks / gc objects",
             f"{end['allocated_blocks']} / {end['gc_objects']}", "",
             f"before {r['before']['allocated_blocks']} / {r['before']['gc_objects']}"),
            (f"{name}: threads / greenlets", f"{end['threads']} / {end['greenlets']}", "",
             f"before {r['before']['threads']} / {r['before']['greenlets']}"),
        ]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--machines", type=int, default=60)
    parser.add_argument("--targets", type=int, default=300)
    parser.add_argument("--latency-ms", type=float, default=3000.0)
    parser.add_argument("--concurrency", type=int, default=16)
    parser.add_argument("--size-kb", type=int, default=20)
    parser.add_argument("--outage-s", type=float, nargs="*", default=[30.0, 20.0, 40.0])
    parser.add_argument("--first-fault-s", type=float, default=10.0,
                        help="seconds into the job before the first outage")
    parser.add_argument("--tracemalloc", type=int, default=0, metavar="FRAMES")
    parser.add_argument("--env", action="append", default=[], metavar="NAME=VALUE",
                        help="more environment for the workers (e.g. MALLOC_ARENA_MAX=2)")
    parser.add_argument("--skip-fresh", action="store_true")
    parser.add_argument("--keep", action="store_true")
    args = parser.parse_args()

    from jobs import db
    from jobs.settings import Settings

    ids = [f"fm-{i:03d}" for i in range(args.machines)]
    content = gcode(args.size_kb * 1024).encode("ascii")
    with bench_folder(args.keep) as folder, contextlib.ExitStack() as stack:
        redis = RedisServer(folder)
        redis.start()
        stack.callback(redis.kill)
        pg = stack.enter_context(postgres_of_its_own())
        data_dir = folder / "data"
        data_dir.mkdir()
        db.upgrade(pg.url)
        register(pg.url, ids, args.latency_ms, folder)
        settings = Settings(data_dir=data_dir, database_url=pg.url, broker_url=redis.url)
        env = child_env(data_dir=data_dir, db_url=pg.url, broker_url=redis.url,
                        port=free_port())
        env.update(dict(e.split("=", 1) for e in args.env))
        common: dict[str, Any] = {"folder": folder, "env": env, "settings": settings,
                                  "ids": ids, "content": content, "pg": pg, "redis": redis}
        rows = [] if args.skip_fresh else run_job(args, label="fresh", with_faults=False,
                                                  **common)
        rows += run_job(args, label="faults", with_faults=True, **common)
        (folder / "figures.json").write_text(json.dumps(rows, indent=1))
        print(f"{args.targets} targets over {args.machines} mock machines, latency "
              f"{args.latency_ms:g} ms, 2 gevent workers x {args.concurrency}; "
              f"figures in {folder / 'figures.json'}")
        print_table(table(rows))


if __name__ == "__main__":
    main()
