"""An RS-232 line's options: the port (a pyserial URL), its framing and its timing."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from worker.transports.base import TransportOptions

EOL_BYTES = {"cr": b"\r", "lf": b"\n", "crlf": b"\r\n"}


class SerialOptions(TransportOptions):
    """Options of a machine reached over an RS-232 line (fleet file `options:`)."""

    url: str = Field(min_length=1)
    """A pyserial URL: `/dev/ttyS0` or a USB adapter, `socket://host:4001` (a raw TCP
    serial device server), `rfc2217://host:port` (one that speaks RFC 2217; add
    `?ign_set_control` when it does not answer modem-line settings)."""
    baud: int = Field(default=9600, gt=0)
    """Line speed in bits per second."""
    data_bits: Literal[7, 8] = 8
    parity: Literal["none", "even", "odd", "mark", "space"] = "none"
    stop_bits: float = 1
    """1, 1.5 or 2."""
    flow_control: Literal["xonxoff", "rtscts", "none"] = "xonxoff"
    """XON/XOFF is done by dncq, not the port driver, so it works alike on every kind of
    URL and dncq knows when the machine holds the line; RTS/CTS is the port's."""
    code: Literal["iso", "eia"] = "iso"
    """The punch code on the line: ISO (ASCII) or EIA RS-244; dncq's copies are ISO."""
    end_of_line: Literal["cr", "lf", "crlf"] = "lf"
    """What ends each block sent (ISO only: EIA has one end-of-block code)."""
    framing: bool = True
    """Send `program_start` before a program and `program_end` after it; a received
    program is taken between them. Off: programs are bare lines, a receive ends at silence."""
    program_start: str = Field(default="%", min_length=1, max_length=1)
    program_end: str = Field(default="%", min_length=1, max_length=1)
    leader_nulls: int = Field(default=0, ge=0, le=10_000)
    """NUL characters sent before a program (blank tape, for readers that need a run-in)."""
    trailer_nulls: int = Field(default=0, ge=0, le=10_000)
    """NUL characters sent after a program."""
    char_delay_ms: float = Field(default=0.0, ge=0, le=1000)
    """Pause after every character, for old controls that lose characters at full speed."""
    send_timeout_s: float = Field(default=30.0, gt=0)
    """Longest the line may stay held (XOFF, or CTS low) while dncq sends."""
    receive_timeout_s: float = Field(default=60.0, gt=0)
    """Longest silence from the machine inside a program it punches."""
    punch_end_silence_s: float = Field(default=2.0, gt=0)
    """Without `framing`: the silence after which a punched program is taken as complete."""
    max_receive_bytes: int = Field(default=1024 * 1024, gt=0)
    """Longest program `receive_program` takes (a request the operator sends): a longer
    one is discarded to its end and refused, never held whole in memory."""
    ready_signal: Literal["dc1", "none"] = "dc1"
    """How the control says it is ready to read a program in (`wait_ready_to_read`):
    "dc1", it sends DC1 (XON) when its operator presses READ (a Fanuc with DC codes on);
    "none", it says nothing: dncq waits `ready_delay_s` and takes it as ready."""
    ready_delay_s: float = Field(default=3.0, ge=0)
    """With `ready_signal` "none": how long the operator has to press READ before dncq
    sends the program."""

    @field_validator("stop_bits")
    @classmethod
    def _a_stop_bit_count(cls, value: float) -> float:
        if value not in (1, 1.5, 2):
            raise ValueError("stop_bits must be 1, 1.5 or 2")
        return value

    @field_validator("program_start", "program_end")
    @classmethod
    def _one_ascii_character(cls, value: str) -> str:
        if not value.isascii() or value in "\x11\x13\r\n\x00":
            raise ValueError("must be one ASCII character, not NUL, CR, LF, DC1 or DC3")
        return value

    @property
    def eol(self) -> bytes:
        """The end-of-line bytes sent after each block (ISO text, before any EIA encoding)."""
        return EOL_BYTES[self.end_of_line]

    @property
    def char_time_s(self) -> float:
        """Seconds one character takes on the line: start bit, data, parity, stop bits."""
        bits = 1 + self.data_bits + (self.parity != "none") + self.stop_bits
        return bits / self.baud
