"""Listeners: dncq waits on a serial or dnc machine's link for what its operator sends.

A machine whose requests are on is listened to whenever it has no work: one listener per
machine across every worker, because it holds the machine's lease while it listens (group
`listen:<machine>`, jobs.run.leases), renewed like a runner's. It gives the machine up,
between two programs, as soon as a job has targets for it or a single-machine request
asks it to (`ask_listener_to_yield`), and hands it to the job that waits; the reaper's
next tick listens again once the machine is free. A program that comes in is handled by
jobs.requests.handling while the lease is held, answers included. It is kept on the disk
first (jobs.requests.spool): what a worker killed before recording it had read is taken up
by the machine's next listener, and recorded once. A listener that loses the database goes
on hearing the machine, keeping what it sends, and records what it kept once the database
answers again.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable

from sqlalchemy import func, select

from jobs import db
from jobs.db import session_scope
from jobs.errors import ContractError
from jobs.fleet import checks, door, registry
from jobs.fleet.registry import MachineSpec
from jobs.fleet.rules import MachineFiles
from jobs.models import MachineLease, Target, TargetState, utcnow
from jobs.requests import handling, record, spool
from jobs.run import leases
from jobs.run.slot import hand_on
from jobs.settings import Settings
from worker import transports
from worker.transports.base import (
    CutShort,
    Permanent,
    TimedOut,
    TransportError,
)
from worker.transports.optional import RequestLink

log = logging.getLogger(__name__)

LISTEN_POLL_S = 1.0  # longest a listener waits on the link before it looks for work waiting
RECHECK_S = 5.0  # how often a listener reads its machine again (removed, changed, turned off)
BACKOFF_S = (1.0, 2.0, 5.0, 10.0, 30.0)  # waits after a link that fails, one after another
NOTE_EVERY_S = 60.0  # how often a listener keeps "the link answers" as the machine's check
# Waits before a listener tries again to record the programs it kept while the database was
# away, one after another: each try costs one look at the database between two receptions.
KEPT_RETRY_S = (1.0, 2.0, 5.0, 10.0, 30.0)
# After giving its machine up to a request, how long before this process listens on it
# again: the request looks for the free slot every 0.05 s, and a listener back on the next
# tick of a quick reaper took the machine first, time after time, until the request gave up.
GIVE_WAY_S = 2.0


def _request_transports() -> list[str]:
    """The transports whose links carry what an operator sends from the control."""
    return [name for name in transports.REGISTRY
            if transports.kind(name).cls.capabilities.requests]


def listens(spec: MachineSpec) -> bool:
    """Whether dncq listens on the machine's link: on, and its transport takes requests."""
    if not spec.enabled or not spec.requests or spec.transport not in transports.REGISTRY:
        return False
    if not transports.kind(spec.transport).cls.capabilities.requests:
        return False
    try:
        return spec.request_settings().enabled
    except ValueError:
        return False


def _has_work(settings: Settings, machine_id: str, *, holder: str | None = None) -> bool:
    """Targets due on the machine, or a lease on it other than `holder`'s."""
    now = utcnow()
    with session_scope(settings.resolved_database_url) as session:
        due = session.scalar(select(Target.id).where(
            Target.machine_id == machine_id, Target.state == TargetState.PENDING,
            Target.next_attempt_at.is_(None) | (Target.next_attempt_at <= now)).limit(1))
        others = session.scalar(select(func.count()).where(
            MachineLease.machine_id == machine_id, MachineLease.expires_at >= now,
            MachineLease.holder != (holder or "")))
    return due is not None or bool(others)


class Listeners:
    """The listeners of this worker process; `tick` starts those of free machines."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._running: dict[str, Listener] = {}
        # `tick` runs on the reaper's thread and `stop` on the worker's: a listener is
        # registered and started, or the listeners stopped, one at a time, so that a stop
        # never meets one registered but not started, nor leaves one started after it.
        self._lock = threading.Lock()
        self._stopped = False

    def tick(self) -> int:
        """Start listening on every machine that wants it and is free; returns how many run."""
        if not self.settings.listen:
            return 0
        url = self.settings.resolved_database_url
        with session_scope(url) as session:
            specs = [s for s in registry.taking_requests(session=session,
                                                         kinds=_request_transports())
                     if listens(s)]
        for spec in specs:
            running = self._running.get(spec.id)
            if running is not None and (running.is_alive() or running.giving_way()):
                continue
            if _has_work(self.settings, spec.id):
                continue
            holder = leases.acquire(url, machine_id=spec.id, max_concurrent=1,
                                    group=leases.listen_group(spec.id),
                                    ttl_s=self.settings.lease_ttl_s)
            if holder is None:
                continue  # another worker listens, or a job just took the machine
            with self._lock:
                if not self._stopped:
                    log.info("listening on machine %s", spec.id, extra={"machine_id": spec.id})
                    listener = Listener(self.settings, spec, holder)
                    self._running[spec.id] = listener
                    listener.start()
                    continue
            leases.release(url, holder=holder)  # stopped meanwhile: the machine goes back
        return sum(1 for x in self._running.values() if x.is_alive())

    def hearing(self, machine_id: str) -> bool:
        """Whether this process listens on the machine's link now, the link open."""
        listener = self._running.get(machine_id)
        return listener is not None and listener.is_alive() and listener.open.is_set()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop every listener of this process and give their machines back; none starts
        after this."""
        with self._lock:
            self._stopped = True
            running = list(self._running.values())
        for listener in running:
            listener.stop()
        deadline = time.monotonic() + timeout_s
        for listener in running:
            listener.join(max(0.0, deadline - time.monotonic()))


class Listener(threading.Thread):
    """Listens on one machine's link under its lease until the machine is wanted."""

    def __init__(self, settings: Settings, spec: MachineSpec, holder: str) -> None:
        super().__init__(name=f"dncq-listen-{spec.id}", daemon=True)
        self.settings, self.spec, self.holder = settings, spec, holder
        self._stopping = threading.Event()
        self.open = threading.Event()  # the link is open: what the operator sends now is heard
        self._files: MachineFiles | None = None
        self._noted: tuple[bool, float] | None = None  # the last check kept, and when
        self._gave_way_at: float | None = None  # time.monotonic() when asked away
        self._took_up = False  # the programs a lost listener left kept are taken up
        self._retry_kept_at: float | None = None  # time.monotonic(): kept ones unrecorded
        self._kept_misses = 0  # tries in a row that left a kept program unrecorded
        self._without_database = False  # the last look found it away (said once)

    def giving_way(self) -> bool:
        """Whether this listener gave its machine up to a request within GIVE_WAY_S."""
        return self._gave_way_at is not None \
            and time.monotonic() - self._gave_way_at < GIVE_WAY_S

    def stop(self) -> None:
        """Ask the listener to end (it does between two waits on the link)."""
        self._stopping.set()

    def run(self) -> None:
        url = self.settings.resolved_database_url
        try:
            with leases.Heartbeat(url, holder=self.holder, ttl_s=self.settings.lease_ttl_s):
                self._listen()
        except Exception:
            log.exception("listener of machine %s stopped", self.spec.id,
                          extra={"machine_id": self.spec.id})
        finally:
            self._close()
            try:
                leases.release(url, holder=self.holder)
                hand_on(self.settings, [self.spec.id])
            except Exception:  # the lease runs out by itself; the reaper queues the waiting
                log.exception("listener of machine %s could not hand the machine over",
                              self.spec.id, extra={"machine_id": self.spec.id})

    def _listen(self) -> None:
        failures = 0
        checked = 0.0
        while not self._stopping.is_set():
            if time.monotonic() - checked >= RECHECK_S:
                checked = time.monotonic()
                if not self._unless_unreachable(self._still_wanted, True):
                    return
            if self._unless_unreachable(self._wanted_elsewhere, False):
                self._gave_way_at = time.monotonic()
                return
            try:
                link = self._link()
                # Opened before it says it hears: opening a serial port discards what the
                # operator punched into it before.
                link.connect()
                self.open.set()
                if not self._took_up:  # once the link is open: a request is answered on it
                    self._took_up = True
                    self._take_up()
                elif self._retry_kept_at is not None \
                        and time.monotonic() >= self._retry_kept_at:
                    self._retry_kept()
                text = link.receive_program(timeout_s=LISTEN_POLL_S)
                self._note(reachable=True)
            except (ContractError, TransportError) as exc:
                if isinstance(exc, (TimedOut, Permanent)) and self.open.is_set():
                    # A program began and stopped midway, or one too large or not taken:
                    # recorded as a failed reception; the line itself is still good.
                    self._broken_off(str(exc), exc.received if isinstance(exc, CutShort)
                                     else b"")
                    continue
                self._close()
                self._note(reachable=False, error=str(exc))
                wait_s = BACKOFF_S[min(failures, len(BACKOFF_S) - 1)]
                failures += 1
                log.warning("listening on machine %s: %s; again in %g s", self.spec.id, exc,
                            wait_s, extra={"machine_id": self.spec.id})
                if self._stopping.wait(wait_s):
                    return
                continue
            failures = 0
            if text is not None:
                self._handle(text)

    def _note(self, *, reachable: bool, error: str | None = None) -> None:
        """Keep what the link says as the machine's check: the listener holds the machine,
        so no other check reaches it. At once when it changes, else every NOTE_EVERY_S."""
        if self._noted is not None and self._noted[0] == reachable \
                and time.monotonic() - self._noted[1] < NOTE_EVERY_S:
            return
        self._noted = (reachable, time.monotonic())
        try:
            checks.record(self.settings.resolved_database_url, [
                checks.noted(self.spec, reachable=reachable, error=error, by="listener")])
        except Exception:  # a check not kept is no reason to stop listening
            log.exception("keeping the check of machine %s failed", self.spec.id,
                          extra={"machine_id": self.spec.id})

    def _link(self) -> RequestLink:
        if self._files is None:
            self._files = door.open_files(self.spec, data_dir=self.settings.data_dir)
        return self._files.request_link()

    def _close(self) -> None:
        self.open.clear()
        if self._files is not None:
            try:
                self._files.close()
            finally:
                self._files = None

    def _handle(self, text: bytes) -> None:
        self._kept(text, broken_off=None)

    def _broken_off(self, reason: str, received: bytes) -> None:
        self._kept(received, broken_off=reason)

    def _kept(self, text: bytes, *, broken_off: str | None) -> None:
        """Keep what came in on the disk before anything else, then record and answer it:
        the control gives no receipt, so a program lost here is lost without a word."""
        try:
            entry = spool.put(self.settings, self.spec.id, text, broken_off=broken_off)
        except OSError:
            log.exception("keeping what machine %s sent on the disk failed; handled without",
                          self.spec.id, extra={"machine_id": self.spec.id})
            with contextlib.suppress(Exception):  # logged there
                self._record(None, text, broken_off, kept_s=0.0)
            return
        # Said once it is on the disk: a worker killed from here on loses none of it.
        log.info("machine %s sent %d bytes%s", self.spec.id, len(text),
                 f" before its reception broke off ({broken_off})" if broken_off else "",
                 extra={"machine_id": self.spec.id})
        if self._retry_kept_at is not None:  # after those kept before it, in their order
            self._retry_kept()
            return
        self._take(entry, maybe_recorded=False)  # kept just now: no job can have its id

    def _take_up(self) -> None:
        """Record what a listener lost before this one (killed, or its database away) had
        read from the machine and kept, in the order it came."""
        try:
            entries = spool.pending(self.settings, self.spec.id)
        except OSError as exc:  # what the machine sends now is still heard and recorded
            log.warning("the programs kept for machine %s cannot be read (%s); listening "
                        "without taking them up", self.spec.id, exc,
                        extra={"machine_id": self.spec.id})
            return
        if entries:
            log.info("machine %s: taking up what a lost listener had read (%d)", self.spec.id,
                     len(entries), extra={"machine_id": self.spec.id})
        for entry in entries:
            if not self._take(entry):  # the rest after it, in their order, on the next try
                return

    def _retry_kept(self) -> None:
        """Record, in the order they came, the programs kept while the database was away;
        the first that still cannot be recorded puts the rest off to the next try."""
        self._retry_kept_at = None
        try:
            entries = spool.pending(self.settings, self.spec.id)
        except OSError as exc:
            log.warning("the programs kept for machine %s cannot be read (%s)", self.spec.id,
                        exc, extra={"machine_id": self.spec.id})
            self._put_off_kept()
            return
        for entry in entries:
            if not self._take(entry):
                return
        log.info("machine %s: recorded what it sent while the database was away (%d)",
                 self.spec.id, len(entries), extra={"machine_id": self.spec.id})
        self._kept_misses = 0

    def _put_off_kept(self) -> None:
        """Try the kept programs again after the next wait of KEPT_RETRY_S."""
        self._retry_kept_at = time.monotonic() + \
            KEPT_RETRY_S[min(self._kept_misses, len(KEPT_RETRY_S) - 1)]
        self._kept_misses += 1

    def _take(self, entry: spool.Spooled, *, maybe_recorded: bool = True) -> bool:
        """Record one kept program unless its job already is (a listener killed between the
        two); forgotten once recorded, else tried again later (`_retry_kept`). Returns
        whether it is recorded."""
        try:
            if not (maybe_recorded and record.recorded(settings=self.settings,
                                                       job_id=entry.id)):
                self._record(entry.id, entry.text, entry.broken_off, kept_s=entry.kept_s)
        except Exception:  # whether it was recorded all the same is asked again
            if not self._recorded(entry.id):
                self._put_off_kept()
                return False
        spool.remove(entry)
        return True

    def _recorded(self, job_id: str) -> bool:
        try:
            return record.recorded(settings=self.settings, job_id=job_id)
        except Exception:
            log.warning("what machine %s sent stays kept until the database answers",
                        self.spec.id, extra={"machine_id": self.spec.id})
            return False

    def _record(self, job_id: str | None, text: bytes, broken_off: str | None, *,
                kept_s: float) -> None:
        """Record (and answer) one program; raises after logging when it failed."""
        try:
            if broken_off is not None:
                handling.receive_failed(settings=self.settings, spec=self.spec, text=text,
                                        reason=broken_off, origin="link", job_id=job_id)
                return
            handling.handle(settings=self.settings, spec=self.spec, text=text,
                            answerer=handling.LinkAnswerer(self._link(),
                                                           self.spec.request_settings()),
                            origin="link", job_id=job_id, kept_s=kept_s)
        except Exception:  # recorded where it could be; the link goes on listening
            log.exception("handling what machine %s sent failed", self.spec.id,
                          extra={"machine_id": self.spec.id})
            raise

    def _unless_unreachable(self, look: Callable[[], bool], meanwhile: bool) -> bool:
        """`look()`, or `meanwhile` while the database is away: the machine's lease cannot
        be taken from this listener then, and what the operator sends is still heard and
        kept; the first look once the database answers gives the machine up if it is
        wanted."""
        try:
            answer = look()
        except Exception as exc:
            if not db.unreachable(exc):
                raise
            if not self._without_database:  # said once an outage, not once a second
                log.warning("listening on machine %s without the database (%s): what it "
                            "sends is kept until the database answers", self.spec.id,
                            type(exc).__name__, extra={"machine_id": self.spec.id})
            self._without_database = True
            return meanwhile
        self._without_database = False
        return answer

    def _wanted_elsewhere(self) -> bool:
        url = self.settings.resolved_database_url
        return (leases.asked_to_yield(url, holder=self.holder)
                or _has_work(self.settings, self.spec.id, holder=self.holder))

    def _still_wanted(self) -> bool:
        """The machine is still registered as it was, and still to be listened to."""
        with session_scope(self.settings.resolved_database_url) as session:
            try:
                now = registry.get(session=session, machine_id=self.spec.id)
            except ContractError:
                return False
        return now == self.spec and listens(now)

