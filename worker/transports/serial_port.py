"""One RS-232 line, opened through pyserial's URLs: paced sending that honours XON/XOFF,
and reading; pyserial's errors mapped once to the transport error tree.

dncq paces what it writes to the line's own rate (`SerialOptions.char_time_s`) and keeps
no more than `slack` characters ahead of it: on a local UART that costs nothing, and on a
pseudo-terminal or a TCP device server, where nothing else paces the sender, it is what
lets a DC3 from the machine stop the flow within a few characters (at most the slack,
2 ms of the line and at least 16 characters, plus what the far side already buffers).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator

import serial

from worker.transports.base import (
    ConnectFailed,
    Dropped,
    Permanent,
    TimedOut,
    TransportError,
)
from worker.transports.serial_options import SerialOptions
from worker.transports.serial_tape import DC1, DC3

_PARITY = {"none": serial.PARITY_NONE, "even": serial.PARITY_EVEN, "odd": serial.PARITY_ODD,
           "mark": serial.PARITY_MARK, "space": serial.PARITY_SPACE}
_STOP_BITS = {1: serial.STOPBITS_ONE, 1.5: serial.STOPBITS_ONE_POINT_FIVE,
              2: serial.STOPBITS_TWO}
_POLL_S = 0.001  # between looks at the line while it is held or silent
SLACK_S = 0.002  # how far ahead of the line's clock the sender may be
MIN_SLACK_CHARS = 16  # a UART's FIFO


@contextlib.contextmanager
def mapped(what: str, *, opening: bool = False) -> Iterator[None]:
    """pyserial's and the OS's failures as the transport's errors, said once."""
    try:
        yield
    except serial.SerialTimeoutException as exc:
        raise TimedOut(f"{what}: {exc}") from exc
    except (serial.SerialException, OSError) as exc:
        raise (ConnectFailed if opening else Dropped)(f"{what}: {exc}") from exc
    except ValueError as exc:  # a URL or setting pyserial cannot take
        raise Permanent(f"{what}: {exc}") from exc


def _write_timeout(options: SerialOptions) -> float | None:
    """How long one write may block: `send_timeout_s`, except over RFC 2217, whose pyserial
    port refuses any write timeout (it writes to its socket, which has its own)."""
    return None if options.url.startswith("rfc2217://") else options.send_timeout_s


class Line:
    """An open serial line; one user at a time."""

    def __init__(self, options: SerialOptions) -> None:
        self.options = options
        self.held = False  # the machine sent DC3 and no DC1 since
        self.held_since = 0.0
        self._clock = 0.0  # monotonic time at which what was written has left the line
        self._slack = max(MIN_SLACK_CHARS, int(SLACK_S / options.char_time_s))
        self._received = bytearray()  # what came in while sending, flow control taken out
        # Off while the machine punches to dncq: its data is no flow control (EIA's "3"
        # is 0x13, DC3's code).
        self.flow_in = True
        self.unsent = b""  # what `send` left unwritten when told to stop
        with mapped(f"cannot open {options.url}", opening=True):
            self.port = serial.serial_for_url(
                options.url, baudrate=options.baud, bytesize=options.data_bits,
                parity=_PARITY[options.parity], stopbits=_STOP_BITS[options.stop_bits],
                xonxoff=False,  # dncq does XON/XOFF itself: it must see the machine hold
                rtscts=options.flow_control == "rtscts",
                timeout=0, write_timeout=_write_timeout(options))

    # -- receiving ---------------------------------------------------------------

    def _poll(self) -> None:
        """Take in what the machine sent: DC1/DC3 move `held`, the rest is kept."""
        with mapped(f"reading {self.options.url}"):
            data = self.port.read(4096)
        if not data:
            return
        if self.options.flow_control == "xonxoff" and self.flow_in:
            for byte in data:
                if byte == DC3:
                    if not self.held:
                        self.held, self.held_since = True, time.monotonic()
                elif byte == DC1:
                    self.held = False
                else:
                    self._received.append(byte)
        else:
            self._received += data

    def read_some(self, timeout_s: float) -> bytes:
        """What the machine sends within `timeout_s` (empty when it stays silent)."""
        ends = time.monotonic() + timeout_s
        while True:
            self._poll()
            if self._received or time.monotonic() >= ends:
                data = bytes(self._received)
                self._received.clear()
                return data
            time.sleep(_POLL_S)

    def put_back(self, data: bytes) -> None:
        """Give back bytes read too far: the next `read_some` returns them first."""
        self._received[:0] = data

    def discard_input(self) -> None:
        """Forget what came in so far (an old DC3 must not hold a new send)."""
        with mapped(f"reading {self.options.url}"):
            self.port.reset_input_buffer()
        self._poll()
        self._received.clear()
        self.held = False

    # -- sending -----------------------------------------------------------------

    def wait_until_released(self, should_stop: Callable[[], bool] | None = None) -> bool:
        """Wait while the machine holds the line; False when `should_stop` said so.

        Raises:
            TimedOut: held longer than `send_timeout_s`.
        """
        self._poll()
        while self.held:
            if should_stop is not None and should_stop():
                return False
            if time.monotonic() - self.held_since > self.options.send_timeout_s:
                raise TimedOut(f"the machine held the line (XOFF) for more than "
                               f"{self.options.send_timeout_s:g} s (send_timeout_s)")
            time.sleep(_POLL_S)
            self._poll()
        return True

    def send(self, data: bytes, should_stop: Callable[[], bool] | None = None) -> bool:
        """Write `data` at the line's pace, pausing while the machine holds the line.

        Returns False, with the rest unsent (`unsent`), when `should_stop` said so during a
        hold.
        """
        piece_chars = 1 if self.options.char_delay_ms else self._slack
        per_char_s = self.options.char_time_s + self.options.char_delay_ms / 1000
        for offset in range(0, len(data), piece_chars):
            if not self.wait_until_released(should_stop):
                self.unsent = data[offset:]
                return False
            now = time.monotonic()
            self._clock = max(self._clock, now)
            ahead_s = self._clock - now - self._slack * self.options.char_time_s
            if ahead_s > 0:
                time.sleep(ahead_s)
            piece = data[offset:offset + piece_chars]
            with mapped(f"writing to {self.options.url}"):
                self.port.write(piece)
            self._clock += len(piece) * per_char_s
        return True

    def drain(self) -> None:
        """Wait until what was written has left the line (by the line's clock and the
        port's own buffer)."""
        with mapped(f"writing to {self.options.url}"):
            self.port.flush()
        wait_s = self._clock - time.monotonic()
        if wait_s > 0:
            time.sleep(wait_s)

    def close(self) -> None:
        with contextlib.suppress(TransportError), mapped("closing"):
            self.port.close()
