"""`/metrics`: the Prometheus exposition of the fleet's figures, read by prometheus-client's
own parser, with the counters moving as jobs run on a real queue and worker."""

from __future__ import annotations

import uuid
from datetime import timedelta
from typing import Any

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy import delete, insert, update

from jobs import db
from jobs.api.app import create_app
from jobs.backup_models import Backup, BackupStatus
from jobs.metrics.collector import FleetCollector
from jobs.metrics.figures import read
from jobs.models import (
    Job,
    JobKind,
    JobState,
    Machine,
    MachineCheck,
    MachineLease,
    Run,
    RunState,
    Target,
    TargetState,
    utcnow,
)
from tests.conftest import API_KEY
from tests.jobs.helpers import wait_done

PROGRAM = "G21 G90\nG0 X0 Y0\nM30\n"

Samples = dict[tuple[str, tuple[tuple[str, str], ...]], float]


def scrape(client: TestClient) -> Samples:
    """Every sample of one scrape, by name and labels, as prometheus-client parses them."""
    response = client.get("/metrics")
    assert response.status_code == 200
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(response.text)
            for s in family.samples}


def value(samples: Samples, name: str, **labels: str) -> float:
    return samples[(name, tuple(sorted(labels.items())))]


def mocks(n: int, **options: Any) -> list[dict[str, Any]]:
    return [{"id": f"m{i}", "name": f"M{i}", "model": "Mock", "options": dict(options)}
            for i in range(n)]


def test_metrics_without_the_api_key_are_refused(settings):
    with TestClient(create_app(settings)) as anonymous:
        assert anonymous.get("/metrics").status_code == 401
        assert anonymous.get("/metrics", headers={"X-Api-Key": "wrong"}).status_code == 403


def test_metrics_parse_as_prometheus_families_named_dncq_beside_the_process_ones(client):
    response = client.get("/metrics")
    assert response.headers["content-type"].startswith("text/plain")
    families = {f.name: f for f in text_string_to_metric_families(response.text)}
    ours = {name for name in families if name.startswith("dncq_")}
    assert {"dncq_jobs_finished", "dncq_targets_finished", "dncq_bytes_moved",
            "dncq_target_retries", "dncq_target_duration_seconds", "dncq_targets_pending",
            "dncq_targets_running", "dncq_targets_waiting_for_machine", "dncq_machines",
            "dncq_machine_leases", "dncq_backups", "dncq_backup_bytes", "dncq_dnc_runs",
            "dncq_dnc_lines_sent", "dncq_dnc_run_lines_per_second"} <= ours
    assert families["dncq_jobs_finished"].type == "counter"
    assert families["dncq_target_duration_seconds"].type == "histogram"
    assert "process_resident_memory_bytes" in families or "python_info" in families
    assert set(families) - ours <= {n for n in families if n.startswith(("process_", "python_"))}


def test_openmetrics_is_answered_when_the_scraper_asks_for_it(client):
    response = client.get("/metrics", headers={"Accept": "application/openmetrics-text"})
    assert response.headers["content-type"].startswith("application/openmetrics-text")
    assert response.text.rstrip().endswith("# EOF")


def test_counters_move_as_a_send_job_runs_and_the_queue_empties(
        queue_client, add_machines, queue_settings):
    add_machines(*mocks(3))
    before = scrape(queue_client)
    targets = [{"machineID": f"m{i}", "fileName": "P.nc"} for i in range(3)]
    targets.append({"machineID": "nope", "fileName": "P.nc"})  # fails at once: no machine
    job = queue_client.post("/api/jobs", json={"kind": "send", "content": PROGRAM,
                                               "targets": targets}).json()
    wait_done(queue_client, job["id"])
    after = scrape(queue_client)

    def gained(name: str, **labels: str) -> float:
        return value(after, name, **labels) - value(before, name, **labels)

    assert gained("dncq_targets_finished_total", kind="send", state="succeeded") == 3
    assert gained("dncq_targets_finished_total", kind="send", state="failed") == 1
    assert gained("dncq_jobs_finished_total", kind="send", state="failed") == 1
    assert gained("dncq_bytes_moved_total", kind="send") == 3 * len(PROGRAM)
    # The target refused at creation never started: three durations.
    assert gained("dncq_target_duration_seconds_count", kind="send") == 3
    assert gained("dncq_target_duration_seconds_bucket", kind="send", le="+Inf") == 3
    assert value(after, "dncq_targets_pending") == 0
    assert value(after, "dncq_targets_running") == 0
    assert value(after, "dncq_jobs", kind="send", state="running") == 0


def test_retries_count_the_attempts_beyond_the_first(queue_client, add_machines):
    add_machines({"id": "off", "name": "Off", "model": "Mock", "options": {"offline": True}})
    before = scrape(queue_client)
    job = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM, "max_attempts": 3,
        "targets": [{"machineID": "off", "fileName": "P.nc"}]}).json()
    wait_done(queue_client, job["id"])
    after = scrape(queue_client)
    assert value(after, "dncq_target_retries_total", kind="send") \
        - value(before, "dncq_target_retries_total", kind="send") == 2
    assert value(after, "dncq_targets_finished_total", kind="send", state="failed") \
        - value(before, "dncq_targets_finished_total", kind="send", state="failed") == 1


def record_finished_job(url: str, *, kind: JobKind = JobKind.SEND, targets: int = 1,
                        took_s: float = 1.0) -> str:
    """A finished job of `targets` succeeded targets that took `took_s` each."""
    job_id = uuid.uuid4().hex
    now = utcnow()
    with db.session_scope(url) as session:
        session.execute(insert(Job).values(id=job_id, kind=kind, state=JobState.SUCCEEDED,
                                           options={}, created_at=now - timedelta(seconds=took_s),
                                           finished_at=now))
        session.execute(insert(Target), [{
            "job_id": job_id, "position": i, "machine_id": "m0", "params": {},
            "state": TargetState.SUCCEEDED, "attempts": 1, "bytes_done": 0,
            "interrupted": False, "started_at": now - timedelta(seconds=took_s),
            "finished_at": now} for i in range(targets)])
    return job_id


def record_running_job(url: str, target: TargetState, attempts: int) -> str:
    """A job recorded running (queued to the workers) with one target as given."""
    job_id = uuid.uuid4().hex
    with db.session_scope(url) as session:
        session.execute(insert(Job).values(id=job_id, kind=JobKind.SEND, state=JobState.RUNNING,
                                           options={}))
        session.execute(insert(Target).values(job_id=job_id, position=0, machine_id="m0",
                                              params={}, state=target, attempts=attempts,
                                              bytes_done=0, interrupted=False))
    return job_id


def test_a_job_none_of_whose_targets_has_begun_counts_as_queued_as_the_api_shows_it(
        client, settings):
    url = settings.resolved_database_url
    waiting = record_running_job(url, TargetState.PENDING, attempts=0)
    begun = record_running_job(url, TargetState.RUNNING, attempts=1)
    retrying = record_running_job(url, TargetState.PENDING, attempts=1)

    samples = scrape(client)

    shown = {job_id: client.get(f"/api/jobs/{job_id}").json()["state"]
             for job_id in (waiting, begun, retrying)}
    assert shown == {waiting: "queued", begun: "running", retrying: "running"}
    assert value(samples, "dncq_jobs", kind="send", state="queued") == 1
    assert value(samples, "dncq_jobs", kind="send", state="running") == 2


def test_counters_do_not_go_down_when_finished_jobs_are_pruned(client, settings):
    url = settings.resolved_database_url
    job_id = record_finished_job(url, targets=2)
    counted = value(scrape(client), "dncq_targets_finished_total", kind="send", state="succeeded")
    assert counted == 2
    with db.session_scope(url) as session:
        session.execute(delete(Job).where(Job.id == job_id))
    again = scrape(client)
    assert value(again, "dncq_targets_finished_total", kind="send", state="succeeded") == 2
    assert value(again, "dncq_jobs_finished_total", kind="send", state="succeeded") == 1


def test_what_the_record_held_before_the_api_started_is_not_counted(settings):
    record_finished_job(settings.resolved_database_url, targets=5)
    with TestClient(create_app(settings), headers={"X-Api-Key": API_KEY}) as client:
        samples = scrape(client)
    assert value(samples, "dncq_targets_finished_total", kind="send", state="succeeded") == 0


def test_durations_are_put_in_buckets_by_the_database(database_url):
    for took_s in (0.2, 3.0, 3.0, 45.0):
        record_finished_job(database_url, kind=JobKind.DELETE, took_s=took_s)
    with db.session_scope(database_url) as session:
        histogram = read(session=session).target_durations["delete"]
    by_bound = dict(zip(histogram.bounds, histogram.counts, strict=True))
    assert (by_bound[0.1], by_bound[0.25], by_bound[2.5], by_bound[5], by_bound[30],
            by_bound[60]) == (0, 1, 1, 3, 3, 4)
    assert histogram.count == 4
    assert histogram.sum_s == pytest.approx(51.2, abs=0.01)


def test_leases_are_counted_by_their_holder_kind_and_expired_ones_left_out(client, settings):
    now = utcnow()
    with db.session_scope(settings.resolved_database_url) as session:
        session.execute(insert(MachineLease), [
            {"machine_id": "a", "slot": 0, "group": "job:j1", "holder": "1",
             "expires_at": now + timedelta(minutes=1)},
            {"machine_id": "b", "slot": 0, "group": "listen:b", "holder": "2",
             "expires_at": now + timedelta(minutes=1)},
            {"machine_id": "c", "slot": 0, "group": "job:j2", "holder": "3",
             "expires_at": now - timedelta(minutes=1)}])
    samples = scrape(client)
    assert value(samples, "dncq_machine_leases", group_kind="job") == 1
    assert value(samples, "dncq_machine_leases", group_kind="listen") == 1
    assert value(samples, "dncq_machine_leases", group_kind="api") == 0


def test_a_running_drip_feed_shows_its_lines_per_second_and_the_lines_sent_count(
        client, settings):
    now = utcnow()
    with db.session_scope(settings.resolved_database_url) as session:
        session.execute(insert(Run).values(
            job_id="r1", position=0, machine_id="2001", program_name="BIG.NC", program_id="x",
            state=RunState.RUNNING, started_at=now - timedelta(seconds=10), updated_at=now,
            lines_sent=500, lines_total=1000, header=[]))
    samples = scrape(client)
    assert value(samples, "dncq_dnc_runs", state="running") == 1
    assert value(samples, "dncq_dnc_run_lines_per_second", machine="2001") \
        == pytest.approx(50, rel=0.01)
    assert value(samples, "dncq_dnc_lines_sent_total") == 500


def test_a_stored_backup_counts_by_status_with_its_size_and_its_jobs_duration(
        client, settings):
    url = settings.resolved_database_url
    job_id = record_finished_job(url, kind=JobKind.BACKUP, took_s=90.0)
    with db.session_scope(url) as session:
        session.execute(insert(Backup).values(id="b1", job_id=job_id, name="B.zip",
                                              status=BackupStatus.PARTIAL, size=12345))
    samples = scrape(client)
    assert value(samples, "dncq_backups_total", status="partial") == 1
    assert value(samples, "dncq_backup_last_bytes") == 12345
    assert value(samples, "dncq_backup_bytes") == 12345
    assert value(samples, "dncq_backup_last_duration_seconds") == pytest.approx(90, abs=0.1)
    assert value(samples, "dncq_backup_duration_seconds_bucket", le="120.0") \
        - value(samples, "dncq_backup_duration_seconds_bucket", le="60.0") == 1


def test_a_scrape_that_cannot_read_the_database_says_so_and_nothing_else(tmp_path):
    collector = FleetCollector(f"sqlite:///{tmp_path / 'unmigrated.db'}")  # no tables
    families = list(collector.collect())
    assert [(f.name, [s.value for s in f.samples]) for f in families] \
        == [("dncq_database_up", [0])]


def test_machines_online_and_offline_follow_their_last_checks(client, add_machines, settings):
    add_machines(*mocks(2), {"id": "down", "name": "Down", "model": "Mock",
                             "options": {"offline": True}},
                 {"id": "never", "name": "Never", "model": "Mock"})
    before = scrape(client)
    checked = client.post("/api/machines/check", json={"ids": ["m0", "m1", "down"]})
    after = scrape(client)

    assert checked.status_code == 200
    assert [c["reachable"] for c in checked.json()] == [True, True, False]
    assert (value(before, "dncq_machines_online"), value(before, "dncq_machines_offline")) \
        == (0, 0)
    assert (value(after, "dncq_machines_online"), value(after, "dncq_machines_offline")) \
        == (2, 1)  # "never" is neither: nobody has checked it


def test_a_check_older_than_three_periods_counts_as_none_and_a_drip_feed_as_online(
        database_url):
    from jobs.fleet import checks

    with db.session_scope(database_url) as session:
        for machine_id in ("old", "new", "feeding"):
            session.add(Machine(id=machine_id, name=machine_id, model="Mock",
                                transport="mock"))
    checks.record(database_url, [{"id": m, "reachable": m != "feeding"}
                                 for m in ("old", "new", "feeding")])
    with db.session_scope(database_url) as session:
        session.execute(update(MachineCheck).where(MachineCheck.machine_id == "old")
                        .values(checked_at=utcnow() - timedelta(hours=1)))
        session.execute(insert(Run).values(
            job_id="r1", position=0, machine_id="feeding", program_name="BIG.NC",
            program_id="x", state=RunState.RUNNING, header=[]))
    with db.session_scope(database_url) as session:
        figures = read(session=session, check_max_age_s=900)
        forever = read(session=session, check_max_age_s=None)

    assert (figures.machines_online, figures.machines_offline) == (2, 0)  # new, feeding
    assert (forever.machines_online, forever.machines_offline) == (3, 0)
