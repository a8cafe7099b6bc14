"""Who a job, a library version or a decision is recorded as made by."""

from __future__ import annotations

from jobs.auth.roles import Role
from tests.conftest import API_KEY


def test_a_named_keys_job_is_recorded_as_the_keys_not_as_what_the_client_claims(
        api, make_key) -> None:
    key = make_key(Role.PROGRAMMER, name="ci-robot")
    answer = api.post("/api/jobs", headers={"X-Api-Key": key},
                      json={"kind": "delete", "machines": {"ids": ["1010"]},
                            "fileName": "NOPE.NC", "created_by": "somebody-else"})
    assert answer.status_code == 202, answer.text
    job = api.get(f"/api/jobs/{answer.json()['id']}", headers={"X-Api-Key": key}).json()
    assert job["createdBy"] == "key:ci-robot"


def test_the_shared_admin_key_records_what_the_client_says(api) -> None:
    admin = {"X-Api-Key": API_KEY}
    answer = api.post("/api/jobs", headers=admin,
                      json={"kind": "delete", "machines": {"ids": ["1010"]},
                            "fileName": "NOPE.NC", "created_by": "alice"})
    assert answer.status_code == 202, answer.text
    job = api.get(f"/api/jobs/{answer.json()['id']}", headers=admin).json()
    assert job["createdBy"] == "alice"


def test_a_library_version_added_with_a_named_key_is_the_keys(api, make_key) -> None:
    key = make_key(Role.PROGRAMMER, name="cam-station")
    added = api.post("/api/library/programs", headers={"X-Api-Key": key,
                                                        "content-type": "application/octet-stream"},
                     params={"folder": "VIPROS", "name": "0010", "by": "mallory"},
                     content=b"%\nO0010\nM30\n%\n")
    assert added.status_code in (200, 201), added.text
    assert added.json()["version"]["createdBy"] == "key:cam-station"
