"""Benchmark of making jobs in fleets of 1,000 to 100,000 machines: POST /api/jobs.

Starts its own PostgreSQL, Redis and `dncq api` (no worker: nothing runs the jobs, the
figure is the API's, and the queue is emptied before each request), registers each fleet
size straight into the database, then times `POST /api/jobs` until its 202: a job naming
one machine by id, the same with text that each machine gets in its own encoding, and a
job for every machine of one tag (half the fleet). Each figure is set against the same
figure for the smallest fleet, measured in the same run: a request that names one machine
should cost the same in any fleet, and a fleet-wide one the same per target.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import httpx  # noqa: E402

from bench.common import api_alone, bench_folder, migrated_postgres, print_table  # noqa: E402
from tests.servers import redis_server  # noqa: E402

TARGET_RATIO = 1.1  # the largest fleet's figure over the smallest's
INSERT_BATCH = 10_000


def register(db_url: str, start: int, stop: int) -> None:
    """Machines `m000000`… from `start` to `stop`, tagged hall-a and hall-b in turn."""
    from sqlalchemy import insert

    from jobs import db
    from jobs.models import Machine

    with db.session_scope(db_url) as session:
        for first in range(start, stop, INSERT_BATCH):
            session.execute(insert(Machine), [{
                "id": f"m{n:06d}", "name": f"Machine {n}", "model": "Mock", "transport": "mock",
                "tags": ["hall-a" if n % 2 else "hall-b"],
                "encoding": "latin-1" if n % 3 else "utf-8",
            } for n in range(first, min(stop, first + INSERT_BATCH))])


def timed_ms(client: httpx.Client, body: dict[str, Any], repeat: int,
             empty_queue: Callable[[], None]) -> tuple[float, int]:
    """Median wall of `repeat` POSTs until their 202, and the targets of the last job."""
    walls, total = [], 0
    for _ in range(repeat):
        empty_queue()  # the tasks of the jobs before, which no worker takes
        start = time.perf_counter()
        response = client.post("/api/jobs", json=body)
        walls.append((time.perf_counter() - start) * 1000)
        if response.status_code != 202:
            raise SystemExit(f"POST /api/jobs answered {response.status_code}: "
                             f"{response.text[:300]}")
        total = response.json()["total"]
    return statistics.median(walls), total


def run(args: argparse.Namespace, folder: Path) -> list[tuple[str, str, str, str]]:
    """The whole benchmark; returns the table rows (figure, value, target, verdict)."""
    rows: list[tuple[str, str, str, str]] = []
    with contextlib.ExitStack() as stack:
        db_url = migrated_postgres(stack, folder)
        redis_folder = folder / "redis"
        redis_folder.mkdir()
        redis = stack.enter_context(redis_server(redis_folder))
        api, client = api_alone(stack, folder, db_url=db_url, broker_url=redis.url)

        requests = {
            "one machine by id": {"kind": "delete", "fileName": "P.nc",
                                  "machines": {"ids": ["m000007"]}},
            "one machine, text in its encoding": {
                "kind": "send", "fileName": "P.nc", "content": "(Maß 3)\nG0 X0\n",
                "machines": {"ids": ["m000007"]}},
            "every machine tagged hall-a": {"kind": "delete", "fileName": "P.nc",
                                            "machines": {"tags": ["hall-a"]}},
        }
        base: dict[str, float] = {}
        registered = 0
        for n in sorted(args.sizes):
            say(f"{n:,} machines: registering ...")
            register(db_url, registered, n)
            registered = n
            for name, body in requests.items():
                timed_ms(client, body, 1, redis.flush)  # warm-up
                wall, total = timed_ms(client, body, args.repeat, redis.flush)
                per_target = wall / total
                # A request naming one machine is compared whole; a fleet-wide one per target.
                figure = wall if total == 1 else per_target
                base.setdefault(name, figure)
                ratio = figure / base[name]
                largest = n == max(args.sizes) and n > min(args.sizes)
                rows.append((
                    f"{n:,} machines: {name} ({total:,} target{'s' if total > 1 else ''})",
                    f"{wall:.1f} ms" + (f" ({per_target * 1000:.0f} µs a target)"
                                        if total > 1 else ""),
                    f"<= {TARGET_RATIO:g}x the smallest fleet" if largest else "",
                    (f"{ratio:.2f}x: " + ("met" if ratio <= TARGET_RATIO else "NOT met"))
                    if largest else f"{ratio:.2f}x the smallest"))
        rss = api.peak_rss_mb()
        rows.append(("API peak RSS", f"{rss:.0f} MB" if rss else "?", "", ""))
    return rows


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 100_000])
    parser.add_argument("--repeat", type=int, default=3, help="POSTs per figure (median)")
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder")
    args = parser.parse_args()
    with bench_folder(args.keep) as folder:
        print_table(run(args, folder))


if __name__ == "__main__":
    main()
