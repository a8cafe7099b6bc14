"""Benchmark of backupFiles' check: every target asked of its machine before the answer begins.

A client of `POST /api/cnc/backupFiles` gets the first byte of its ZIP only once every
target was checked (the machine asked whether its file or folder is there), so that a bad
target is answered with the contract's JSON error; then once the ZIP's first piece is
ready, so that a target failing while fetched is too (not measured here). This bench
registers `--machines` mock machines answering after `--latency-ms` each (SQLite in a
temporary folder, in-process: no server to start), one program on each, and times
`jobs.backup.streamed.check` for a backupFiles naming every machine, against the same
probes made one machine after another (`check_one` in a loop, as the endpoint did before
2026-12-05), alternated for `--repeat` rounds in the same run.

    python bench/backup_check.py [--machines 200] [--latency-ms 20] [--repeat 2] [--keep]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from bench.common import bench_folder, print_table  # noqa: E402
from jobs import db  # noqa: E402
from jobs.backup import streamed  # noqa: E402
from jobs.fleet import door, registry  # noqa: E402
from jobs.settings import Settings  # noqa: E402


def fleet(settings: Settings, machines: int, latency_ms: int) -> list[dict[str, Any]]:
    """Register the mock machines with a program each; the backupFiles body naming them."""
    with db.session_scope(settings.resolved_database_url) as session:
        for n in range(machines):
            registry.upsert(session=session, data_dir=settings.data_dir,
                            machine_in=registry.MachineIn.model_validate({
                                "id": f"m{n:04d}", "name": f"Machine {n}", "model": "Mock",
                                "options": {"latency_ms": latency_ms}}))
    for n in range(machines):
        program = settings.data_dir / "mock" / f"m{n:04d}" / "files" / "P.NC"
        program.parent.mkdir(parents=True, exist_ok=True)
        program.write_text("G0 X0 Y0\nM30\n")
    return [{"machineID": f"m{n:04d}"} for n in range(machines)]


def at_once(settings: Settings, body: list[dict[str, Any]]) -> int:
    """dncq's check; how many machines it planned."""
    with db.session_scope(settings.resolved_database_url) as session:
        return len(streamed.check(session=session, settings=settings, raw_targets=body))


def one_after_another(settings: Settings, body: list[dict[str, Any]]) -> int:
    """The same probes in turn, one machine after another; how many machines it probed."""
    with db.session_scope(settings.resolved_database_url) as session:
        for position, raw in enumerate(body):
            target = streamed.BackupTarget.parse(raw, position)
            spec = registry.get(session=session, machine_id=target.machineID)
            with door.open_files(spec, data_dir=settings.data_dir) as files:
                streamed.check_one(files, target)
    return len(body)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--machines", type=int, default=200)
    parser.add_argument("--latency-ms", type=int, default=20)
    parser.add_argument("--repeat", type=int, default=2, help="alternated rounds; medians count")
    parser.add_argument("--keep", action="store_true", help="Keep the folder (data)")
    args = parser.parse_args()
    with bench_folder(args.keep) as folder:
        data = folder / "data"
        data.mkdir()
        # Its own SQLite, whatever DNCQ_DATABASE_URL says: the bench registers machines.
        settings = Settings(data_dir=data, database_url=f"sqlite:///{data}/dncq.sqlite3",
                            machine_check_interval_s=0)
        db.upgrade(settings.resolved_database_url)
        body = fleet(settings, args.machines, args.latency_ms)
        walls: dict[str, list[float]] = {"at once": [], "in turn": []}
        for _ in range(args.repeat):  # alternated, so that a busy moment hits both
            for name, check in (("in turn", one_after_another), ("at once", at_once)):
                started = time.perf_counter()
                checked = check(settings, body)
                walls[name].append(time.perf_counter() - started)
                assert checked == args.machines, f"{name} checked {checked} machines"
    turn, once = (statistics.median(walls[k]) for k in ("in turn", "at once"))
    print_table([
        ("fleet", f"{args.machines} mock machines @ {args.latency_ms} ms per operation, "
                  f"one program each", "", ""),
        ("the same probes, one machine after another (the baseline)",
         f"{turn:.2f} s  (all: {', '.join(f'{w:.2f}' for w in walls['in turn'])} s)", "", ""),
        (f"dncq's check, the machines at once ({streamed.CHECK_THREADS} threads)",
         f"{once:.2f} s  (all: {', '.join(f'{w:.2f}' for w in walls['at once'])} s)", "", ""),
        ("dncq / the baseline", f"{once / turn:.2f}x", "", ""),
    ])


if __name__ == "__main__":
    main()
