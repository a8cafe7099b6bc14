"""A download that frees its machine at the machine's pace, whatever the client's.

Were receiveFileStream to read the machine only as fast as the client reads the response,
a slow client, or one that stopped reading, would hold the machine's slot (and every batch
waiting for it) for as long as it liked. So a thread of its own copies the file from the
machine into an anonymous spool file in the data folder and gives the slot back at the last
byte, while the response sends whatever has arrived. Memory stays flat; the spool file
disappears when both sides are done with it.
"""

from __future__ import annotations

import os
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from worker.transports.base import CHUNK_BYTES

_FILLER, _READER = "filler", "reader"


class ReadAhead:
    """One download: `fill` on a thread of its own, `stream` for the response."""

    def __init__(self, spool_dir: Path) -> None:
        spool_dir.mkdir(parents=True, exist_ok=True)
        self._spool = tempfile.TemporaryFile(dir=spool_dir)  # no name: gone once closed
        self._fd = self._spool.fileno()
        self._changed = threading.Condition()
        self._written = 0
        self._finished = False  # the machine's last byte is in the spool
        self._error: BaseException | None = None
        self._left: set[str] = set()

    def start(self, chunks: Iterable[bytes], release: Callable[[], None]) -> None:
        """Copy `chunks` into the spool on a new thread, then call `release` (the slot)."""
        threading.Thread(target=self._fill, args=(chunks, release), daemon=True,
                         name="receive-read-ahead").start()

    def _fill(self, chunks: Iterable[bytes], release: Callable[[], None]) -> None:
        try:
            for chunk in chunks:
                if _READER in self._left:
                    break  # the client went away: stop reading the machine
                os.pwrite(self._fd, chunk, self._written)
                with self._changed:
                    self._written += len(chunk)
                    self._changed.notify_all()
        except BaseException as exc:  # the response cuts the download short with it
            with self._changed:
                self._error = exc
        finally:
            try:
                release()
            finally:
                with self._changed:
                    self._finished = True
                    self._changed.notify_all()
                self._leave(_FILLER)

    def stream(self) -> Iterator[bytes]:
        """The file as it arrives; raises the machine's error if the copy failed midway."""
        sent = 0
        try:
            while True:
                with self._changed:
                    while self._written <= sent and not self._finished:
                        self._changed.wait()
                    available, error = self._written, self._error
                if available > sent:
                    chunk = os.pread(self._fd, min(CHUNK_BYTES, available - sent), sent)
                    sent += len(chunk)
                    yield chunk
                elif error is not None:
                    raise error
                else:
                    return
        finally:
            self.stop()

    def stop(self) -> None:
        """The response is over (sent, failed or abandoned); safe to call more than once."""
        self._leave(_READER)

    def _leave(self, who: str) -> None:
        with self._changed:
            if who in self._left:
                return
            self._left.add(who)
            last = len(self._left) == 2
        if last:  # neither side uses the file any more (closing earlier could reuse its fd)
            self._spool.close()
