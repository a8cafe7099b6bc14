"""Benchmark of reading a job: GET /api/jobs/{id} for jobs of 1,000 to 100,000 targets.

Starts its own PostgreSQL and `dncq api`, records jobs of each size straight into the
database (no machine is involved: the figure is the API's), then times the summary alone
(`limit=0`), the first page, a page at the end (`after`), and a walk over every page, and
reads the API's peak RSS after each size. Each figure is also set against the same figure
for the smallest job, measured in the same run: a flat cost reads 1.0x.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import time
import uuid
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import httpx  # noqa: E402

from bench.common import api_alone, bench_folder, migrated_postgres, print_table  # noqa: E402

TARGET_FIRST_PAGE_MS = 200.0  # first page of a 100,000-target job
MACHINES = 2000
INSERT_BATCH = 10_000


def record_job(db_url: str, n: int) -> str:
    """A finished send job of `n` targets over MACHINES machines, inserted in bulk."""
    from sqlalchemy import insert

    from jobs import db
    from jobs.models import Job, JobKind, JobState, Target, TargetState, utcnow

    job_id = uuid.uuid4().hex
    now = utcnow()
    with db.session_scope(db_url) as session:
        session.execute(insert(Job).values(id=job_id, kind=JobKind.SEND, state=JobState.FAILED,
                                           options={}, created_by="bench", created_at=now,
                                           finished_at=now, file_name="P.nc"))
        for start in range(0, n, INSERT_BATCH):
            session.execute(insert(Target), [{
                "job_id": job_id, "position": i, "machine_id": f"m{i % MACHINES:05d}",
                "params": {"fileName": "P.nc"},
                "state": TargetState.FAILED if i % 10 == 0 else TargetState.SUCCEEDED,
                "error_code": 20004 if i % 10 == 0 else 0, "attempts": 1,
                "started_at": now, "finished_at": now,
            } for i in range(start, min(n, start + INSERT_BATCH))])
    return job_id


def timed_ms(client: httpx.Client, path: str, params: dict[str, object], repeat: int
             ) -> tuple[float, dict]:
    """Median wall of `repeat` GETs, and the last answer."""
    walls, body = [], {}
    for _ in range(repeat):
        start = time.perf_counter()
        response = client.get(path, params=params)
        walls.append((time.perf_counter() - start) * 1000)
        response.raise_for_status()
        body = response.json()
    return statistics.median(walls), body


def walk_ms(client: httpx.Client, job_id: str, limit: int) -> tuple[float, int]:
    """Wall of reading every page in turn, and the targets read."""
    start, seen, after = time.perf_counter(), 0, None
    while True:
        params: dict[str, object] = {"limit": limit}
        if after is not None:
            params["after"] = after
        body = client.get(f"/api/jobs/{job_id}", params=params).json()
        seen += len(body["targets"])
        after = body["nextAfter"]
        if after is None:
            return (time.perf_counter() - start) * 1000, seen


def run(args: argparse.Namespace, folder: Path) -> list[tuple[str, str, str, str]]:
    """The whole benchmark; returns the table rows (figure, value, target, verdict)."""
    rows: list[tuple[str, str, str, str]] = []
    with contextlib.ExitStack() as stack:
        db_url = migrated_postgres(stack, folder)
        api, client = api_alone(stack, folder, db_url=db_url, broker_url="memory://")

        base: dict[str, float] = {}
        for n in args.sizes:
            say(f"{n:,} targets: recording ...")
            job_id = record_job(db_url, n)
            path = f"/api/jobs/{job_id}"
            timed_ms(client, path, {}, 1)  # warm-up: the job's rows into the caches
            summary_ms, _ = timed_ms(client, path, {"limit": 0}, args.repeat)
            first_ms, first = timed_ms(client, path, {}, args.repeat)
            last_ms, _ = timed_ms(client, path, {"after": n - 1001}, args.repeat)
            walk, seen = walk_ms(client, job_id, args.walk_limit)
            assert seen == n and first["total"] == n, (seen, first["total"])
            figures = {"summary": summary_ms, "first": first_ms, "last": last_ms}
            base = base or figures
            rss = api.peak_rss_mb()
            rows += [
                (f"{n:,} targets: summary only (limit=0)", f"{summary_ms:.1f} ms",
                 "", f"{summary_ms / base['summary']:.2f}x the smallest"),
                (f"  first page ({len(first['targets'])} targets)", f"{first_ms:.1f} ms",
                 f"< {TARGET_FIRST_PAGE_MS:g} ms" if n >= 100_000 else "",
                 ("met" if first_ms < TARGET_FIRST_PAGE_MS else "NOT met") if n >= 100_000
                 else f"{first_ms / base['first']:.2f}x the smallest"),
                ("  last page (after=n-1001)", f"{last_ms:.1f} ms", "",
                 f"{last_ms / base['last']:.2f}x the smallest"),
                (f"  every page of {args.walk_limit}", f"{walk / 1000:.2f} s",
                 "", f"{walk * 1000 / n:.1f} µs per target"),
                ("  API peak RSS so far", f"{rss:.0f} MB" if rss else "?", "", ""),
            ]
    return rows


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 10_000, 100_000])
    parser.add_argument("--repeat", type=int, default=5, help="GETs per figure (median)")
    parser.add_argument("--walk-limit", type=int, default=1000, help="page size of the walk")
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder")
    args = parser.parse_args()
    with bench_folder(args.keep) as folder:
        print_table(run(args, folder))


if __name__ == "__main__":
    main()
