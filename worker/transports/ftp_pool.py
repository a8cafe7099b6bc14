"""FTP connections kept between the tasks of one process.

A job's task opens its machine's transport, does the machine's targets and closes it; the
next job's task for the same machine would log in again: a connection and four round trips
(USER, PASS, TYPE, OPTS) before the first useful one. A closing transport hands its
connections here instead, and the next transport for the same server and account takes
them back, with the time it was last used: one used moments ago and on which the server has
sent nothing since is used at once, any other after a NOOP to make sure the server still
answers on it (one round trip; a connection the server ended meanwhile is replaced). A
connection left unused longer than its machine's `keep_connection_s` is ended (QUIT) by a
sweeper thread, so a control that allows few sessions is not held for long.
"""

from __future__ import annotations

import ftplib
import os
import threading
import time
from collections.abc import Hashable
from dataclasses import dataclass

SWEEP_S = 0.5  # how often kept connections are looked at for their time being up


@dataclass
class _Kept:
    ftp: ftplib.FTP
    used: float  # monotonic time it was last used
    until: float  # monotonic time it is ended if still unused


class KeptConnections:
    """Logged-in connections not in use, per server and account, newest first."""

    def __init__(self) -> None:
        self._kept: dict[Hashable, list[_Kept]] = {}
        self._lock = threading.Lock()
        self._pid = os.getpid()
        self._sweeper: threading.Thread | None = None

    def take(self, key: Hashable) -> tuple[ftplib.FTP, float] | None:
        """A kept connection for `key` and when it was last used (monotonic), or None."""
        with self._lock:
            self._forget_if_forked()
            kept = self._kept.get(key)
            if not kept:
                return None
            found = kept.pop()
            if not kept:
                del self._kept[key]
            return found.ftp, found.used

    def give(self, key: Hashable, ftp: ftplib.FTP, *, used: float, keep_s: float) -> None:
        """Keep `ftp`, last used at `used` (monotonic), for the next transport of `key`,
        for `keep_s` from now at most."""
        with self._lock:
            self._forget_if_forked()
            self._kept.setdefault(key, []).append(_Kept(ftp, used, time.monotonic() + keep_s))
            if self._sweeper is None or not self._sweeper.is_alive():
                self._sweeper = threading.Thread(target=self._sweep, daemon=True,
                                                 name="ftp-kept-connections")
                self._sweeper.start()

    def count(self) -> int:
        """How many connections are kept."""
        with self._lock:
            return sum(len(kept) for kept in self._kept.values())

    def end_all(self) -> None:
        """End every kept connection now."""
        with self._lock:
            ending = [k.ftp for kept in self._kept.values() for k in kept]
            self._kept.clear()
        for ftp in ending:
            quit_quietly(ftp)

    def _forget_if_forked(self) -> None:
        # A forked child shares its parent's sockets: it must neither use nor end them.
        if os.getpid() != self._pid:
            self._kept.clear()
            self._pid, self._sweeper = os.getpid(), None

    def _sweep(self) -> None:
        while True:
            time.sleep(SWEEP_S)
            now = time.monotonic()
            with self._lock:
                if os.getpid() != self._pid:
                    return
                ending = [k.ftp for kept in self._kept.values() for k in kept if k.until <= now]
                for key in list(self._kept):
                    self._kept[key] = [k for k in self._kept[key] if k.until > now]
                    if not self._kept[key]:
                        del self._kept[key]
                last = not self._kept
                if last:
                    self._sweeper = None
            for ftp in ending:
                quit_quietly(ftp)
            if last:
                return


def quit_quietly(ftp: ftplib.FTP) -> None:
    """QUIT, or just close a connection that no longer answers."""
    try:
        ftp.quit()
    except (ftplib.Error, OSError, EOFError):
        ftp.close()


KEPT = KeptConnections()  # the process's own
