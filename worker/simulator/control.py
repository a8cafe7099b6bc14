"""The simulated control: modes, IO channel, the DNC program window and its running line,
and what its operator does at it: READ pressed, programs punched toward the PC.

A link server (the seed's TCP protocol, an RS-232 line) drives one `Control`: it starts a
DNC run, loads lines into the window while there is room, marks the end of data, reads the
running line, and resets. A thread executes the loaded lines at `block_rate` blocks per
second: it sleeps until its next lines are due (at least `_TICK_S`, so a fast control
executes them in batches) or until lines arrive, so a slow or idle control costs next to
nothing. The window holds at most `WINDOW_LINES` lines (executed ones included) and frees
`FREE_STEP` executed lines at a time, as the seed's control does.

The operator's READ (`press_read`) makes the control ready to read one program in, for a
window of time: the next program a link brings is stored replacing its namesake
(`read_in`). Programs the operator punches toward the PC over the network wait in an
outbox until a client has taken one whole (`punch`, `first_punch`, `punch_sent`).

Every executed line is appended to `executed.log` and every ended run to `runs.jsonl` in
`log_dir` (when given), so a test can check that no line was lost or repeated. Each run
also records its longest starvation: a stretch with every loaded line executed while more
were due, the feed hold a slow link causes at the machine. It is timed from when the first
line the window lacked was due, so the batching does not shorten it; a hold shorter than
one batch (`_TICK_S`) is not seen.
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from enum import StrEnum
from pathlib import Path
from typing import BinaryIO, TextIO

from worker.simulator.modes import IoChannel, Mode
from worker.simulator.programs import ProgramStore

READ_WINDOW_S = 180.0  # how long a control stays ready to read in after READ
WINDOW_LINES = 1000  # the most lines the window holds, executed ones included
FREE_STEP = 100  # executed lines freed at a time
_TICK_S = 0.01  # the executing thread's shortest sleep between batches (10 lines at 1,000/s)


class RunState(StrEnum):
    """Where a DNC run is."""

    IDLE = "idle"  # no run
    WAIT = "wait"  # accepted, waiting for its first lines (the seed's SOCK_DNC_WAIT)
    RUNNING = "running"  # executing lines
    STARVED = "starved"  # every loaded line executed, more are due: feed hold
    DONE = "done"  # the last line executed
    RESET = "reset"  # stopped by a reset


class DncRefused(Exception):
    """The control cannot start a DNC run now; `reason` says why, in the hint's words."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason  # "mode", "io_channel" or "busy"


class NotReadyToRead(Exception):
    """A program came to be read in while the control was not ready (no READ pressed)."""


@dataclass(frozen=True)
class RunRecord:
    """A DNC run that ended, as written to runs.jsonl."""

    name: str
    lines_loaded: int
    last_line: int  # the last line executed
    peak_window_lines: int  # the most lines the window ever held
    ended: str  # "done", "reset" or "abandoned"
    longest_starved_ms: float = 0.0  # the longest feed hold while lines were due
    starved_count: int = 0  # how many times the window ran dry before the end of data


class Control:
    """One simulated machine; thread-safe, every method returns at once."""

    def __init__(self, store: ProgramStore, *, mode: Mode = Mode.DNC,
                 io_channel: IoChannel = IoChannel.NETWORK, block_rate: float = 1000.0,
                 log_dir: Path | None = None) -> None:
        if block_rate <= 0:
            raise ValueError("block_rate must be above 0 blocks/s")
        self.store = store
        self.mode = mode
        self.io_channel = io_channel
        self.block_rate = block_rate
        self._log_dir = log_dir
        self._log: TextIO | None = None
        self._cond = threading.Condition()
        self._clear_run("")
        self.peak_window_lines = 0  # across every run since start
        self.longest_starved_s = 0.0  # across every run since start
        self.last_run: RunRecord | None = None
        self._outbox: deque[tuple[str, bytes]] = deque()  # punched toward the PC, oldest first
        self._read_until = 0.0  # monotonic end of the read-in state (READ pressed)
        self.read_presses = 0  # READ pressed, counted: a side that signals it watches this
        self._closed = False
        self._thread = threading.Thread(target=self._execute, name="control", daemon=True)
        self._thread.start()

    def _clear_run(self, name: str) -> None:
        self.state = RunState.IDLE
        self.program = name
        self._window: deque[bytes] = deque()  # lines loaded and not yet freed, in order
        # Number of the next line the window takes: one int, set in one step, because the
        # line's side reads it without the lock. Summed from the window's parts, it read
        # too small while the executing thread freed lines, and the line loaded there was
        # refused as one already held: lost.
        self.next_line = 1
        self._executed_in_window = 0
        self.running_line = 0  # the last line executed
        self._end_of_data = False
        self._run_peak = 0
        self._starved_since: float | None = None  # when the window ran dry, lines due
        self._run_longest_starved_s = 0.0
        self._run_starved_count = 0

    # -- what a link server calls ------------------------------------------------

    def start_dnc(self, name: str, *, channel: IoChannel) -> None:
        """Begin a DNC run of `name` fed from `channel`; DncRefused unless the mode is DNC,
        the IO channel is `channel` and no run is going on."""
        with self._cond:
            if self.mode is not Mode.DNC:
                raise DncRefused("mode", f"the control is in {self.mode.value.upper()} mode, "
                                 "not DNC")
            if self.io_channel is not channel:
                raise DncRefused("io_channel", f"the IO channel is {self.io_channel.value}, "
                                 f"not {channel.value}")
            if self.state in (RunState.WAIT, RunState.RUNNING, RunState.STARVED):
                raise DncRefused("busy", f"a DNC run of {self.program} is going on")
            self._clear_run(name)
            self.state = RunState.WAIT
            self._open_log()

    @property
    def active(self) -> bool:
        """True while a run takes lines or executes them."""
        return self.state in (RunState.WAIT, RunState.RUNNING, RunState.STARVED)

    @property
    def free_lines(self) -> int:
        """Lines the window can take now (0 when no run takes lines)."""
        with self._cond:
            if not self.active or self._end_of_data:
                return 0
            return WINDOW_LINES - len(self._window)

    def load(self, first_line: int, lines: list[bytes]) -> int:
        """Put lines numbered from `first_line` into the window; return how many it took.

        Lines it already holds are skipped and a gap is refused (0 taken), so a block sent
        twice after a reconnect is never executed twice.
        """
        with self._cond:
            if not self.active or self._end_of_data or first_line > self.next_line:
                return 0
            fresh = lines[self.next_line - first_line:]
            room = WINDOW_LINES - len(self._window)
            taken = fresh[:room]
            self._window.extend(taken)
            self.next_line += len(taken)
            self._run_peak = max(self._run_peak, len(self._window))
            self.peak_window_lines = max(self.peak_window_lines, len(self._window))
            if taken and self.state is RunState.WAIT:
                self.state = RunState.RUNNING
            if taken:
                self._fed()
            self._cond.notify_all()
            return len(taken)

    def end_of_data(self) -> None:
        """No more lines come: the run is done once the loaded ones are executed."""
        with self._cond:
            self._end_of_data = True
            self._fed()  # a starvation waiting for the end of data ends here
            self._cond.notify_all()

    def reset(self, *, ended: str = "reset") -> None:
        """Stop the run at once: the window is emptied, nothing more executes."""
        with self._cond:
            if self.active:
                self.state = RunState.RESET
                self._window.clear()
                self._finish(ended)

    def close(self) -> None:
        """Stop the executing thread (a run going on is abandoned)."""
        self.reset(ended="abandoned")
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._thread.join(5)

    # -- the operator: READ and PUNCH ----------------------------------------------

    def press_read(self, window_s: float = READ_WINDOW_S) -> None:
        """The operator presses READ: the control reads in the next program sent to it,
        until one is read in or `window_s` passes."""
        with self._cond:
            self._read_until = time.monotonic() + window_s
            self.read_presses += 1

    @property
    def ready_to_read(self) -> bool:
        """True while READ holds: a program sent now is read in."""
        return time.monotonic() < self._read_until

    @contextmanager
    def read_in(self, name: str) -> Iterator[BinaryIO]:
        """A file to read a program in to: stored under `name`, replacing a program of that
        name, only if the block ends without an error; the control then leaves its
        read-in state. NotReadyToRead unless READ holds; BadPath for a name it cannot
        store (both before the block starts)."""
        if not self.ready_to_read:
            raise NotReadyToRead("the control is not ready to read a program in (no READ)")
        with self.store.receive(name, replace=True) as out:
            yield out
        with self._cond:
            self._read_until = 0.0

    def punch(self, name: str, data: bytes) -> None:
        """The operator punches program `data` toward the PC over the network: it waits
        in the outbox until a client has taken it whole."""
        with self._cond:
            self._outbox.append((name, data))

    def first_punch(self) -> tuple[str, bytes] | None:
        """The oldest program in the outbox, left there; None when it is empty."""
        with self._cond:
            return self._outbox[0] if self._outbox else None

    def punch_sent(self, punched: tuple[str, bytes]) -> None:
        """A client took `punched` (from `first_punch`) whole: it leaves the outbox."""
        with self._cond:
            if self._outbox and self._outbox[0] is punched:
                self._outbox.popleft()

    @property
    def outbox_length(self) -> int:
        """Programs punched toward the PC that no client has taken yet."""
        return len(self._outbox)

    # -- the executing thread ---------------------------------------------------

    def _execute(self) -> None:
        started = time.monotonic()
        done = 0  # lines executed since `started`
        with self._cond:
            while True:
                while not self._closed and not self._has_work():
                    self._cond.wait()
                    started, done = time.monotonic(), 0  # no burst after a wait
                if self._closed:
                    return
                due = int((time.monotonic() - started) * self.block_rate) - done
                done += self._execute_lines(max(due, 0), started + (done + 1) / self.block_rate)
                # A reset, close or lines arriving wake it early (notify_all).
                next_due_s = started + (done + 1) / self.block_rate - time.monotonic()
                self._cond.wait(max(next_due_s, _TICK_S))

    def _has_work(self) -> bool:
        # A starved run goes on with new lines, or ends once the end of data comes.
        if self.state is RunState.STARVED and (
                self._executed_in_window < len(self._window) or self._end_of_data):
            self.state = RunState.RUNNING
        return self.state is RunState.RUNNING

    def _execute_lines(self, count: int, next_due_s: float) -> int:
        """Execute up to `count` lines, the first of them due at monotonic `next_due_s`."""
        executed = 0
        while executed < count:
            if self._executed_in_window == len(self._window):
                if self._end_of_data:  # done once its lines and its run are on record
                    self._finish("done")
                    self.state = RunState.DONE
                else:
                    self.state = RunState.STARVED
                    if self._starved_since is None:  # since the missing line was due
                        self._starved_since = next_due_s + executed / self.block_rate
                        self._run_starved_count += 1
                break
            line = self._window[self._executed_in_window]
            self._executed_in_window += 1
            self.running_line += 1
            executed += 1
            if self._log is not None:
                self._log.write(line.decode("latin-1") + "\n")
            if self._executed_in_window >= FREE_STEP:
                for _ in range(FREE_STEP):
                    self._window.popleft()
                self._executed_in_window -= FREE_STEP
        return executed

    # -- records -----------------------------------------------------------------

    def _fed(self) -> None:
        """Lines arrived: a starvation going on ends here (called holding the lock)."""
        if self._starved_since is not None:
            starved_s = time.monotonic() - self._starved_since
            self._starved_since = None
            self._run_longest_starved_s = max(self._run_longest_starved_s, starved_s)
            self.longest_starved_s = max(self.longest_starved_s, starved_s)

    def _open_log(self) -> None:
        if self._log_dir is not None:
            self._log_dir.mkdir(parents=True, exist_ok=True)
            self._log = (self._log_dir / "executed.log").open("a", encoding="latin-1")

    def _finish(self, ended: str) -> None:
        self._fed()  # a reset ends a starvation too: it lasted until then
        self.last_run = RunRecord(self.program, self.next_line - 1, self.running_line,
                                  self._run_peak, ended,
                                  round(self._run_longest_starved_s * 1000, 1),
                                  self._run_starved_count)
        if self._log is not None:
            self._log.close()
            self._log = None
        if self._log_dir is not None:
            with (self._log_dir / "runs.jsonl").open("a") as runs:
                runs.write(json.dumps(asdict(self.last_run)) + "\n")
        self._cond.notify_all()
