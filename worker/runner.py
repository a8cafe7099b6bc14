"""Runs one job's targets on one machine, in request order, under the machine's lease."""

from __future__ import annotations

import contextlib
import logging
import threading
from concurrent.futures import Future

from jobs import db, service
from jobs.db import session_scope
from jobs.dnc import feeding
from jobs.dnc import runs as dnc_runs
from jobs.errors import ContractError, ErrorCode, unknown_machine
from jobs.fleet import door
from jobs.fleet.registry import MachineSpec
from jobs.fleet.rules import MachineFiles
from jobs.models import JobKind
from jobs.requests import record
from jobs.run import job_ends, leases, queue, running, settle, targets
from jobs.run.work import Finished, Started, Work
from jobs.settings import Settings
from worker.operations import Outcome, execute

log = logging.getLogger(__name__)

class OperationSlots:
    """How many targets of this worker talk to their machines at once.

    Unlimited by default: Celery's pool is the limit. A gevent worker holds twice as many
    tasks as its `--concurrency` (worker/app.py): each claims its target, then waits here
    for one of `--concurrency` slots, so a slot that frees starts the next machine
    operation at once, instead of waiting for Celery's one consumer to hand over the next
    message and for that task's claim to be committed.
    """

    def __init__(self) -> None:
        self.limit: int | None = None
        self._slots: threading.BoundedSemaphore | None = None

    def set_limit(self, limit: int) -> None:
        self.limit, self._slots = limit, threading.BoundedSemaphore(limit)

    def __enter__(self) -> None:
        if self._slots is not None:
            self._slots.acquire()

    def __exit__(self, *_: object) -> None:
        if self._slots is not None:
            self._slots.release()


OPERATION_SLOTS = OperationSlots()


def run_machine(settings: Settings, job_id: str, machine_id: str) -> None:
    """Run the job's due targets on the machine, one after another, then hand over the slot.

    The last target's result is handed to the shared transactions without waiting for
    them: the slot goes to the next task at once, and what the result leaves to do (a
    retry, a job waiting for the machine, the job's end) follows once it is committed.
    A worker that dies before that commit leaves the target running under its lease,
    which the reaper recovers like any attempt cut short.

    A database lost for longer than the task waits ends the task with one warning, not an
    exception: its target stays running under its lease (or pending, unclaimed) and the
    reaper recovers it, as it would if the task had failed. A task that raises costs far
    more: Celery copies the whole chained traceback, with every frame's code positions,
    into an ExceptionInfo (about 0.5 MB for this one), and while an outage lasts those pile
    up faster than they are freed; the interpreter keeps the arenas they spread over long
    after (docs/performance.md, "Worker memory after faults").
    """
    try:
        _run_machine(settings, job_id, machine_id)
    except Exception as exc:
        if not db.unreachable(exc):
            raise
        log.warning("job %s on machine %s stopped: database unavailable (%s); its targets "
                    "are recovered once the machine's lease runs out", job_id, machine_id,
                    type(exc).__name__, extra={"job_id": job_id, "machine_id": machine_id})


def _run_machine(settings: Settings, job_id: str, machine_id: str) -> None:
    url = settings.resolved_database_url
    started = _begin(settings, job_id, machine_id)
    if started.job_done:  # it was cancelled: a batch request waiting for it may answer now
        # a run stopped while its worker was lost: its end is recorded here or never
        dnc_runs.close_unstarted(url=url, job_id=job_id, machine_id=machine_id)
        job_ends.announce(settings, job_id)
    if started.spec is None:  # machine removed after the job was made
        _fail_all(settings, job_id, machine_id)
        dnc_runs.close_unstarted(url=url, job_id=job_id, machine_id=machine_id)  # its run too
        return
    if started.holder is None or started.work is None:
        return  # busy (the job waits its turn) or nothing due
    holder, work, kind = started.holder, started.work, started.work.kind
    files: MachineFiles | None = None
    handed_over = False  # the slot's last step (a finish or a give-back) is taken care of
    try:
        with leases.Heartbeat(url, holder=holder, ttl_s=settings.lease_ttl_s,
                              on_renew=lambda: running.extend_running(
                                  url=url, job_id=job_id, machine_id=machine_id,
                                  lease_s=settings.lease_ttl_s)):
            while True:
                outcome = attempt(settings, started.spec, work, files)
                files = outcome.files
                if outcome.behind:  # nothing to record: the slot is given back below
                    return
                recorded = targets.finish_later(
                    settings=settings, work=work, holder=holder, error=outcome.error,
                    state=outcome.state, status_msg=outcome.status_msg,
                    replaced_payload_id=outcome.replaced_payload_id)
                if not work.more:  # claimed as the machine's last: nothing more to ask
                    recorded.add_done_callback(lambda future: _once_committed(
                        settings, job_id, machine_id, kind, future))
                    handed_over = True
                    return
                done = recorded.result()
                if done.next_work is None:
                    handed_over = True
                    _follow_up(settings, job_id, machine_id, kind, done)
                    return
                work = done.next_work
    finally:
        if files is not None:
            files.close()
        if not handed_over:  # left the loop by an exception, or a run behind another
            waiting = targets.give_back(settings=settings, holder=holder, machine_id=machine_id)
            _follow_up(settings, job_id, machine_id, kind, Finished(None, None, waiting))


def _begin(settings: Settings, job_id: str, machine_id: str) -> Started:
    """`targets.begin`, waiting out a lost database for up to `redispatch_after_s`.

    Nothing runs without the database; a task that gave up at once would be acknowledged
    and gone until the reaper queued its machine again. Waiting holds the worker's slot,
    so an outage does not drain the queue into failures either.
    """
    def waits(exc: BaseException) -> None:
        log.warning("job %s on machine %s waits for the database (%s)", job_id, machine_id,
                    type(exc).__name__, extra={"job_id": job_id, "machine_id": machine_id})

    return db.when_reachable(
        lambda: targets.begin(settings=settings, job_id=job_id, machine_id=machine_id),
        wait_s=settings.redispatch_after_s, on_wait=waits)


def _once_committed(settings: Settings, job_id: str, machine_id: str, kind: JobKind,
                    future: Future[Finished]) -> None:
    """Called where the finish was committed: anything slower goes to a thread of its own."""
    error = future.exception()
    if error is not None:  # the target stays running under its lease until the reaper
        log.error("recording the result of job %s on machine %s failed: %r; it is recovered "
                  "when its lease runs out", job_id, machine_id, error,
                  extra={"job_id": job_id, "machine_id": machine_id})
        return
    done = future.result()
    if done.retry_in_s is not None or done.waiting_job_id or done.job_done \
            or kind is JobKind.DNC_RUN:
        threading.Thread(target=_follow_up, args=(settings, job_id, machine_id, kind, done),
                         name="dncq-follow-up", daemon=True).start()


def _follow_up(settings: Settings, job_id: str, machine_id: str, kind: JobKind,
               done: Finished) -> None:
    """What a machine's slot leaves to do when handed over: queue a retry, the job that
    waits for the machine, the backup's assembly, or say that a job ended (and how)."""
    if done.job_done:  # first: a batch request waits for it to answer
        job_ends.announce(settings, job_id)
    if done.retry_in_s is not None:
        queue.enqueue_machine(settings, job_id, machine_id, countdown_s=done.retry_in_s)
    if done.waiting_job_id:
        queue.enqueue_machine(settings, done.waiting_job_id, machine_id)
    if kind is JobKind.DNC_RUN and done.retry_in_s is None:  # an attempt that found the
        # link down put its run back in the queue; with no attempt after it, the run is over
        url = settings.resolved_database_url
        dnc_runs.close_unstarted(url=url, job_id=job_id,
                                 machine_id=machine_id)  # its own run: one of many
        behind = feeding.next_behind(url=url, job_id=job_id, machine_id=machine_id)
        if behind is not None and behind != done.waiting_job_id:  # the link is free now
            queue.enqueue_machine(settings, behind, machine_id)
    if done.job_done and kind is JobKind.BACKUP:
        queue.enqueue_assembly(settings, job_id)
    elif done.job_done:
        service.alert_if_failed(settings=settings, job_id=job_id)


def attempt(settings: Settings, spec: MachineSpec, work: Work,
             files: MachineFiles | None) -> Outcome:
    """One attempt, with every failure turned into the contract error it records."""
    try:
        if work.kind is JobKind.REQUEST:  # recorded running by a listener that died since
            raise ContractError(ErrorCode.CONNECTION_FAILED, record.LISTENER_LOST,
                                transient=False)
        # A drip-feed run waits on its machine for hours: it takes no operation slot, so
        # it never holds up the other machines' transfers.
        with OPERATION_SLOTS if work.kind is not JobKind.DNC_RUN else contextlib.nullcontext():
            if files is None:
                files = door.open_files(spec, data_dir=settings.data_dir)
            outcome = execute(settings, files, work)
    except ContractError as exc:
        outcome = Outcome(error=exc)
    except feeding.Behind:
        outcome = Outcome(behind=True)
    except Exception as exc:
        if not db.unreachable(exc):  # a bug must not leave the target running forever
            log.exception("target %s of job %s failed unexpectedly", work.target_id,
                          work.job.job_id,
                          extra={"job_id": work.job.job_id, "machine_id": work.machine_id})
            outcome = Outcome(error=ContractError(ErrorCode.INTERNAL_ERROR, type(exc).__name__))
        else:  # the database, not the machine nor the request: worth another attempt
            log.warning("target %s of job %s: database unavailable (%s); retried",
                        work.target_id, work.job.job_id, type(exc).__name__,
                        extra={"job_id": work.job.job_id, "machine_id": work.machine_id})
            outcome = Outcome(error=ContractError(
                ErrorCode.INTERNAL_ERROR, f"database unavailable ({type(exc).__name__})",
                transient=True))
    outcome.files = files
    return outcome


def _fail_all(settings: Settings, job_id: str, machine_id: str) -> None:
    """Every pending target on a machine that is no longer registered fails with 10003."""
    with session_scope(settings.resolved_database_url) as session:
        settle.fail_pending(session=session, job_id=job_id, machine_id=machine_id,
                             error=unknown_machine(machine_id))
