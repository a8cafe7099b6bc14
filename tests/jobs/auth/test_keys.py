"""Named API keys: shown once when made, kept as a hash, listed by their first characters,
refused once revoked (401); the admin key keeps working; a named key acts with its role."""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import select

from jobs import db
from jobs.auth import passwords, service
from jobs.auth.models import ApiKey
from tests.conftest import API_KEY

ADMIN = {"X-Api-Key": API_KEY}


def _made(api, **body):
    return api.post("/api/keys", headers=ADMIN, json={"name": "robot", "role": "operator",
                                                      **body})


def test_a_new_key_is_in_the_answer_that_makes_it(api) -> None:
    made = _made(api)

    assert made.status_code == 201
    key = made.json()["key"]
    assert key.startswith("dncq_") and len(key) > 40
    assert api.get("/api/machines", headers={"X-Api-Key": key}).status_code == 200


def test_a_key_is_never_shown_again_only_its_first_characters(api) -> None:
    key = _made(api).json()["key"]

    listed = api.get("/api/keys", headers=ADMIN)

    assert key not in listed.text
    assert listed.json()[0]["prefix"] == key[:passwords.KEY_SHOWN_CHARS]


def test_the_database_keeps_the_keys_sha256_not_the_key(api, settings) -> None:
    key = _made(api).json()["key"]

    with db.session_scope(settings.resolved_database_url) as session:
        row = session.scalars(select(ApiKey)).one()
        kept = [str(v) for v in vars(row).values()]
    assert row.key_hash == passwords.key_digest(key)
    assert not [v for v in kept if key in v]


def test_a_revoked_key_is_refused_with_401(api) -> None:
    key = _made(api).json()["key"]

    revoked = api.delete("/api/keys/robot", headers=ADMIN)
    refused = api.get("/api/machines", headers={"X-Api-Key": key})

    assert revoked.status_code == 200 and revoked.json()["revoked"]
    assert refused.status_code == 401
    assert refused.json()["errorCode"] == 20403


def test_a_revoked_keys_refusal_says_it_was_revoked(api) -> None:
    key = _made(api).json()["key"]
    api.delete("/api/keys/robot", headers=ADMIN)

    refused = api.get("/api/machines", headers={"X-Api-Key": key})

    assert refused.json() == {"errorCode": 20403, "errorMsg": "API key is not valid.",
                              "statusMsg": "key robot was revoked"}


def test_a_key_nobody_has_is_refused_with_403(api) -> None:
    assert api.get("/api/machines", headers={"X-Api-Key": "dncq_nope"}).status_code == 403


def test_the_admin_key_and_a_named_key_work_side_by_side(api, make_key) -> None:
    named = make_key("viewer")

    assert api.get("/api/machines", headers=ADMIN).status_code == 200
    assert api.get("/api/machines", headers={"X-Api-Key": named}).status_code == 200


def test_a_named_key_in_the_apikey_query_parameter_is_accepted(api, make_key) -> None:
    named = make_key("viewer")

    assert api.get(f"/api/machines?apikey={named}").status_code == 200


def test_a_named_key_name_that_is_taken_is_refused_with_409(api) -> None:
    _made(api)

    assert _made(api).status_code == 409


def test_last_use_is_noted_at_most_once_a_minute(api, make_key, settings, monkeypatch) -> None:
    key = make_key("viewer", name="reader")

    def last_used():
        with db.session_scope(settings.resolved_database_url) as session:
            return service.get_key(session=session, name="reader").last_used_at

    api.get("/api/machines", headers={"X-Api-Key": key})
    first = last_used()
    api.get("/api/machines", headers={"X-Api-Key": key})
    assert first is not None and last_used() == first

    later = first + timedelta(seconds=service.LAST_USED_EVERY_S + 1)
    monkeypatch.setattr(service, "utcnow", lambda: later)
    api.get("/api/machines", headers={"X-Api-Key": key})
    assert last_used() == later


def test_a_key_never_appears_in_an_answer_but_its_own(api, make_key) -> None:
    key = _made(api).json()["key"]
    answers = [api.get("/api/keys", headers=ADMIN), api.get("/api/audit", headers=ADMIN),
               api.get("/api/audit.csv", headers=ADMIN),
               api.get("/api/machines", headers={"X-Api-Key": key}),
               api.post("/api/machines/check", headers={"X-Api-Key": key}, json={"all": True})]

    assert [a for a in answers if key in a.text] == []


def test_an_admin_key_or_user_with_a_machine_list_is_refused(api) -> None:
    key = _made(api, role="admin", machines=["1010"])
    user = api.post("/api/users", headers=ADMIN, json={
        "name": "ann", "password": "a long password", "role": "admin", "machines": ["1010"]})
    api.post("/api/users", headers=ADMIN, json={
        "name": "bob", "password": "a long password", "role": "operator", "machines": ["1010"]})
    promoted = api.patch("/api/users/bob", headers=ADMIN, json={"role": "admin"})

    assert (key.status_code, user.status_code, promoted.status_code) == (422, 422, 422)
    assert "an admin may change every machine: give it no machine list" in key.text
    assert api.get("/api/keys", headers=ADMIN).json() == []
    assert [u["role"] for u in api.get("/api/users", headers=ADMIN).json()] == ["operator"]


def test_a_key_or_user_limited_to_a_look_alike_of_a_machine_is_refused_naming_that_machine(
        api) -> None:
    key = _made(api, machines=["1O10"])
    user = api.post("/api/users", headers=ADMIN, json={
        "name": "ann", "password": "a long password", "role": "operator", "machines": ["1O11"]})

    assert (key.status_code, user.status_code) == (422, 422)
    assert "no machine has the id 1O10 (did you mean 1010?)" in key.json()["statusMsg"]
    assert "no machine has the id 1O11 (did you mean 1011?)" in user.json()["statusMsg"]
    assert api.get("/api/keys", headers=ADMIN).json() == []
