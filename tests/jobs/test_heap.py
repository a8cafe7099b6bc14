"""A worker's heap after its start is set aside: what its tasks leave behind is still
collected, on the collector's own schedule and not only when asked."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

# A process of its own: freezing pytest's heap would outlive the test.
SCRIPT = """
import gc, weakref
from jobs import heap

class Node:
    pass

made_at_start = [Node() for _ in range(1000)]
heap.settle()
frozen = gc.get_freeze_count()
start_tracked = any(o is made_at_start[0] for o in gc.get_objects())
later = Node()
later_tracked = any(o is later for o in gc.get_objects())

refs = []
for _ in range(100_000):  # what tasks leave behind: objects in reference cycles
    a, b = Node(), Node()
    a.other, b.other = b, a
    refs.append(weakref.ref(a))
del a, b
left_unasked = sum(r() is not None for r in refs)
gc.collect()
left_after_a_collection = sum(r() is not None for r in refs)
print(frozen, start_tracked, later_tracked, left_unasked, left_after_a_collection)
"""


def test_garbage_made_after_the_start_is_collected_without_being_asked() -> None:
    out = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, capture_output=True,
                         text=True, timeout=60, check=True).stdout.split()
    frozen, start_tracked, later_tracked = int(out[0]), out[1], out[2]
    left_unasked, left_after_a_collection = map(int, out[3:])
    assert frozen >= 1000  # the start's objects are out of every collection ...
    assert start_tracked == "False" and later_tracked == "True"  # ... and only those
    assert left_unasked < 20_000  # young collections ran by themselves and freed most
    assert left_after_a_collection == 0
