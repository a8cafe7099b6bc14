"""The data folder is private, and machine secrets are sealed in the database."""

from __future__ import annotations

import stat
from pathlib import Path
from typing import Any

import pytest
from kombu import Connection

from jobs import db, models
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import door, registry, sealed
from jobs.run.queue import producer
from jobs.settings import Settings
from tests.jobs.helpers import run_backup

PASSWORD = "s3cret-Pa55-word"
FTP = {"id": "f1", "name": "Lathe", "model": "Fanuc 0i-F", "transport": "ftp",
       "options": {"host": "127.0.0.1", "port": 1, "user": "cnc", "password": PASSWORD}}


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def stored_bytes(settings: Settings) -> bytes:
    """Everything SQLite keeps on disk: the database and its write-ahead log."""
    base = settings.data_dir / "dncq.sqlite3"
    return b"".join(p.read_bytes() for p in (base, Path(f"{base}-wal")) if p.exists())


def stored_options(settings: Settings, machine_id: str) -> dict[str, Any]:
    with db.session_scope(settings.resolved_database_url) as session:
        return dict(session.get(models.Machine, machine_id).options)


def test_the_data_folder_is_made_0700_when_the_api_starts(settings, client) -> None:
    assert mode(settings.data_dir) == 0o700  # the fixture made it 0755


def test_the_database_and_its_wal_and_shm_files_are_0600(tmp_path) -> None:
    s = Settings(data_dir=tmp_path / "data", api_key="k" * 20)
    db.upgrade(s.resolved_database_url)

    files = sorted(s.data_dir.glob("dncq.sqlite3*"))
    assert [f.name for f in files] == ["dncq.sqlite3", "dncq.sqlite3-shm", "dncq.sqlite3-wal"]
    assert {f.name: mode(f) for f in files} == {f.name: 0o600 for f in files}
    assert mode(s.data_dir) == 0o700


def test_the_api_key_and_secrets_key_files_are_0600(tmp_path, monkeypatch) -> None:
    monkeypatch.delenv(sealed.KEY_ENV, raising=False)
    s = Settings(data_dir=tmp_path / "data")
    s.effective_api_key(create=True)
    sealed.keyring(s.data_dir)

    assert mode(s.data_dir / "api-key") == 0o600
    assert mode(s.data_dir / sealed.KEY_FILE) == 0o600


def test_a_mock_machines_state_files_are_0600(settings, client, add_machines) -> None:
    add_machines({"id": "m1", "name": "M1", "model": "Fanuc 0i-F", "options": {"trace": True}})
    locked = client.get("/api/cnc/lockFileByRange", params={
        "machineID": "m1", "isLock": "true", "lockStart": 8000, "lockEnd": 8999}).json()
    assert locked["errorCode"] == 0
    folder = settings.data_dir / "mock" / "m1"

    state = [folder / "counters", folder / "locks.json", folder / "trace"]
    assert {p.name: mode(p) for p in state} == {p.name: 0o600 for p in state}


def test_a_queued_message_file_is_0600(settings) -> None:
    conf = producer(settings.model_copy(update={"broker_url": None})).conf
    with Connection(conf.broker_url, transport=conf.broker_transport,
                    transport_options=conf.broker_transport_options) as conn:
        conn.SimpleQueue("modes").put({"n": 1})
    messages = list((settings.data_dir / "queue").glob("*.msg"))

    assert len(messages) == 1 and mode(messages[0]) == 0o600
    assert mode(settings.data_dir / "queue") == 0o700


def test_a_stored_backup_zip_is_0600(queue_client, add_machines, queue_settings) -> None:
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    backup = run_backup(queue_client, machines={"ids": ["a1"]})

    assert mode(queue_settings.data_dir / "backups" / backup["name"]) == 0o600


def test_a_machine_password_is_not_in_the_database_file(settings, client) -> None:
    assert client.post("/api/machines", json=FTP).status_code == 201

    assert PASSWORD.encode() not in stored_bytes(settings)
    assert sealed.is_sealed(stored_options(settings, "f1")["password"])


@pytest.mark.parametrize("sealed_by", ["this dncq's key", "another key"])
def test_a_password_given_already_sealed_is_refused_and_the_machine_not_saved(
        settings, client, sealed_by) -> None:
    keys = (sealed.keyring(settings.data_dir) if sealed_by == "this dncq's key"
            else sealed.Keyring([sealed.new_key()], source="another dncq"))
    given = {**FTP, "options": {**FTP["options"], "password": keys.seal(PASSWORD)}}

    answer = client.post("/api/machines", json=given)

    assert answer.status_code == 422 and answer.json()["errorCode"] == 20001
    assert answer.json()["statusMsg"] == (
        "options.password: dncq-sealed:v1:… is how dncq stores a secret, not one it takes: "
        "give the secret itself")
    assert client.get("/api/machines").json() == []


def test_a_sealed_password_is_given_to_the_transport_in_clear(settings, add_machines) -> None:
    spec = add_machines(FTP)[0]

    files = door.open_files(spec, data_dir=settings.data_dir)
    assert files.transport.inner.options.password.get_secret_value() == PASSWORD
    files.close()


def test_a_password_stored_before_sealing_is_used_and_sealed_on_the_next_write(
        settings, client) -> None:
    with db.session_scope(settings.resolved_database_url) as session:
        session.add(models.Machine(id="f1", name="Lathe", model="Fanuc 0i-F", transport="ftp",
                                   options=FTP["options"], tags=[]))
    with db.session_scope(settings.resolved_database_url) as session:
        spec = registry.get(session=session, machine_id="f1")
    with door.open_files(spec, data_dir=settings.data_dir) as files:
        assert files.transport.inner.options.password.get_secret_value() == PASSWORD

    shown = client.get("/api/machines/f1").json()
    assert client.put("/api/machines/f1", json={**shown, "name": "Lathe 2"}).status_code == 200

    assert sealed.is_sealed(stored_options(settings, "f1")["password"])


def test_secrets_sealed_with_a_key_from_the_environment_need_that_key(
        settings, add_machines, monkeypatch) -> None:
    monkeypatch.setenv(sealed.KEY_ENV, sealed.new_key())
    spec = add_machines(FTP)[0]
    monkeypatch.setenv(sealed.KEY_ENV, sealed.new_key())  # another installation's key

    with pytest.raises(ContractError) as refused:
        door.open_files(spec, data_dir=settings.data_dir)
    assert refused.value.code == ErrorCode.INTERNAL_ERROR
    assert f"the secrets of machine f1 cannot be read: a machine secret was sealed with a key " \
           f"${sealed.KEY_ENV} does not hold" == refused.value.status_msg
    assert not (settings.data_dir / sealed.KEY_FILE).exists()


def test_reseal_moves_every_secret_to_the_new_first_key(
        settings, add_machines, monkeypatch) -> None:
    old, new = sealed.new_key(), sealed.new_key()
    monkeypatch.setenv(sealed.KEY_ENV, old)
    add_machines(FTP)
    monkeypatch.setenv(sealed.KEY_ENV, f"{new},{old}")  # rotation: the new key first

    with db.session_scope(settings.resolved_database_url) as session:
        assert registry.reseal(session=session, data_dir=settings.data_dir) == 1
    monkeypatch.setenv(sealed.KEY_ENV, new)  # the old key is gone

    with db.session_scope(settings.resolved_database_url) as session:
        spec = registry.get(session=session, machine_id="f1")
    with door.open_files(spec, data_dir=settings.data_dir) as files:
        assert files.transport.inner.options.password.get_secret_value() == PASSWORD


def test_a_host_without_the_secrets_key_says_so_and_makes_none(
        settings, add_machines, monkeypatch, tmp_path) -> None:
    monkeypatch.delenv(sealed.KEY_ENV, raising=False)
    spec = add_machines(FTP)[0]
    elsewhere = tmp_path / "worker-host"  # a worker's own data folder on another host

    with pytest.raises(ContractError) as refused:
        door.open_files(spec, data_dir=elsewhere)
    assert refused.value.status_msg == (
        f"the secrets of machine f1 cannot be read: no secrets key: set {sealed.KEY_ENV} "
        f"(the same on every host) or give this host the data folder's {sealed.KEY_FILE}")
    assert not (elsewhere / sealed.KEY_FILE).exists()


def test_a_key_file_rewritten_is_read_again_by_a_running_process(
        settings, monkeypatch) -> None:
    from cryptography.fernet import Fernet

    monkeypatch.delenv(sealed.KEY_ENV, raising=False)
    first = sealed.keyring(settings.data_dir)  # makes the key file
    assert sealed.keyring(settings.data_dir) is first  # unchanged: not read again
    token = first.seal("pw")
    old = (settings.data_dir / sealed.KEY_FILE).read_text().strip()
    new = sealed.new_key()
    (settings.data_dir / sealed.KEY_FILE).write_text(f"{new}\n{old}\n")  # rotation

    ring = sealed.keyring(settings.data_dir)
    assert ring.unseal(token) == "pw"  # the old key still unseals
    resealed = ring.seal("pw").removeprefix(sealed.PREFIX)
    assert Fernet(new.encode()).decrypt(resealed.encode()) == b"pw"  # the new key seals
