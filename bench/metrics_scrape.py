"""Benchmark of one `/metrics` scrape over a large record: 100,000 targets by default.

Records jobs of every kind straight into SQLite and into a PostgreSQL of its own (no machine
is involved: the figure is the collector's), with their payloads, attempts, backups with
their files, drip-feed runs and machine leases, then times the scrape as Prometheus sees it:
`GET /metrics` through the API app, the median of `--repeat` after one discarded warm-up.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import time
import uuid
from datetime import timedelta
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from bench.common import bench_folder, print_table  # noqa: E402
from tests.servers import postgres_server  # noqa: E402

TARGET_SCRAPE_MS = 500.0  # a scrape every 15-30 s: at most a few per cent of a core
TARGETS_PER_JOB = 1000
MACHINES = 500
INSERT_BATCH = 10_000
API_KEY = "bench-key-0123456789"


def record(db_url: str, targets: int) -> None:
    """Jobs of `TARGETS_PER_JOB` targets each, up to `targets`, of every kind and outcome."""
    from sqlalchemy import insert

    from jobs import db
    from jobs.backup_models import Backup, BackupFile, BackupStatus
    from jobs.models import (
        Job,
        JobKind,
        JobState,
        Machine,
        MachineLease,
        Payload,
        Run,
        RunState,
        Target,
        TargetState,
        utcnow,
    )

    now = utcnow()
    kinds = [JobKind.SEND, JobKind.SEND, JobKind.SEND, JobKind.DELETE, JobKind.BACKUP]
    states = [TargetState.SUCCEEDED] * 7 + [TargetState.FAILED, TargetState.SKIPPED,
                                            TargetState.PENDING]
    with db.session_scope(db_url) as session:
        session.execute(insert(Machine), [
            {"id": f"m{i:05d}", "name": f"M{i}", "model": "Mock", "transport": "mock",
             "options": {}, "tags": [], "enabled": i % 50 != 0} for i in range(MACHINES)])
        payload = uuid.uuid4().hex
        session.execute(insert(Payload).values(id=payload, size=100_000, data=b"",
                                               created_at=now))
        for j in range(0, targets, TARGETS_PER_JOB):
            kind = kinds[(j // TARGETS_PER_JOB) % len(kinds)]
            job_id = uuid.uuid4().hex
            session.execute(insert(Job).values(
                id=job_id, kind=kind, state=JobState.RUNNING, options={}, created_by="bench",
                created_at=now - timedelta(minutes=10), finished_at=None, file_name="P.nc",
                payload_id=payload if kind is JobKind.SEND else None))
            rows = []
            for i in range(j, min(targets, j + TARGETS_PER_JOB)):
                state = states[i % len(states)]
                rows.append({
                    "job_id": job_id, "position": i - j, "machine_id": f"m{i % MACHINES:05d}",
                    "params": {"fileName": "P.nc"}, "state": state, "attempts": 1 + i % 3,
                    "bytes_done": 0, "interrupted": False,
                    "dispatched_at": None if i % 20 == 9 else now,
                    "started_at": None if state is TargetState.PENDING else
                    now - timedelta(seconds=(i % 600) / 10),
                    "finished_at": None if not state.final else now})
            for start in range(0, len(rows), INSERT_BATCH):
                session.execute(insert(Target), rows[start:start + INSERT_BATCH])
            if kind is JobKind.BACKUP:
                backup_id = uuid.uuid4().hex
                session.execute(insert(Backup).values(
                    id=backup_id, job_id=job_id, name=f"BackupFiles-{job_id}.zip",
                    status=BackupStatus.COMPLETE, size=40_000_000, sha256="", file_count=1000,
                    created_at=now))
                session.execute(insert(BackupFile), [
                    {"backup_id": backup_id, "machine_id": f"m{i % MACHINES:05d}",
                     "path": f"O{i:04d}", "archive_path": f"x/O{i:04d}", "size": 40_000,
                     "sha256": ""} for i in range(TARGETS_PER_JOB)])
        session.execute(insert(Run), [
            {"job_id": uuid.uuid4().hex, "position": 0, "machine_id": f"m{i:05d}",
             "program_name": "BIG.NC", "program_id": "x", "state":
             RunState.RUNNING if i < 20 else RunState.SUCCEEDED, "started_at": now,
             "updated_at": now, "lines_sent": 10_000, "lines_total": 20_000, "header": []}
            for i in range(200)])
        session.execute(insert(MachineLease), [
            {"machine_id": f"m{i:05d}", "slot": 0, "group": f"job:{i}", "holder": str(i),
             "expires_at": now + timedelta(minutes=1)} for i in range(100)])


def scrape_ms(db_url: str, folder: Path, repeat: int) -> tuple[float, int]:
    """Median wall of `repeat` scrapes through the API app, and the answer's size."""
    from fastapi.testclient import TestClient

    from jobs.api.app import create_app
    from jobs.settings import AuthMode, Settings

    settings = Settings(data_dir=folder, database_url=db_url, api_key=API_KEY,
                        auth=AuthMode.KEY)
    walls, size = [], 0
    with TestClient(create_app(settings), headers={"X-Api-Key": API_KEY}) as client:
        client.get("/metrics").raise_for_status()  # warm-up: connections, statement cache
        for _ in range(repeat):
            start = time.perf_counter()
            response = client.get("/metrics")
            walls.append((time.perf_counter() - start) * 1000)
            response.raise_for_status()
            size = len(response.content)
    return statistics.median(walls), size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--targets", type=int, default=100_000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--no-postgres", action="store_true")
    parser.add_argument("--keep", action="store_true")
    args = parser.parse_args()

    from jobs import db

    rows = []
    with bench_folder(args.keep) as folder:
        urls = [("SQLite", f"sqlite:///{folder / 'metrics.sqlite3'}")]
        data = folder / "data"
        data.mkdir()
        (folder / "pg").mkdir()
        with (postgres_server(folder / "pg") if not args.no_postgres
              else contextlib.nullcontext()) as server:
            if server is not None:
                urls.append(("PostgreSQL", server.url))
            for name, url in urls:
                db.upgrade(url)
                started = time.perf_counter()
                record(url, args.targets)
                print(f"{name}: recorded {args.targets} targets in "
                      f"{time.perf_counter() - started:.1f} s", file=sys.stderr)
                wall, size = scrape_ms(url, data, args.repeat)
                rows.append((f"{name}: one scrape at {args.targets} targets", f"{wall:.0f} ms",
                             f"< {TARGET_SCRAPE_MS:.0f} ms",
                             "met" if wall < TARGET_SCRAPE_MS else "NOT met"))
                rows.append((f"{name}: answer size", f"{size / 1024:.1f} KiB", "", ""))
    print_table(rows)


if __name__ == "__main__":
    main()
