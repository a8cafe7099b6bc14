"""What PostgreSQL spent its time on during a bench: pg_stat_statements, reset and reported.

The server must be started with `STATEMENT_SETTINGS` (the extension is loaded at start).
"""

from __future__ import annotations

import sys

from sqlalchemy import text

from jobs.db import engine_for

STATEMENT_SETTINGS = {
    "shared_preload_libraries": "pg_stat_statements",
    "pg_stat_statements.track_planning": "on",
}


def install(url: str) -> None:
    with engine_for(url).begin() as conn:
        conn.execute(text("CREATE EXTENSION IF NOT EXISTS pg_stat_statements"))


def reset(url: str) -> None:
    with engine_for(url).begin() as conn:
        conn.execute(text("SELECT pg_stat_statements_reset()"))


def report(url: str, *, top: int, targets: int) -> None:
    """The `top` statements by time (execution plus planning), per target of the batches."""
    with engine_for(url).connect() as conn:
        total_ms, total_calls = conn.execute(text(
            "SELECT sum(total_exec_time + total_plan_time), sum(calls) "
            "FROM pg_stat_statements")).one()
        rows = conn.execute(text(
            "SELECT calls, total_exec_time, total_plan_time, rows, query "
            "FROM pg_stat_statements ORDER BY total_exec_time + total_plan_time DESC "
            "LIMIT :top"), {"top": top}).all()
    out = sys.stderr
    print(f"statements: {float(total_ms or 0) / targets:.3f} ms and "
          f"{int(total_calls or 0) / targets:.1f} calls per target, all statements "
          f"({targets} targets)", file=out)
    print(f"{'ms/target':>9} {'plan ms':>8} {'calls/t':>7} {'rows/call':>9}  query", file=out)
    for calls, exec_ms, plan_ms, nrows, query in rows:
        one_line = " ".join(query.split())
        print(f"{(exec_ms + plan_ms) / targets:9.4f} {plan_ms:8.0f} {calls / targets:7.2f} "
              f"{nrows / max(calls, 1):9.1f}  {one_line[:220]}", file=out)
