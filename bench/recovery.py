"""Benchmark of recovery: a worker killed mid-job, until its targets run again on another.

Starts Redis, PostgreSQL, `dncq api` and two `dncq worker --pool gevent`, registers mock
machines slow enough that each target runs for several seconds, and for each of `--kills`
rounds: sends one program to every machine (batchSendFile, answered at once with the job
id), waits until both workers run targets, waits a random moment more (so that the kills
fall at every point of the lease renewals), kills one worker with SIGKILL, and reads the
database until each target it was running has started again on the other worker. Prints
every round's time from the kill to the first and to the last of those restarts, and to
the job's end, with the goal beside them: within one lease period (`DNCQ_LEASE_TTL_S`).
A new worker takes the killed one's place before the next round. Prints figures only; it
asserts nothing.

    python bench/recovery.py [--machines 32] [--latency-ms 5000] [--concurrency 8]
                             [--kills 5] [--lease-ttl-s 30] [--seed 1] [--keep]
"""

from __future__ import annotations

import argparse
import contextlib
import random
import socket
import statistics
import sys
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import httpx  # noqa: E402

from bench.common import (  # noqa: E402
    HTTP_TIMEOUT_S,
    Process,
    bench_folder,
    child_env,
    fleet_yaml,
    gcode,
    print_table,
    wait_for_api,
    wait_for_worker,
)
from tests.servers import RedisServer, free_port, postgres_server  # noqa: E402

RESTART_TIMEOUT_S = 180.0  # a round whose targets have not run again by then is reported so
POLL_S = 0.1


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


@dataclass
class Round:
    """One kill: seconds from it to the first and last restart elsewhere, and the job's end."""

    killed_running: int
    first_s: float | None
    last_s: float | None
    done_s: float | None


def register(url: str, ids: list[str], latency_ms: float, folder: Path) -> None:
    from jobs.db import session_scope
    from jobs.fleet import fleet_file

    path = folder / "fleet.yaml"
    path.write_text(fleet_yaml(ids, latency_ms))
    with session_scope(url) as session:
        fleet_file.import_fleet(session=session,
                                machines=fleet_file.parse_fleet(path.read_text()),
                                data_dir=folder / "data")


def running_on(url: str, job_id: str) -> dict[str, list[int]]:
    """The job's running targets, by the worker (host:pid) that claimed them."""
    from sqlalchemy import select

    from jobs.db import session_scope
    from jobs.models import Target, TargetState

    with session_scope(url) as session:
        rows = session.execute(select(Target.id, Target.claimed_by).where(
            Target.job_id == job_id, Target.state == TargetState.RUNNING)).all()
    found: dict[str, list[int]] = {}
    for target_id, claimed_by in rows:
        found.setdefault(claimed_by or "", []).append(target_id)
    return found


def restarted(url: str, ids: list[int], dead: str, killed_at: datetime
              ) -> dict[int, datetime | None]:
    """Per target: when it started again on another worker after the kill, if it has."""
    from sqlalchemy import select

    from jobs.db import session_scope
    from jobs.models import Target

    with session_scope(url) as session:
        rows = session.execute(select(Target.id, Target.claimed_by, Target.started_at)
                               .where(Target.id.in_(ids))).all()
    return {target_id: started if (claimed and claimed != dead and started is not None
                                   and started > killed_at) else None
            for target_id, claimed, started in rows}


def job_finished_at(url: str, job_id: str) -> datetime | None:
    from sqlalchemy import func, select

    from jobs.db import session_scope
    from jobs.models import Target

    with session_scope(url) as session:
        states = session.execute(select(Target.state).where(Target.job_id == job_id)).all()
        if not states or not all(state.final for (state,) in states):
            return None
        return session.scalar(select(func.max(Target.finished_at))
                              .where(Target.job_id == job_id))


def one_round(client: httpx.Client, url: str, workers: list[Process], ids: list[str],
              content: str, name: str, rng: random.Random, lease_ttl_s: float
              ) -> tuple[Round, int]:
    """Send, kill a worker mid-job, measure; returns the round and the killed worker's index."""
    from jobs.models import utcnow

    response = client.post("/api/cnc/batchSendFile", json={
        "content": content, "targets": [{"machineID": m, "fileName": name} for m in ids]})
    response.raise_for_status()
    job_id = response.headers["X-Dncq-Job"]
    host = socket.gethostname()
    names = {f"{host}:{w.pid}": n for n, w in enumerate(workers)}  # as targets name them
    deadline = time.monotonic() + RESTART_TIMEOUT_S
    while True:
        running = running_on(url, job_id)
        if sum(1 for worker in running if worker in names) == len(workers):
            break
        if time.monotonic() > deadline:
            raise TimeoutError("the two workers did not both run targets")
        time.sleep(POLL_S)
    # The kill falls anywhere between two renewals of the leases (every third of a lease
    # period or less).
    time.sleep(rng.uniform(0.0, lease_ttl_s / 3))
    running = running_on(url, job_id)
    victim_name = max((w for w in running if w in names), key=lambda w: len(running[w]))
    victim = names[victim_name]
    killed_at = utcnow()
    workers[victim].proc.kill()
    workers[victim].proc.wait()
    orphans = running[victim_name]
    say(f"  killed worker {victim} running {len(orphans)} targets")
    first_s = last_s = done_s = None
    while time.monotonic() < deadline:
        again = restarted(url, orphans, victim_name, killed_at)
        starts = [t for t in again.values() if t is not None]
        if starts and first_s is None:
            first_s = (min(starts) - killed_at).total_seconds()
        if len(starts) == len(orphans):
            last_s = (max(starts) - killed_at).total_seconds()
            break
        time.sleep(POLL_S)
    while time.monotonic() < deadline and done_s is None:
        finished = job_finished_at(url, job_id)
        if finished is not None:
            done_s = (finished - killed_at).total_seconds()
        time.sleep(POLL_S)
    return Round(len(orphans), first_s, last_s, done_s), victim


def run(args: argparse.Namespace, folder: Path) -> list[tuple[str, str, str, str]]:
    from jobs import db

    ids = [f"rec-{i:03d}" for i in range(args.machines)]
    content = gcode(20 * 1024)
    rng = random.Random(args.seed)
    with contextlib.ExitStack() as stack:
        redis = RedisServer(folder)
        redis.start()
        stack.callback(redis.kill)
        pg_folder = folder / "pg"
        pg_folder.mkdir()
        url = stack.enter_context(postgres_server(pg_folder)).url
        data_dir = folder / "data"
        data_dir.mkdir()
        db.upgrade(url)
        register(url, ids, args.latency_ms, folder)
        port = free_port()
        env = child_env(data_dir=data_dir, db_url=url, broker_url=redis.url, port=port)
        env["DNCQ_BATCH_WAIT_S"] = "0"  # answer at once: the job runs while it is watched
        env["DNCQ_LEASE_TTL_S"] = f"{args.lease_ttl_s:g}"
        api = Process("api", ["api", "--host", "127.0.0.1", "--port", str(port)], env, folder)
        stack.callback(api.stop)
        started = 0

        def worker() -> Process:
            nonlocal started
            started += 1
            process = Process(f"worker{started}", [
                "worker", "--pool", "gevent", "--concurrency", str(args.concurrency),
                "--loglevel", "WARNING", "-n", f"recovery{started}@%h",
                "--without-mingle", "--without-gossip"], env, folder)
            stack.callback(process.stop)
            return process

        workers = [worker(), worker()]
        client = stack.enter_context(httpx.Client(base_url=f"http://127.0.0.1:{port}",
                                                  timeout=HTTP_TIMEOUT_S))
        wait_for_api(client, api)
        wait_for_worker(redis.url, data_dir, *workers)
        rounds: list[Round] = []
        for n in range(args.kills):
            say(f"round {n + 1} of {args.kills} ...")
            measured, victim = one_round(client, url, workers, ids, content, f"R{n}.NC", rng,
                                         args.lease_ttl_s)
            rounds.append(measured)
            say(f"  first {_s(measured.first_s)}, last {_s(measured.last_s)}, "
                f"job done {_s(measured.done_s)} after the kill")
            workers[victim] = worker()
            wait_for_worker(redis.url, data_dir, *workers)
    ttl = args.lease_ttl_s
    lasts = [r.last_s for r in rounds if r.last_s is not None]
    worst = max(lasts) if len(lasts) == len(rounds) else None
    return [
        ("fleet", f"{args.machines} mock machines @ {args.latency_ms:g} ms per operation; "
                  f"2 gevent workers x {args.concurrency}", "", ""),
        ("lease period (DNCQ_LEASE_TTL_S)", f"{ttl:g} s", "", ""),
        ("targets running on the killed worker", " / ".join(
            str(r.killed_running) for r in rounds), "", ""),
        ("kill -> first of them runs again", " / ".join(_s(r.first_s) for r in rounds), "", ""),
        ("kill -> last of them runs again", " / ".join(_s(r.last_s) for r in rounds), "", ""),
        ("  median / worst", f"{_s(statistics.median(lasts) if lasts else None)} / "
                             f"{_s(worst)}", f"<= {ttl:g} s",
         "MET" if worst is not None and worst <= ttl else "MISSED"),
        ("kill -> the job done", " / ".join(_s(r.done_s) for r in rounds), "", ""),
    ]


def _s(seconds: float | None) -> str:
    return "never" if seconds is None else f"{seconds:.1f} s"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--machines", type=int, default=32)
    parser.add_argument("--latency-ms", type=float, default=5000.0)
    parser.add_argument("--concurrency", type=int, default=8)
    parser.add_argument("--kills", type=int, default=5)
    parser.add_argument("--lease-ttl-s", type=float, default=30.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--keep", action="store_true", help="Keep the folder (logs, data)")
    args = parser.parse_args()
    with bench_folder(args.keep) as folder:
        print_table(run(args, folder))


if __name__ == "__main__":
    main()
