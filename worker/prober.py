"""The prober: a worker checks the machines whose last check is older than
`machine_check_interval_s`, so that the fleet page and `dncq_machines_online` say which answer
without anyone asking.

A check takes one of the machine's slots like any operation, without waiting: a machine
that is busy is skipped (it is answering a job) and checked at a later pass. Every worker
probes; a machine checked by one is not due for the others.
"""

from __future__ import annotations

import logging
import threading

from jobs.db import session_scope
from jobs.fleet import checks, registry
from jobs.models import utcnow
from jobs.run import checking
from jobs.settings import Settings

log = logging.getLogger(__name__)


class Prober:
    """Probes in a thread of its own: a sweep over offline machines waits on connect
    timeouts, which must not hold up the reaper's recovery."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._busy = threading.Lock()

    def tick(self) -> bool:
        """Start a sweep unless one is running or none is wanted; whether one started."""
        if not self.settings.machine_check_interval_s or not self._busy.acquire(blocking=False):
            return False
        threading.Thread(target=self._sweep, name="dncq-prober", daemon=True).start()
        return True

    def _sweep(self) -> None:
        try:
            probe_due(self.settings)
        except Exception:  # the next tick tries again
            log.exception("checking the machines failed")
        finally:
            self._busy.release()


def probe_due(settings: Settings) -> int:
    """Check every enabled machine that is due and not busy; how many were checked."""
    with session_scope(settings.resolved_database_url) as session:
        specs = [s for s in registry.list_all(session=session) if s.enabled]
        due = checks.due(checks.latest(session), specs,
                         every_s=settings.machine_check_interval_s, now=utcnow())
    return checking.check_idle(settings, due, every_s=settings.machine_check_interval_s)
