"""The simulated control's operator panel: files in a folder stand for its keys, and
`status.json` there shows its state.

Each key is a file written into the folder and removed once acted on:

- `mode`: `edit`, `mem` or `dnc` switches the mode;
- `reset`: anything resets the control;
- `read`: READ is pressed: the control reads in the next program sent to it (the file may
  hold the seconds it stays ready, else 180);
- `punch`: the name of a stored program punches it toward the PC;
- `type`: a program's text is typed at the control and punched toward the PC.

A punch goes out on the RS-232 side when the panel has one, else into the TCP side's
outbox, where a client takes it (QUERY_PUNCH).
"""

from __future__ import annotations

import json
import logging
import os
import threading
from pathlib import Path
from typing import Any

from worker.simulator.control import READ_WINDOW_S, Control, Mode
from worker.simulator.serial_machine import SerialMachine
from worker.simulator.tcp_server import DncServer
from worker.transports.base import TransportError

log = logging.getLogger(__name__)

POLL_S = 0.1  # between looks at the folder
KEYS = ("mode", "reset", "read", "punch", "type")


class Panel:
    """The keys of one `Control`, pressed through files in `folder`; `start()` returns at
    once, `close()` stops it."""

    def __init__(self, folder: Path, control: Control, *, serial: SerialMachine | None = None,
                 tcp: DncServer | None = None) -> None:
        self.folder = folder
        self.control = control
        self.serial = serial
        self.tcp = tcp
        self.last_error: str | None = None
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="panel", daemon=True)

    def start(self) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        self._thread.start()

    def close(self) -> None:
        self._closed.set()
        self._thread.join(5)

    def status(self) -> dict[str, Any]:
        """What status.json shows: the control's state, then the RS-232 side's."""
        c = self.control
        shown: dict[str, Any] = {
            "mode": c.mode.value, "state": c.state.value, "running_line": c.running_line,
            "ready_to_read": c.ready_to_read, "outbox": c.outbox_length,
            "last_error": self.last_error}
        if self.serial is not None:
            shown |= self.serial.status()
            shown["last_error"] = self.serial.last_error or self.last_error
        return shown

    def _watch(self) -> None:
        while not self._closed.wait(POLL_S):
            for key in KEYS:
                press = self.folder / key
                try:
                    value = press.read_bytes()
                except FileNotFoundError:
                    continue
                press.unlink()
                try:
                    self.press(key, value)
                except (TransportError, ValueError) as exc:  # a control's alarm, no crash
                    self.last_error = f"{key}: {exc}"
            try:
                self._write_status()
            except OSError:
                log.exception("cannot write the panel's status")

    def press(self, key: str, value: bytes) -> None:
        """Press one key with what its file held."""
        text = value.decode("utf-8", errors="replace").strip()
        if key == "mode":
            self.control.mode = Mode(text)
        elif key == "reset":
            if self.serial is not None:
                self.serial.reset()  # the RS-232 side drops what its buffer holds too
            else:
                self.control.reset()
        elif key == "read":
            self.control.press_read(float(text) if text else READ_WINDOW_S)
        elif key == "punch":
            if self.serial is not None:
                self.serial.request_punch(text)
            elif self.tcp is not None:
                self.tcp.request_punch(text)
        elif key == "type":
            if self.serial is not None:
                self.serial.punch_text(value)
            elif self.tcp is not None:
                self.tcp.punch_text(value)

    def _write_status(self) -> None:
        status = self.folder / "status.json"
        written = status.with_suffix(f".{os.getpid()}.tmp")
        written.write_text(json.dumps(self.status()))
        written.replace(status)  # whole: a reader never sees half of it
