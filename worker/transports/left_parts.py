"""The temporary files this process's failed uploads left on a server (it was gone past
their clean-up), and when it last looked for stale ones in a folder: what the next upload
there removes. Kept in memory: a process that ends forgets them, and the folder's sweep,
by age, is what finds them then.
"""

from __future__ import annotations

import threading
import time


class LeftParts:
    """Temporary files left, by server and the file they were for; folders swept, by server."""

    def __init__(self) -> None:
        self._left: dict[tuple[object, str], set[str]] = {}
        self._swept: dict[tuple[object, str], float] = {}  # monotonic s
        self._lock = threading.Lock()

    def add(self, server: object, full: str, part: str) -> None:
        """`part`, a write of `full` on `server`, was left behind: no write is at it now."""
        with self._lock:
            self._left.setdefault((server, full), set()).add(part)

    def take(self, server: object, full: str, folder: str, *,
             sweep_every_s: float) -> tuple[set[str], bool]:
        """After a write placed `full` in `folder`: the parts earlier writes of it left, handed
        over (give back with `add` those that could not be removed), and whether the folder
        is due a sweep (then counted as swept now)."""
        now = time.monotonic()
        with self._lock:
            left = self._left.pop((server, full), set())
            swept = self._swept.get((server, folder))
            sweep = swept is None or now - swept >= sweep_every_s
            if sweep:
                self._swept[(server, folder)] = now
        return left, sweep

    def clear(self) -> None:
        """Forget everything, as a new process would."""
        with self._lock:
            self._left.clear()
            self._swept.clear()
