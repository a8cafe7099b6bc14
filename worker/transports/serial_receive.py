"""A program punched from the control, read off the line: where it starts and ends, the
noise in it, and how much of it dncq takes."""

from __future__ import annotations

import time

from worker.transports import eia
from worker.transports.base import CutShort, Permanent
from worker.transports.serial_options import SerialOptions
from worker.transports.serial_port import Line
from worker.transports.serial_tape import NOISE


def take_punch(line: Line, options: SerialOptions, *, timeout_s: float,
               max_bytes: int | None) -> bytes | None:
    """The next program punched on `line` as ISO text, framing characters included; None
    when none began within `timeout_s`.

    With `framing` a program runs from the start character to the end character; what
    came after the end is left on the line for its next reader (a DC1 the operator's READ
    sent at once). Without, it runs from the first character that is not noise to
    `punch_end_silence_s` of silence. The caller has turned the line's flow control off.

    Raises:
        CutShort: with `framing`, the punch stopped for `receive_timeout_s` before its
            end; what came of it (as it came, noise aside) is kept with the error.
        Permanent: the program is longer than `max_bytes`; the rest of it was read to its
            end and dropped first, so the line is ready for the next one.
    """
    o = options
    end = _encoded(o, o.program_end)
    got = bytearray()
    too_long = False  # over max_bytes: what follows is read and dropped
    began = False
    search_from = 0  # where in a piece the end character may be (not the start's place)
    ends = time.monotonic() + timeout_s
    while True:
        if began:
            wait_s = o.receive_timeout_s if o.framing else o.punch_end_silence_s
        else:
            wait_s = ends - time.monotonic()
            if wait_s <= 0:
                return None
        raw = line.read_some(wait_s)
        if not raw:
            if not began:
                continue  # the loop's check says the time is up
            if not o.framing:
                break
            raise CutShort(f"the punch stopped for {o.receive_timeout_s:g} s before its end "
                           "(receive_timeout_s)", received=b"" if too_long else bytes(got))
        if not began:
            at = punch_start(o, raw)
            if at < 0:
                continue  # noise before the tape starts
            raw, search_from, began = raw[at:], int(o.framing), True
        done = False
        if o.framing:
            close = raw.find(end, search_from)
            search_from = 0
            if close >= 0:
                line.put_back(raw[close + 1:])
                raw, done = raw[:close + 1], True
        piece = _cleaned(o, raw)
        if not too_long and max_bytes is not None and len(got) + len(piece) > max_bytes:
            too_long, got = True, bytearray()  # let go of what was held
        if not too_long:
            got += piece
        if done and not too_long and _blank(o, bytes(got[1:-1])):
            # Nothing between a start and an end: the end just read is the next tape's
            # start (after a tape cut at a stray end character, or torn and punched again).
            # Taken for an end, it would put every program after it out of step, each
            # read from its end to the next one's start.
            got, done = bytearray(piece[-1:]), False
        if done:
            break
    if too_long:
        raise Permanent(f"the program punched is longer than {max_bytes} bytes "
                        "(max_receive_bytes): discarded")
    return eia.decode(bytes(got)) if o.code == "eia" else bytes(got)


def punch_start(options: SerialOptions, raw: bytes) -> int:
    """Where in `raw` a punched program begins: its start character with `framing`, else
    its first character that is not noise; -1 when none does."""
    if options.framing:
        return raw.find(_encoded(options, options.program_start))
    noise = NOISE if options.code == "iso" else b"\0"
    return next((at for at, byte in enumerate(raw) if byte not in noise), -1)


def _blank(options: SerialOptions, cleaned: bytes) -> bool:
    """Whether what a tape holds between its start and end is no program at all."""
    try:
        text = eia.decode(cleaned) if options.code == "eia" else cleaned
    except eia.EiaError:  # codes, then: something
        return False
    return not text.strip()


def _encoded(options: SerialOptions, char: str) -> bytes:
    text = char.encode("ascii")
    return eia.encode(text) if options.code == "eia" else text


def _cleaned(options: SerialOptions, raw: bytes) -> bytes:
    """`raw` without noise; in EIA only blank tape is (its 3 is DC3's byte, and DEL is
    the decoder's to skip)."""
    return raw.translate(None, NOISE) if options.code == "iso" else raw.replace(b"\0", b"")
