"""The benches' short versions, one after another, as CI runs them after the tests.

Each prints its table with its goals beside the figures, as the full bench does, at a size
that takes well under a minute. A guard against regressions that shows in every landing's
log, not a gate: figures of a short run on a shared CI host are noisy, so this prints them
and a summary line per bench and exits 0 whatever they say. A bench that crashes is named
in the summary with its exit status (and still does not fail the build: the tests decide
that).

    python bench/ci.py [--only batch_send,backup] [--timeout-s 240]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

# bench -> the arguments of its short version
SHORT: dict[str, list[str]] = {
    "batch_send": ["--machines", "100", "--latency-ms", "50", "--repeat", "1"],
    "backup": ["--machines", "10", "--files", "10", "--latency-ms", "10", "--repeat", "1",
               "--skip-large"],
    "backup_check": ["--machines", "50", "--latency-ms", "20", "--repeat", "1"],
    "transports": ["--machines", "10", "--files", "10", "--rounds", "1"],
    "job_view": ["--sizes", "1000", "10000", "--repeat", "3"],
    "metrics_scrape": ["--targets", "10000", "--repeat", "3", "--no-postgres"],
    "fleet_requests": ["--sizes", "1000", "10000", "--repeat", "3"],
    "dnc": ["--machines", "5", "--lines", "20000", "--transfer-mb", "5"],
    "recovery": ["--machines", "8", "--concurrency", "2", "--latency-ms", "2000", "--kills", "1",
                 "--lease-ttl-s", "15"],
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="", help="comma-separated benches (default: all)")
    parser.add_argument("--timeout-s", type=float, default=240.0, help="per bench")
    args = parser.parse_args()
    chosen = [b for b in SHORT if not args.only or b in args.only.split(",")]
    summary = []
    for bench in chosen:
        command = [sys.executable, str(HERE / f"{bench}.py"), *SHORT[bench]]
        print(f"\n===== bench/{bench}.py {' '.join(SHORT[bench])}", flush=True)
        started = time.monotonic()
        try:
            status = subprocess.run(command, timeout=args.timeout_s).returncode
        except subprocess.TimeoutExpired:
            status = None
        took_s = time.monotonic() - started
        said = "done" if status == 0 else (f"exit {status}" if status is not None
                                           else f"stopped after {args.timeout_s:g} s")
        summary.append(f"bench/{bench}.py: {said} in {took_s:.0f} s")
    print("\n===== short benches (figures above; they gate nothing)")
    for line in summary:
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
