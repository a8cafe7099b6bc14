"""The Prometheus collector of the fleet's figures, and the registry `/metrics` serves.

Counters are counted from when this process started: at each scrape, what the record
gained since the previous scrape is added (`Tally`). Pruning old jobs and backups, or
retrying failed targets, lowers the record's totals; a counter read straight from them
would go down, which Prometheus takes for a restart and counts the whole total again.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Hashable, Iterable, Iterator
from typing import Any

from prometheus_client import (
    GC_COLLECTOR,
    PLATFORM_COLLECTOR,
    PROCESS_COLLECTOR,
    CollectorRegistry,
)
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector

from jobs.db import session_scope
from jobs.metrics.figures import BACKUP_BUCKETS_S, TARGET_BUCKETS_S, Figures, Histogram, read
from jobs.models import JobKind, JobState, RunState, TargetState

log = logging.getLogger(__name__)

_FINAL_JOB_STATES = [JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED]
_FINAL_TARGET_STATES = [s for s in TargetState if s.final]


class Tally:
    """Counters that only go up: the increases of the record's totals since a baseline."""

    def __init__(self) -> None:
        self._last: dict[Hashable, float] = {}
        self._total: dict[Hashable, float] = {}
        self._lock = threading.Lock()  # two scrapes at once must not add a gain twice

    def baseline(self, values: dict[Hashable, float]) -> None:
        """Count from these totals on: what the record held before is not counted."""
        with self._lock:
            self._last = dict(values)
            self._total = {}

    def add(self, values: dict[Hashable, float]) -> dict[Hashable, float]:
        """The counters after the record's totals became `values` (a missing key is 0)."""
        with self._lock:
            for key in set(values) | set(self._last):
                now = values.get(key, 0)
                gained = now - self._last.get(key, 0)
                if gained > 0:
                    self._total[key] = self._total.get(key, 0) + gained
                self._last[key] = now
            return dict(self._total)  # a total whose records were all pruned stays counted


def _totals(figures: Figures) -> dict[Hashable, float]:
    """Every counted total of the record, by a key of its own."""
    values: dict[Hashable, float] = {}
    for (kind, state), n in figures.jobs.items():
        values[("jobs", kind, state)] = n
    for (kind, state), t in figures.targets.items():
        values[("targets", kind, state)] = t.count
        values[("bytes", kind)] = values.get(("bytes", kind), 0) + t.bytes_moved
        values[("retries", kind)] = values.get(("retries", kind), 0) + t.retries
    backup = JobKind.BACKUP.value
    values[("bytes", backup)] = values.get(("bytes", backup), 0) + figures.backup_file_bytes
    for kind, histogram in figures.target_durations.items():
        _histogram_totals(values, ("duration", kind), histogram)
    for status, n in figures.backups.items():
        values[("backups", status)] = n
    _histogram_totals(values, ("backup_duration",), figures.backup_durations)
    values[("lines",)] = figures.run_lines_sent
    return values


def _histogram_totals(values: dict[Hashable, float], key: tuple[str, ...],
                      histogram: Histogram) -> None:
    for bound, n in zip(histogram.bounds, histogram.counts, strict=True):
        values[(*key, bound)] = n
    values[(*key, "count")] = histogram.count
    values[(*key, "sum")] = histogram.sum_s


class FleetCollector(Collector):
    """The fleet's figures, read from the database at each scrape."""

    def __init__(self, url: str, *, check_max_age_s: float | None = None) -> None:
        self.url = url
        self.check_max_age_s = check_max_age_s
        self.tally = Tally()
        self._counted_from_start = False
        try:
            self.tally.baseline(_totals(self._read()))
            self._counted_from_start = True
        except Exception as exc:  # counted from the first scrape that reads the database
            log.warning("metrics: the database could not be read at start (%s)", exc)

    def _read(self) -> Figures:
        with session_scope(self.url) as session:
            return read(session=session, check_max_age_s=self.check_max_age_s)

    def collect(self) -> Iterator[Metric]:
        """The metric families of one scrape."""
        up = GaugeMetricFamily("dncq_database_up",
                               "Whether the database answered this scrape (0: no other figures)")
        try:
            figures = self._read()
        except Exception as exc:  # a scrape says the database is down instead of failing
            log.warning("metrics: the database could not be read (%s)", exc)
            up.add_metric([], 0)
            yield up
            return
        up.add_metric([], 1)
        yield up
        if not self._counted_from_start:
            self.tally.baseline(_totals(figures))
            self._counted_from_start = True
        counted = self.tally.add(_totals(figures))
        yield from _job_families(figures, counted)
        yield from _target_families(figures, counted)
        yield from _fleet_families(figures)
        yield from _backup_families(figures, counted)
        yield from _run_families(figures, counted)


def _job_families(figures: Figures, counted: dict[Hashable, float]) -> Iterator[Metric]:
    current = GaugeMetricFamily("dncq_jobs", "Jobs not yet final, by kind and state",
                                labels=["kind", "state"])
    finished = CounterMetricFamily("dncq_jobs_finished", "Jobs that reached a final state",
                                   labels=["kind", "state"])
    for kind in JobKind:
        for state in (JobState.QUEUED, JobState.RUNNING):
            current.add_metric([kind.value, state.value],
                               figures.jobs.get((kind.value, state.value), 0))
        for state in _FINAL_JOB_STATES:
            finished.add_metric([kind.value, state.value],
                                counted.get(("jobs", kind.value, state.value), 0))
    yield current
    yield finished


def _target_families(figures: Figures, counted: dict[Hashable, float]) -> Iterator[Metric]:
    finished = CounterMetricFamily("dncq_targets_finished",
                                   "Targets that reached a final state, by job kind",
                                   labels=["kind", "state"])
    moved = CounterMetricFamily("dncq_bytes_moved", "Bytes moved to and from the machines",
                                labels=["kind"])
    retries = CounterMetricFamily("dncq_target_retries",
                                  "Attempts of targets beyond their first", labels=["kind"])
    durations = HistogramMetricFamily("dncq_target_duration_seconds",
                                      "Time from a target's last start to its end",
                                      labels=["kind"])
    for kind in JobKind:
        for state in _FINAL_TARGET_STATES:
            finished.add_metric([kind.value, state.value],
                                counted.get(("targets", kind.value, state.value), 0))
        moved.add_metric([kind.value], counted.get(("bytes", kind.value), 0))
        retries.add_metric([kind.value], counted.get(("retries", kind.value), 0))
        _add_histogram(durations, [kind.value], ("duration", kind.value), TARGET_BUCKETS_S,
                       counted)
    yield from (finished, moved, retries, durations)

    def in_state(state: TargetState) -> int:
        return sum(t.count for (_, s), t in figures.targets.items() if s == state.value)

    yield _gauge("dncq_targets_pending", "Targets waiting to run", in_state(TargetState.PENDING))
    yield _gauge("dncq_targets_running", "Targets a runner holds", in_state(TargetState.RUNNING))
    yield _gauge("dncq_targets_waiting_for_machine",
                 "Pending targets not queued: their machine was busy (lease waits)",
                 sum(t.waiting for t in figures.targets.values()))


def _fleet_families(figures: Figures) -> Iterator[Metric]:
    machines = GaugeMetricFamily("dncq_machines", "Machines in the registry",
                                 labels=["transport", "enabled"])
    for (transport, enabled), n in sorted(figures.machines.items()):
        machines.add_metric([transport, "true" if enabled else "false"], n)
    leases = GaugeMetricFamily("dncq_machine_leases",
                               "Machine slots held, by holder: job, api (a single-machine "
                               "request), listen (a listener), yield, requests",
                               labels=["group_kind"])
    for kind in ("job", "api", "listen"):  # always there, so that a panel starts at zero
        leases.add_metric([kind], figures.leases.get(kind, 0))
    for kind, n in sorted(figures.leases.items()):
        if kind not in ("job", "api", "listen"):
            leases.add_metric([kind], n)
    yield machines
    yield _gauge("dncq_machines_online", "Enabled machines that answered their last check "
                 "(kept for 3 check periods), or are drip-feeding", figures.machines_online)
    yield _gauge("dncq_machines_offline", "Enabled machines whose last check found them "
                 "unreachable", figures.machines_offline)
    yield leases


def _backup_families(figures: Figures, counted: dict[Hashable, float]) -> Iterator[Metric]:
    backups = CounterMetricFamily("dncq_backups", "Stored backups made, by status",
                                  labels=["status"])
    for status in ("complete", "partial", "failed"):
        backups.add_metric([status], counted.get(("backups", status), 0))
    yield backups
    yield _gauge("dncq_backup_bytes", "Bytes of the backup ZIPs kept", figures.backup_bytes)
    last = figures.last_backup
    yield _gauge("dncq_backup_last_bytes", "Bytes of the newest backup ZIP",
                 last.size if last else 0)
    yield _gauge("dncq_backup_last_timestamp_seconds", "When the newest backup was stored "
                 "(Unix time; 0: none)", last.created_at.timestamp() if last else 0)
    yield _gauge("dncq_backup_last_duration_seconds", "How long the newest backup's job took",
                 last.duration_s if last and last.duration_s is not None else 0)
    durations = HistogramMetricFamily("dncq_backup_duration_seconds",
                                      "How long backup jobs took, from their creation to "
                                      "their last target")
    _add_histogram(durations, [], ("backup_duration",), BACKUP_BUCKETS_S, counted)
    yield durations


def _run_families(figures: Figures, counted: dict[Hashable, float]) -> Iterator[Metric]:
    runs = GaugeMetricFamily("dncq_dnc_runs", "Drip-feed runs in the record, by state",
                             labels=["state"])
    for state in RunState:
        runs.add_metric([state.value], figures.runs.get(state.value, 0))
    yield runs
    lines = CounterMetricFamily("dncq_dnc_lines_sent", "Program lines drip-fed to machines")
    lines.add_metric([], counted.get(("lines",), 0))
    yield lines
    rate = GaugeMetricFamily("dncq_dnc_run_lines_per_second",
                             "A running drip-feed's lines per second since it started",
                             labels=["machine"])
    for run in figures.running:
        rate.add_metric([run.machine_id], run.lines_per_s)
    yield rate


def _gauge(name: str, documentation: str, value: float) -> GaugeMetricFamily:
    return GaugeMetricFamily(name, documentation, value=value)


def _add_histogram(family: HistogramMetricFamily, labels: list[str], key: tuple[str, ...],
                   bounds: tuple[float, ...], counted: dict[Hashable, float]) -> None:
    """Add a histogram's counted buckets; each bucket kept at most the next one up, as
    cumulative buckets are, should one gain what a wider one lost in the same scrape."""
    count = counted.get((*key, "count"), 0)
    buckets: list[tuple[str, float]] = [("+Inf", count)]
    ceiling = count
    for bound in reversed(bounds):
        ceiling = min(ceiling, counted.get((*key, bound), 0))
        buckets.append((_bound(bound), ceiling))
    family.add_metric(labels, list(reversed(buckets)), counted.get((*key, "sum"), 0))


def _bound(bound: float) -> str:
    return f"{bound:g}" if bound != int(bound) else f"{int(bound)}.0"


def registry_for(url: str, *, check_max_age_s: float | None = None) -> CollectorRegistry:
    """A registry of the fleet's figures from `url`, and this process's own metrics."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(FleetCollector(url, check_max_age_s=check_max_age_s))
    for default in _process_collectors():
        registry.register(default)
    return registry


def _process_collectors() -> Iterable[Any]:
    # The default registry's own collectors, shared: they read this process, whichever
    # registry asks.
    return (PROCESS_COLLECTOR, PLATFORM_COLLECTOR, GC_COLLECTOR)
