"""The drip-feed runs of one worker process, told to the database together.

Each run's line is written a few times a second and whether it must stop is asked as often.
Done run by run, that is four statements a second per run, and in a gevent worker each one
holds up the feed of every other run while it waits on the database: with 100 runs, the
controls starved for up to 2 s. The board writes the lines of all the runs that moved in one
statement and asks for the stops of all of them in one query, every `FLUSH_EVERY_S`.

A run's record is refreshed only while its own feed is heard from (a line, or a look at
whether to stop): a feed stuck on its link lets its record go stale, and the reaper then
treats its worker as gone (jobs.run.reaper._keep_live_runs), as it would without the board.
"""

from __future__ import annotations

import logging
import os
import threading
import time

from jobs.dnc import feeding

log = logging.getLogger(__name__)

FLUSH_EVERY_S = 0.5  # how often the lines are written and the stops asked
ALIVE_EVERY_S = 5.0  # a run whose line stands still is still written this often


class Entry:
    """One run on the board: its feed sets the line, the board sets `stop` (and who
    asked it, `stopped_by`, when someone did)."""

    def __init__(self, run_id: int) -> None:
        self.run_id = run_id
        self.last_line = self.lines_sent = 0
        self.stop = False
        self.stopped_by: str | None = None
        self.heard = time.monotonic()  # the feed's last sign of life
        self.written_at = float("-inf")
        self.written: tuple[int, int] | None = None

    def moved(self, last_line: int, lines_sent: int) -> None:
        """The machine got this far (the feed calls it at every line: it costs no I/O)."""
        self.last_line, self.lines_sent = last_line, lines_sent
        self.heard = time.monotonic()

    def alive(self) -> None:
        """The feed is going, even if the line stands still."""
        self.heard = time.monotonic()

    def due(self, now: float) -> bool:
        """Whether the next flush writes this run: heard from since its last write, and
        moved since, or not written for `ALIVE_EVERY_S`."""
        if self.heard <= self.written_at:
            return False
        moved = (self.last_line, self.lines_sent) != self.written
        return moved or now - self.written_at >= ALIVE_EVERY_S


class Board:
    """The runs of this process on one database, with the thread that flushes them.

    The thread runs while the board has runs and ends with the last one.
    """

    def __init__(self, url: str) -> None:
        self.url = url
        self._entries: dict[int, Entry] = {}
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def join(self, run_id: int) -> Entry:
        """Put a run on the board; the flushing thread starts if it is not running."""
        entry = Entry(run_id)
        with self._lock:
            self._entries[run_id] = entry
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, daemon=True,
                                                name="dncq-drip-board")
                self._thread.start()
        return entry

    def leave(self, entry: Entry) -> None:
        """Take a run off the board (before its end is recorded)."""
        with self._lock:
            if self._entries.get(entry.run_id) is entry:
                del self._entries[entry.run_id]

    def flush(self) -> None:
        """Write the lines of the runs that are due, then ask which runs must stop."""
        with self._lock:
            entries = list(self._entries.values())
        now = time.monotonic()
        due = [e for e in entries if e.due(now)]
        lines = [feeding.Line(e.run_id, e.last_line, e.lines_sent) for e in due]
        feeding.progress_many(url=self.url, lines=lines)
        for entry, line in zip(due, lines, strict=True):
            entry.written_at, entry.written = now, (line.last_line, line.lines_sent)
        stopping = feeding.stopping(url=self.url, run_ids=[e.run_id for e in entries])
        for entry in entries:
            if entry.run_id in stopping:
                entry.stop, entry.stopped_by = True, stopping[entry.run_id]

    def _loop(self) -> None:
        while True:
            time.sleep(FLUSH_EVERY_S)
            with self._lock:
                if not self._entries:
                    self._thread = None
                    return
            try:
                self.flush()
            except Exception:  # a database hiccup: the next flush tries again
                log.exception("recording the drip-feed runs failed")


_boards: dict[tuple[int, str], Board] = {}
_boards_lock = threading.Lock()


def board_for(url: str) -> Board:
    """This process's board for the database at `url` (a forked child makes its own)."""
    key = (os.getpid(), url)
    with _boards_lock:
        board = _boards.get(key)
        if board is None:
            board = _boards[key] = Board(url)
        return board
