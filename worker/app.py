"""The Celery app of dncq's workers, and the reaper that runs beside every worker."""

from __future__ import annotations

import logging
import sys
import threading
import time
from typing import Any

from celery import Celery
from celery.signals import (
    after_setup_logger,
    after_setup_task_logger,
    worker_init,
    worker_process_init,
    worker_ready,
    worker_shutdown,
)

from jobs import db, heap, logs
from jobs.run import green, leases
from jobs.run.queue import SCHEDULE_TICK, celery_config
from jobs.settings import Settings, get_settings

log = logging.getLogger(__name__)

SWITCH_INTERVAL_S = 0.001  # CPython default: 0.005


def make_celery(settings: Settings) -> Celery:
    """A Celery app configured from `settings`, with dncq's tasks."""
    app = Celery("dncq", include=["worker.tasks"])
    app.conf.update(celery_config(settings))
    app.conf.dncq_settings = settings
    # Beat only ticks; the schedules themselves live in the database (jobs.schedules).
    app.conf.beat_schedule = {"dncq-schedule-tick": {"task": SCHEDULE_TICK,
                                                      "schedule": settings.schedule_tick_s}}
    return app


celery_app = make_celery(get_settings())


def run_celery(app: Celery, argv: list[str]) -> int:
    """Run the `celery` command line on `app` (e.g. `["worker", ...]`); its exit status.

    `Celery.worker_main` drops the status: a worker that ended on an unrecoverable error
    would exit 0, which a service manager's restart-on-failure takes for a clean stop.
    """
    from celery.bin.celery import celery as command
    from click.exceptions import ClickException, Exit

    command.params[0].default = app  # the `--app` option, as Celery.start sets it
    try:
        status = command.main(args=argv, standalone_mode=False)
    except Exit as exc:
        status = exc.exit_code
    except ClickException as exc:  # a bad option: said as Celery's own command says it
        exc.show()
        status = exc.exit_code
    finally:
        command.params[0].default = None
    return status if isinstance(status, int) else 0


PROBE_LOOK_S = 30.0  # how often the reaper looks for machines due a check (worker/prober.py)
FIRST_PROBE_AFTER_S = 5.0  # the first look, soon after start: the fleet page says who answers


class Reaper:
    """Every few seconds: requeue targets of dead workers and machines that came free."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="dncq-reaper")

    def start(self) -> None:
        ttl_s, every_s = self.settings.lease_ttl_s, self.settings.reaper_interval_s
        if every_s >= ttl_s * (1 - leases.HOLD_SHARE):
            # Leases run out 5/6 of a period on; the reaper must come by within the rest.
            log.warning("DNCQ_REAPER_INTERVAL_S (%g s) is not under a sixth of "
                        "DNCQ_LEASE_TTL_S (%g s): a dead worker's targets may wait longer "
                        "than one lease period", every_s, ttl_s)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._listeners is not None:
            self._listeners.stop()

    _listeners: Any = None  # worker.listener.Listeners, made by the reaper's thread

    def _run(self) -> None:
        from jobs import schedules
        from jobs.requests import drop
        from jobs.run import reaper
        from worker.listener import Listeners
        from worker.prober import Prober

        self._listeners = Listeners(self.settings)
        prober = Prober(self.settings)
        last_tick = last_scan = 0.0
        last_probe = time.monotonic() - PROBE_LOOK_S + FIRST_PROBE_AFTER_S
        while not self._stop.wait(self.settings.reaper_interval_s):
            try:
                reaper.reap(settings=self.settings)
                self._listeners.tick()
                if time.monotonic() - last_scan >= self.settings.request_scan_interval_s:
                    last_scan = time.monotonic()
                    drop.scan(settings=self.settings)
                if time.monotonic() - last_probe >= min(
                        PROBE_LOOK_S, self.settings.machine_check_interval_s):
                    last_probe = time.monotonic()
                    prober.tick()
                # The embedded mode has no beat: its reaper fires the schedules.
                embedded = not self.settings.broker_url
                if embedded and time.monotonic() - last_tick >= self.settings.schedule_tick_s:
                    last_tick = time.monotonic()
                    schedules.tick(settings=self.settings)
            except Exception as exc:  # a database hiccup must not end recovery for good
                if not db.unreachable(exc):
                    log.exception("reaper pass failed")
                    continue
                # A restart or a killed connection: the next pass connects afresh.
                cause = getattr(exc, "orig", None) or exc
                said = (str(cause).strip().splitlines() or [""])[0]
                log.warning("reaper pass cut short, the database did not answer (%s: %s); "
                            "tried again in %g s", type(cause).__name__, said,
                            self.settings.reaper_interval_s)


_reapers: list[Reaper] = []


@after_setup_logger.connect
@after_setup_task_logger.connect
def _json_logs(logger: logging.Logger | None = None, **_: Any) -> None:
    # Celery makes the handlers of the root and task loggers itself (worker and beat);
    # DNCQ_LOG_FORMAT=json turns what they write into JSON lines, wherever they write.
    if logger is not None and get_settings().log_format == "json":
        logs.as_json(logger)


@worker_ready.connect
def _start_reaper(sender: Any = None, **_: Any) -> None:
    settings = sender.app.conf.dncq_settings if sender is not None else get_settings()
    db.upgrade(settings.resolved_database_url)
    reaper = Reaper(settings)
    reaper.start()
    _reapers.append(reaper)


@worker_ready.connect
def _prompt_thread_switches(**_: Any) -> None:
    # A threads-pool worker is dozens of threads that wait on machines and wake for a few
    # milliseconds of work each; handing the interpreter over after 1 ms instead of 5 ms
    # keeps the consumer and the commit thread from queueing behind a busy one (three A/B
    # pairs of bench/batch_send.py: 500 targets in 3.17 s against 3.41 s on average, a
    # small gain inside that host's run-to-run noise).
    sys.setswitchinterval(SWITCH_INTERVAL_S)


CLAIMS_AHEAD = 2  # a gevent worker's tasks per operation slot


@worker_init.connect
def _size_the_pool(sender: Any = None, **_: Any) -> None:
    # A gevent worker runs `--concurrency` machine operations at once, in a pool of twice
    # as many greenlets: the others have claimed their next targets and start the moment a
    # slot frees (worker/runner.py OperationSlots). Its single consumer hands tasks to the
    # pool one message at a time, and a claim is a shared transaction to wait for; with
    # exactly one greenlet per slot both came between one operation and the next
    # (bench/batch_send.py, alternating: 1.46x and 1.31x the ideal against 1.72x and 1.65x).
    # `claim_ahead = false` turns it off: a target claimed ahead waits for a slot for up to
    # one operation, which with long ones (a large backup) another idle worker could have
    # run. Sent once the concurrency is known and before the pool is made.
    from jobs.run import redis_broker
    from worker.runner import OPERATION_SLOTS

    if sender is None or not isinstance(sender.concurrency, int) \
            or sender.options.get("autoscale"):
        return
    slots = None
    if green.active() and sender.app.conf.dncq_settings.claim_ahead:
        OPERATION_SLOTS.set_limit(sender.concurrency)
        slots, sender.concurrency = sender.concurrency, sender.concurrency * CLAIMS_AHEAD
    # What a poll of the broker takes beyond the one message it asked for must find a free
    # slot, and beyond the slots it polls after the workers with room (jobs/run/redis_broker.py).
    redis_broker.take_in_bulk_up_to(sender.concurrency, slots=slots)


@worker_ready.connect
def _say_operation_slots(**_: Any) -> None:
    from worker.runner import OPERATION_SLOTS

    if OPERATION_SLOTS.limit is not None:  # the banner above gives the pool's size
        log.info("%d machine operations at once; as many more tasks wait for a slot with "
                 "their targets claimed", OPERATION_SLOTS.limit)


@worker_process_init.connect
def _fresh_connections(**_: Any) -> None:
    # A prefork child must not share the parent's database connections.
    db.dispose_all()


@worker_shutdown.connect
def _stop_reaper(**_: Any) -> None:
    while _reapers:
        _reapers.pop().stop()


DRAIN_S = 10.0  # how long a stopping worker waits for the results it has yet to commit


@worker_shutdown.connect
def _commit_what_finished(**_: Any) -> None:
    # A runner hands its machine's last result over and returns (jobs.run.targets.finish_later);
    # a worker stopped in good order commits those before it exits.
    from jobs.run import targets

    if not targets.drain(DRAIN_S):
        log.warning("some results were not committed within %g s; the reaper recovers "
                    "their targets when their leases run out", DRAIN_S)


@worker_ready.connect
@worker_process_init.connect
def _settle_heap(**_: Any) -> None:
    # Last of the worker's start: what it made so far lives as long as the worker does.
    heap.settle()
