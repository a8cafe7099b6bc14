"""Work that drops the GIL: at most one call per core, and on gevent off the greenlets' thread."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

from jobs.run import green

REPO = Path(__file__).resolve().parents[3]


class Overlap:
    """Counts how many calls run at once (a native lock: no greenlet ever waits on it)."""

    def __init__(self) -> None:
        self.lock, self.now, self.most = threading.Lock(), 0, 0

    def __call__(self, value: int) -> int:
        with self.lock:
            self.now += 1
            self.most = max(self.most, self.now)
        time.sleep(0.1)  # long enough for calls started apart on a busy host to meet
        with self.lock:
            self.now -= 1
        return value * 2


def test_without_gevent_calls_run_in_place_one_per_core_at_most() -> None:
    overlap, results = Overlap(), {}

    def call(value: int) -> None:
        results[value] = green.run_on_a_core(overlap, value)

    threads = [threading.Thread(target=call, args=(v,)) for v in range(green.CORES * 4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert results == {v: v * 2 for v in range(green.CORES * 4)}
    assert overlap.most == green.CORES


# Run in a process of its own: gevent must patch the standard library before anything
# imports it, which pytest's process did long ago.
GEVENT_SCRIPT = """
from gevent import monkey
monkey.patch_all()
import sys, threading, time
import gevent
from jobs.run import green

native_lock = monkey.get_original("threading", "Lock")()
native_sleep = monkey.get_original("time", "sleep")
state = {"now": 0, "most": 0, "threads": set()}

def work(value):
    with native_lock:
        state["now"] += 1
        state["most"] = max(state["most"], state["now"])
        state["threads"].add(monkey.get_original("threading", "get_ident")())
    native_sleep(0.25)  # holds its thread the way a deflate does, without the GIL
    with native_lock:
        state["now"] -= 1
    return value * 2

ticks = []
def ticker():
    while True:
        ticks.append(time.monotonic())
        gevent.sleep(0.005)

assert green.active()
tick = gevent.spawn(ticker)
calls = [gevent.spawn(green.run_on_a_core, work, v) for v in range(green.CORES * 4)]
gevent.joinall(calls, raise_error=True)
tick.kill()
hub_thread = monkey.get_original("threading", "get_ident")()
print(sorted(c.value for c in calls) == [v * 2 for v in range(green.CORES * 4)],
      state["most"], len(state["threads"]), hub_thread in state["threads"], len(ticks))
"""


def test_on_gevent_calls_run_on_native_threads_one_per_core_while_greenlets_go_on() -> None:
    out = subprocess.run([sys.executable, "-c", GEVENT_SCRIPT], cwd=REPO, capture_output=True,
                         text=True, timeout=60, check=True).stdout.split()
    all_results, most, threads, on_hub_thread, ticks = out
    assert all_results == "True"
    assert int(most) == green.CORES  # the pool is full while calls wait, never fuller
    assert int(threads) == green.CORES
    assert on_hub_thread == "False"  # the greenlets' own thread ran none of them
    # 4 rounds of 250 ms (200 ticks at best): a blocked hub would have ticked a handful of times
    assert int(ticks) >= 20
