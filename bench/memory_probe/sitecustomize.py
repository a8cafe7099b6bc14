"""What a bench's dncq process holds, written to a file when the bench asks (bench only).

`bench/fault_memory.py` puts this folder first on a worker's PYTHONPATH, so Python imports
it at start, before gevent patches anything. With DNCQ_BENCH_PROBE_DIR set, a native thread
looks every 0.2 s for `<dir>/<pid>.ask`, whose text is a label; it answers with
`<dir>/<pid>-<label>.json`: VmRSS/VmHWM, anonymous and file memory (smaps_rollup), glibc's
heap (mallinfo2), Python's allocated blocks, objects by type, threads and greenlets,
database pools, Celery's request lists, logging handlers, and, with
DNCQ_BENCH_TRACEMALLOC=N (frames), tracemalloc's top lines (traced from the first answer
on: tracing the start makes it too slow to answer a ping in time). A label that starts with
`trim` also calls malloc_trim(0) and says the RSS before and after.
"""

from __future__ import annotations

import _thread
import collections
import ctypes
import gc
import json
import logging
import os
import sys
import tracemalloc
from pathlib import Path
from time import sleep  # bound now: gevent's patched sleep would need its hub
from typing import Any

POLL_S = 0.2


class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost")]


def _libc() -> Any:
    libc = ctypes.CDLL("libc.so.6")
    libc.mallinfo2.restype = MallInfo2
    return libc


def _kb_fields(path: str, names: tuple[str, ...]) -> dict[str, int]:
    found: dict[str, int] = {}
    for line in Path(path).read_text().splitlines():
        key, _, value = line.partition(":")
        if key in names:
            found[key] = int(value.split()[0])
    return found


def _memory() -> dict[str, int]:
    status = _kb_fields("/proc/self/status", ("VmRSS", "VmHWM", "RssAnon", "RssFile"))
    rollup = _kb_fields("/proc/self/smaps_rollup", ("Rss", "Anonymous", "Private_Dirty"))
    return {**{f"{k}_kb": v for k, v in status.items()},
            **{f"smaps_{k}_kb": v for k, v in rollup.items()}}


def _mappings() -> dict[str, Any]:
    """Anonymous memory by mapping: the biggest, and how many of each size there are."""
    maps: list[dict[str, Any]] = []
    current: dict[str, Any] = {}
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split()
        if "-" in head[0] and not head[0].endswith(":"):
            start, end = (int(x, 16) for x in head[0].split("-"))
            current = {"range": head[0], "size_kb": (end - start) // 1024,
                       "name": head[5] if len(head) > 5 else "", "perms": head[1]}
            maps.append(current)
        elif head[0] in ("Rss:", "Anonymous:"):
            current[head[0][:-1].lower() + "_kb"] = int(head[1])
    anonymous = [m for m in maps if m.get("anonymous_kb")]
    by_size: collections.Counter[str] = collections.Counter()
    kb_by_size: collections.Counter[str] = collections.Counter()
    for m in anonymous:
        key = f"{m['name'] or 'anon'} {m['perms']} {m['size_kb']} kB"
        by_size[key] += 1
        kb_by_size[key] += m["anonymous_kb"]
    return {"biggest": sorted(anonymous, key=lambda m: -m["anonymous_kb"])[:15],
            "by_size": [(key, by_size[key], kb) for key, kb in kb_by_size.most_common(25)]}


def _heap(libc: Any) -> dict[str, int]:
    info = libc.mallinfo2()
    return {"arena_bytes": info.arena, "mmapped_bytes": info.hblkhd,
            "in_use_bytes": info.uordblks, "free_bytes": info.fordblks,
            "top_releasable_bytes": info.keepcost, "free_chunks": info.ordblks}


def _objects() -> dict[str, Any]:
    counts: collections.Counter[str] = collections.Counter()
    for obj in gc.get_objects():
        kind = type(obj)
        counts[f"{kind.__module__}.{kind.__qualname__}"] += 1
    greenlets = sum(n for name, n in counts.items() if name.endswith("greenlet")
                    or name.endswith("Greenlet"))
    return {"gc_objects": sum(counts.values()), "greenlets": greenlets,
            "by_type": counts.most_common(40)}


def _pools() -> list[str]:
    db = sys.modules.get("jobs.db")
    if db is None:
        return []
    return [f"{engine.url.render_as_string()}: {engine.pool.status()}"
            for engine in db._engines()]


def _celery() -> dict[str, int]:
    state = sys.modules.get("celery.worker.state")
    if state is None:
        return {}
    return {name: len(getattr(state, name)) for name in (
        "requests", "active_requests", "reserved_requests", "revoked")
        if hasattr(state, name)}


def _handlers() -> int:
    loggers = [logging.getLogger()] + [
        logger for logger in logging.Logger.manager.loggerDict.values()
        if isinstance(logger, logging.Logger)]
    return sum(len(logger.handlers) for logger in loggers)


def _traced(frames: int) -> dict[str, Any]:
    if not tracemalloc.is_tracing():
        return {}
    current, peak = tracemalloc.get_traced_memory()
    snapshot = tracemalloc.take_snapshot().filter_traces(
        [tracemalloc.Filter(False, tracemalloc.__file__)])
    key = "traceback" if frames > 1 else "lineno"
    top = [(str(stat.traceback.format(limit=frames)), stat.size, stat.count)
           for stat in snapshot.statistics(key)[:30]]
    return {"traced_bytes": current, "traced_peak_bytes": peak, "top": top}


def answer(label: str, libc: Any, frames: int) -> dict[str, Any]:
    """Everything this probe reads, after a full collection; trims the heap if asked."""
    gc.collect()
    found: dict[str, Any] = {
        "label": label, "memory": _memory(), "heap": _heap(libc),
        "mappings": _mappings(),
        "allocated_blocks": sys.getallocatedblocks(),
        "threads": len(os.listdir("/proc/self/task")), **_objects(),
        "pools": _pools(), "celery": _celery(), "log_handlers": _handlers(),
        "tracemalloc": _traced(frames)}
    if label.startswith("trim"):
        sys._debugmallocstats()  # pymalloc's arenas and pools, to stderr (the log)
        found["trimmed"] = bool(libc.malloc_trim(0))
        found["memory_after_trim"] = _memory()
        found["heap_after_trim"] = _heap(libc)
    return found


def _watch(folder: Path, frames: int) -> None:
    libc = _libc()
    ask = folder / f"{os.getpid()}.ask"
    while True:
        sleep(POLL_S)
        try:
            label = ask.read_text().strip()
        except OSError:
            continue
        ask.unlink()
        try:
            found = answer(label, libc, frames)
        except Exception as exc:  # the bench says what went wrong instead of waiting
            found = {"label": label, "error": repr(exc)}
        if frames and not tracemalloc.is_tracing():
            tracemalloc.start(frames)
        out = folder / f"{os.getpid()}-{label}.json"
        out.with_suffix(".tmp").write_text(json.dumps(found, indent=1))
        out.with_suffix(".tmp").rename(out)


def _start() -> None:
    folder = os.environ.get("DNCQ_BENCH_PROBE_DIR")
    if not folder:
        return
    frames = int(os.environ.get("DNCQ_BENCH_TRACEMALLOC", "0") or 0)
    _thread.start_new_thread(_watch, (Path(folder), frames))


_start()
