"""`dncq machines reseal` masks a machine's secret in the messages already stored of it."""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import select

from jobs import db
from jobs.backup_models import Backup, BackupMachine, BackupStatus, MachineBackupStatus
from jobs.fleet import registry, scrub
from jobs.fleet.redact import MASK
from jobs.models import (
    Attempt,
    Job,
    JobKind,
    MachineCheck,
    Run,
    Target,
    TargetState,
    utcnow,
)

PASSWORD = "s3cr3t-pw"
ECHOED = "530 Login incorrect for S3CR3T-PW"  # pyftpdlib's refusal, the password capitalized


def _machine(session, data_dir: Path, machine_id: str, password: str) -> None:
    registry.upsert(session=session, data_dir=data_dir, machine_in=registry.MachineIn(
        id=machine_id, name=machine_id, model="FTP server", transport="ftp",
        options={"host": "127.0.0.1", "user": "cnc", "password": password}))


def _stored_messages(session, machine_id: str, text: str) -> None:
    """What an older dncq, whose mask missed the capitals, wrote of one machine."""
    session.add(Job(id=f"job-{machine_id}", kind=JobKind.SEND, targets=[Target(
        position=0, machine_id=machine_id, state=TargetState.FAILED, error_code=10,
        error_msg=text, status_msg=text, history=[Attempt(number=1, error_msg=text)])]))
    session.add(Run(job_id=f"run-{machine_id}", position=0, machine_id=machine_id,
                    program_name="O0010", program_id="0" * 64, message=text))
    session.add(Backup(id=f"b-{machine_id}", name="b.zip", status=BackupStatus.COMPLETE,
                       machines=[BackupMachine(
                           position=0, machine_id=machine_id, machine_name=machine_id,
                           status=MachineBackupStatus.FAILED, error_msg=text,
                           left_out=[{"path": "/O1", "reason": text}])]))
    session.add(MachineCheck(machine_id=machine_id, checked_at=utcnow(), reachable=False,
                             found={"error": text, "latency_ms": None}))


def _texts(session, machine_id: str) -> list[str]:
    target = session.scalars(select(Target).where(Target.machine_id == machine_id)).one()
    backup = session.scalars(select(BackupMachine).where(
        BackupMachine.machine_id == machine_id)).one()
    return [target.error_msg, target.status_msg, target.history[0].error_msg,
            session.scalars(select(Run.message).where(Run.machine_id == machine_id)).one(),
            backup.error_msg, backup.left_out[0]["reason"],
            session.get(MachineCheck, machine_id).found["error"]]


def test_reseal_masks_a_secret_stored_in_another_case_in_every_message_of_its_machine(
        database_url, tmp_path):
    with db.session_scope(database_url) as session:
        _machine(session, tmp_path, "ftp1", PASSWORD)
        _machine(session, tmp_path, "ftp2", "other-pw")
        _stored_messages(session, "ftp1", ECHOED)
        _stored_messages(session, "ftp2", ECHOED)  # not its secret: left as it is

    with db.session_scope(database_url) as session:
        changed = scrub.mask_stored(session=session, data_dir=tmp_path)

    assert changed == 5  # the target, its attempt, the run, the backup's machine, the check
    with db.session_scope(database_url) as session:
        assert _texts(session, "ftp1") == [f"530 Login incorrect for {MASK}"] * 7
        assert _texts(session, "ftp2") == [ECHOED] * 7
    with db.session_scope(database_url) as session:
        assert scrub.mask_stored(session=session, data_dir=tmp_path) == 0  # nothing left
