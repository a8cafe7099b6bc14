"""A drip-feed run over the seed protocol (worker.transports.drip), client side.

UPDATE_FILE_DNC starts the run; then, round after round: QUERY_FILE_DNC asks for room in
the control's window, SEND_FILE_DNC sends as many of the next lines as fit, SEND_DATA asks
for the running line. END_FILE_DNC follows the last line; the run ends when the control
says DONE. Rounds are paced by how long the lines the control holds ahead of its running
line last at its recent block rate (`Pace`), so a control with plenty in hand is asked
seldom and one about to run dry at once. A link that drops is opened again and the run
resumed (RESUME_DNC) from the line the control asks for, within `grace_s`; lines are kept
only until the control has them, so memory stays flat whatever the program's length.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Iterable, Iterator

from worker.transports import dnc_wire as wire
from worker.transports.base import Busy, Dropped, Permanent, Transient
from worker.transports.dnc_link import ControlError, DncLink
from worker.transports.dnc_wire import Command, ErrorCode, Frame, HintCode, WireState
from worker.transports.drip import DripResult, LineFn, LinkLost, StopFn

log = logging.getLogger(__name__)

POLL_FRACTION = 0.25  # of the time until the window runs dry: the wait before the next round
RATE_ROUNDS = 8  # recent rounds whose highest block rate paces the rounds


class NotInDncMode(Busy):
    """The control refused DNC with a hint: not in DNC mode, or its IO channel is not the
    network. The operator has to switch it; until then every run is refused."""


def feed(link: DncLink, name: str, lines: Iterable[bytes], *, total_lines: int | None,
         on_line: LineFn, should_stop: StopFn) -> DripResult:
    """Run `name` on the control behind `link`; the caller holds `link.lock`."""
    return _Run(link, lines, on_line).go(name, total_lines, should_stop)


class _Run:
    def __init__(self, link: DncLink, lines: Iterable[bytes], on_line: LineFn) -> None:
        self.link = link
        self.options = link.options
        self.on_line = on_line
        self.source: Iterator[bytes] = iter(lines)
        self.exhausted = False
        self.pending: deque[bytes] = deque()  # read, not yet held by the control
        self.next_to_read = 1  # number of the next line taken from the source
        self.held = 0  # lines the control confirmed it holds (1..held)
        self.running = 0  # the control's running line
        self.ended = False  # END_FILE_DNC sent
        self.run_id = 0
        self.hinted: str | None = None  # why the control takes no data now (out of DNC mode)
        self.pace = Pace(link.options.poll_interval_s, link.options.max_poll_interval_s)

    def go(self, name: str, total_lines: int | None, should_stop: StopFn) -> DripResult:
        reply = self.link.request(Command.UPDATE_FILE_DNC,
                                  wire.file_payload(name, total_lines or 0))
        if reply.command is Command.HINT:
            _, message = self.link.decode(reply, wire.read_error)
            raise NotInDncMode(f"the control refused DNC: {message}")
        self.run_id = self.link.decode(_expect(reply, Command.OK),
                                       lambda payload: wire.read_uint(payload, 4))
        while True:
            try:
                result = self._round(should_stop)
            except (Transient, Dropped) as exc:
                if isinstance(exc, Busy):
                    raise
                self._resume(exc)
                continue
            except ControlError as exc:
                if exc.code == ErrorCode.NO_RUN:  # reset at the machine: the run is gone
                    raise self._lost(f"the control no longer holds the run (reset at the "
                                     f"machine): {exc}") from exc
                raise
            if result is not None:
                return result

    def _round(self, should_stop: StopFn) -> DripResult | None:
        if should_stop():
            return self._stop()
        sent = False
        if not self.ended:
            # Once every line is held, no room is asked for: resumed after END_FILE_DNC
            # went and its answer was lost, a control that ran on to done holds no run
            # taking lines (NO_RUN).
            if not self.exhausted or self.pending:
                sent = self._fill()
            if self.exhausted and not self.pending:
                self._position(self.link.request(Command.END_FILE_DNC))
                self.ended = True
        state = self._position(self.link.request(
            Command.SEND_DATA, wire.uint_payload(wire.SendData.LINE_SYNC, 1)))
        if state is WireState.DONE and self.ended:
            return DripResult(self.held, self.running, stopped=False)
        if state is WireState.RESET:  # after the last line was sent too: lost, as mid-run
            raise self._lost("the control ended the run (reset at the machine)")
        self.pace.saw(self.running)
        wait_s = self.pace.wait_s(ahead_lines=self.held - self.running, sent=sent)
        if self.hinted:  # waiting for the operator: asked as seldom as the pace allows
            wait_s = self.pace.max_wait_s
        if wait_s > 0:
            time.sleep(wait_s)
        return None

    def _fill(self) -> bool:
        """Ask for room and send the next lines into it; True if any were sent."""
        reply = self.link.request(Command.QUERY_FILE_DNC)
        if reply.command is Command.HINT:
            code, message = self.link.decode(reply, wire.read_error)
            if code != HintCode.WAIT:
                # Switched out of DNC mode mid-run: the client goes on querying until the
                # control's conditions are met again (the seed, S63), the running line
                # still asked each round; the run goes on once the operator switches back,
                # and `dncq stop` ends it meanwhile.
                self._hint(message)
            return False
        self._hint(None)
        next_line, free = self._ready(reply)
        while not self.exhausted and self.next_to_read < next_line + free:
            line = next(self.source, None)
            if line is None:
                self.exhausted = True
                break
            if len(line) > wire.MAX_LINE_BYTES:
                raise Permanent(f"line {self.next_to_read} is longer than "
                                f"{wire.MAX_LINE_BYTES} bytes")
            self.pending.append(line)
            self.next_to_read += 1
        block = list(self.pending)[:free]
        count = wire.lines_fit(block)
        if count == 0:
            return False
        reply = self.link.request(Command.SEND_FILE_DNC,
                                  wire.lines_payload(next_line, block[:count]))
        self._ready(reply)
        return True

    def _ready(self, reply: Frame) -> tuple[int, int]:
        """Take a GET_FILE_DNC: forget the lines the control holds now."""
        next_line, free = self.link.decode(_expect(reply, Command.GET_FILE_DNC), wire.read_ready)
        first_pending = self.next_to_read - len(self.pending)
        for _ in range(min(next_line - first_pending, len(self.pending))):
            self.pending.popleft()
        self._moved(self.running, next_line - 1)
        return next_line, free

    def _position(self, reply: Frame) -> WireState:
        running, _, state = self.link.decode(_expect(reply, Command.SEND_MAC_POS),
                                             wire.read_position)
        self._moved(running, self.held)
        return state

    def _hint(self, message: str | None) -> None:
        """Say when the control stops and starts taking data again (once each)."""
        if message and message != self.hinted:
            log.warning("DNC run %d waits at line %d: %s; it goes on when the control is "
                        "switched back to DNC", self.run_id, self.running, message)
        elif message is None and self.hinted:
            log.info("DNC run %d goes on at line %d", self.run_id, self.running)
        self.hinted = message

    def _moved(self, running: int, held: int) -> None:
        if (running, held) != (self.running, self.held):
            self.running, self.held = running, held
            self.on_line(running, held)

    def _stop(self) -> DripResult:
        """The seed's stop: SEND_DATA with STOP resets the machine, then END_FILE_DNC."""
        state = self._position(self.link.request(Command.SEND_DATA,
                                                 wire.uint_payload(wire.SendData.STOP, 1)))
        self._position(self.link.request(Command.END_FILE_DNC))
        # A control that ran the last line before the stop came has nothing to reset.
        done = state is WireState.DONE and self.ended
        return DripResult(self.held, self.running, stopped=not done)

    def _resume(self, cause: Exception) -> None:
        """Connect again and resume the run, for up to grace_s; LinkLost after."""
        self.link.close()
        self.pace.forget()  # the lines run while the link was down say nothing of the rate
        down_since = time.monotonic()
        while time.monotonic() - down_since < self.options.grace_s:
            try:
                self._ready(self.link.request(Command.RESUME_DNC,
                                              wire.uint_payload(self.run_id, 4)))
                return
            except ControlError as exc:
                if exc.code == ErrorCode.NO_RUN:
                    raise self._lost(f"the control no longer holds the run: {exc}") from exc
                raise
            except Transient:
                self.link.close()
                time.sleep(self.options.poll_interval_s)
        raise self._lost(f"link down for more than {self.options.grace_s:g} s (grace_s): "
                         f"{cause}") from cause

    def _lost(self, message: str) -> LinkLost:
        return LinkLost(message, last_line=self.running, lines_sent=self.held)


class Pace:
    """When to poll again: from the control's running line over time (its block rate) and
    the lines it holds beyond it, a fraction of the time until its window would run dry."""

    def __init__(self, min_wait_s: float, max_wait_s: float) -> None:
        self.min_wait_s = min_wait_s
        self.max_wait_s = max(max_wait_s, min_wait_s)
        self.rates: deque[float] = deque(maxlen=RATE_ROUNDS)  # lines/s between two rounds
        self.last: tuple[float, int] | None = None  # (monotonic s, running line) last seen

    def saw(self, running: int) -> None:
        """The control's running line now (once a round)."""
        now = time.monotonic()
        if self.last is None or running < self.last[1]:
            self.last = (now, running)
        elif now - self.last[0] >= self.min_wait_s:  # rounds at once are too close to time
            self.rates.append((running - self.last[1]) / (now - self.last[0]))
            self.last = (now, running)

    def forget(self) -> None:
        """Start measuring the rate again (after a reconnect)."""
        self.rates.clear()
        self.last = None

    def wait_s(self, *, ahead_lines: int, sent: bool) -> float:
        """Seconds to wait before the next round; 0 for at once.

        The highest recent rate is taken, so a stretch the control spent starved or waiting
        does not lengthen the wait. Without a rate, or when the window would run dry within
        a few shortest waits, the round after one that sent lines comes at once and the one
        after an idle round after `min_wait_s`, as a fixed poll would.
        """
        rate = max(self.rates, default=0.0)
        wait_s = POLL_FRACTION * ahead_lines / rate if rate > 0 else 0.0
        if wait_s < self.min_wait_s:
            return 0.0 if sent else self.min_wait_s
        return min(wait_s, self.max_wait_s)


def _expect(frame: Frame, command: Command) -> Frame:
    if frame.command is not command:
        raise Dropped(f"the control answered {frame.command.name}, not {command.name}")
    return frame
