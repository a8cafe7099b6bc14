"""GET /api/jobs/{id} a page of targets at a time, and `dncq job` on those pages."""

from __future__ import annotations

from typing import Any

import pytest
from sqlalchemy import update

from jobs import db, job_views, service
from jobs.job_options import JobOptions
from jobs.models import JobKind, Target, TargetState
from tests.jobs.cli.runner import dncq
from tests.live_server import serving

MACHINES = ["a", "b", "c"]


@pytest.fixture
def big_job(settings, add_machines) -> str:
    """A recorded job of 25 targets over three machines; every fourth one failed."""
    add_machines(*[{"id": m, "name": m.upper(), "model": "Mock"} for m in MACHINES])
    targets = [service.TargetIn(machineID=MACHINES[i % 3], fileName=f"P{i}.nc")
               for i in range(25)]
    with db.session_scope(settings.resolved_database_url) as session:
        job = service.create(session=session, kind=JobKind.SEND, targets=targets,
                             options=JobOptions())
        session.flush()
        session.execute(update(Target).where(Target.job_id == job.id,
                                             Target.position % 4 == 0)
                        .values(state=TargetState.FAILED, error_code=158,
                                error_msg="File not found."))
        return job.id


def pages(client: Any, job_id: str, **params: Any) -> list[dict[str, Any]]:
    """Every page of the job's view, following nextAfter."""
    found = [client.get(f"/api/jobs/{job_id}", params=params).json()]
    while found[-1]["nextAfter"] is not None:
        found.append(client.get(f"/api/jobs/{job_id}",
                                params={**params, "after": found[-1]["nextAfter"]}).json())
    return found


def test_paging_through_a_job_returns_every_target_once_in_request_order(client, big_job):
    read = pages(client, big_job, limit=10)

    assert [len(p["targets"]) for p in read] == [10, 10, 5]
    assert [t["position"] for p in read for t in p["targets"]] == list(range(25))
    assert [t["fileName"] for t in read[2]["targets"]] == [f"P{i}.nc" for i in range(20, 25)]


def test_every_page_carries_the_whole_jobs_counts(client, big_job):
    read = pages(client, big_job, limit=10)

    for page in read:
        assert page["total"] == 25
        assert page["counts"]["failed"] == 7 and page["counts"]["pending"] == 18


def test_a_page_can_hold_only_failed_targets_or_one_machines(client, big_job):
    failed = pages(client, big_job, state="failed", limit=3)
    on_b = pages(client, big_job, machine="b")

    assert [t["position"] for p in failed for t in p["targets"]] == [0, 4, 8, 12, 16, 20, 24]
    assert {t["state"] for p in failed for t in p["targets"]} == {"failed"}
    assert [t["position"] for t in on_b[0]["targets"]] == list(range(1, 25, 3))


def test_a_page_of_a_mistyped_machines_targets_is_refused_naming_the_machine_meant(
        client, add_machines, big_job):
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})

    page = client.get(f"/api/jobs/{big_job}", params={"machine": "1O10"})  # a letter O

    assert page.status_code == 404
    assert page.json() == {"errorCode": 10003, "errorMsg": "Machine ID does not exist.",
                           "statusMsg": "Invalid MachineID (1O10) (did you mean 1010?)"}


def test_a_page_of_a_registered_machine_with_no_target_in_the_job_is_empty(
        client, add_machines, big_job):
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})

    page = client.get(f"/api/jobs/{big_job}", params={"machine": "1010"})

    assert page.status_code == 200, page.text
    assert page.json()["targets"] == []


def test_limit_zero_answers_the_summary_without_targets(client, big_job):
    body = client.get(f"/api/jobs/{big_job}", params={"limit": 0}).json()

    assert body["targets"] == [] and body["total"] == 25


@pytest.mark.parametrize("params", [{"limit": -1}, {"limit": job_views.TARGET_PAGE_MAX + 1},
                                    {"after": "x"}, {"after": 2**63}, {"state": "exploded"}])
def test_a_bad_page_request_is_refused_with_400(client, big_job, params):
    response = client.get(f"/api/jobs/{big_job}", params=params)

    assert response.status_code == 400
    assert response.json()["errorCode"] == 20001


def test_dncq_job_shows_one_page_and_says_how_to_get_the_next(settings, big_job, monkeypatch):
    from jobs.api.app import create_app
    from jobs.settings import get_settings
    from tests.conftest import API_KEY

    with serving(create_app(settings)) as live:
        monkeypatch.setenv("DNCQ_URL", live.url)
        monkeypatch.setenv("DNCQ_API_KEY", API_KEY)
        get_settings.cache_clear()  # the CLI reads its settings once
        try:
            first = dncq("job", big_job, "--limit", "10")
            last = dncq("job", big_job, "--limit", "10", "--after", "19")
        finally:
            get_settings.cache_clear()

    assert "P9.nc" in first.output and "P10.nc" not in first.output
    # the hint keeps the page size that was asked for
    assert f"dncq job {big_job} --limit 10 --after 9" in first.output
    assert "P24.nc" in last.output and "--after" not in last.output
    assert first.exit_code == 1  # the job has failed targets, as with every `dncq job`
