"""Simulated DNC controls for bench/dnc.py: many `Control` + `DncServer` pairs in one process.

A process per control would be a hundred interpreters on a small host; the bench starts a
few of these instead (`python bench/dnc_fleet.py --machines 25 ...`). Each prints its
ports as a JSON list on its first line, then answers every line `stats` on its stdin with
one JSON line: per control, its last run, its longest starvation, the server's longest
wait from room offered to lines received and the requests it answered. EOF or SIGTERM stops it.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from worker.simulator.control import Control  # noqa: E402
from worker.simulator.programs import ProgramStore  # noqa: E402
from worker.simulator.tcp_server import DncServer  # noqa: E402


def stats(pairs: list[tuple[Control, DncServer]]) -> list[dict[str, Any]]:
    """What each control saw, in the order of the ports."""
    found = []
    for control, server in pairs:
        run = control.last_run
        found.append({
            "port": server.port, "state": control.state.value,
            "running_line": control.running_line,
            "ended": run.ended if run else None,
            "lines_loaded": run.lines_loaded if run else control.next_line - 1,
            "longest_starved_ms": round(control.longest_starved_s * 1000, 1),
            "starved_count": run.starved_count if run else None,
            "longest_ask_ms": round(server.longest_ask_s * 1000, 1),
            "requests": sum(server.requests.values()),
        })
    return found


def serve(root: Path, count: int, block_rate: float, heartbeat_s: float) -> None:
    """Serve `count` controls (programs under root/cNNN) until stdin closes."""
    pairs = []
    for n in range(count):
        control = Control(ProgramStore(root / f"c{n:03d}"), block_rate=block_rate)
        server = DncServer(control, heartbeat_s=heartbeat_s)
        server.start()
        pairs.append((control, server))
    print(json.dumps([server.port for _, server in pairs]), flush=True)
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(0))
    try:
        for line in sys.stdin:
            if line.strip() == "stats":
                print(json.dumps(stats(pairs)), flush=True)
    finally:
        for control, server in pairs:
            server.close()
            control.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True)
    parser.add_argument("--machines", type=int, default=25)
    parser.add_argument("--block-rate", type=float, default=1000.0)
    parser.add_argument("--heartbeat-s", type=float, default=2.0)
    args = parser.parse_args()
    serve(args.root, args.machines, args.block_rate, args.heartbeat_s)


if __name__ == "__main__":
    main()
