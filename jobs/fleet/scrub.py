"""Secrets masked in the messages the database already holds of each machine (`dncq machines
reseal`): a message written while the mask missed a spelling (a password a server echoed in
capitals, before secrets were masked in any case) shows it until it is masked again."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from sqlalchemy import or_, select, update
from sqlalchemy.orm import Session

from jobs.backup_models import BackupMachine
from jobs.fleet import door, registry
from jobs.fleet.redact import Redactor
from jobs.models import Attempt, MachineCheck, Run, Target


def mask_stored(*, session: Session, data_dir: Path) -> int:
    """Mask every machine's secrets in the messages stored of it; returns the rows changed."""
    changed = 0
    for spec in registry.list_all(session=session):
        redactor = Redactor(door.secrets_of(spec, data_dir))
        if not redactor.secrets:
            continue
        for model, key, columns, query in _stores(spec.id):
            masked = []
            for row in session.execute(query).yield_per(1000):
                stored = dict(zip((c.key for c in columns), row[1:], strict=True))
                values = {name: _masked(text, redactor) for name, text in stored.items()}
                if values != stored:
                    masked.append({key.key: row[0], **values})
            if masked:  # after the read: a cursor still open would see its own updates
                session.execute(update(model), masked)
                changed += len(masked)
    session.flush()
    return changed


def _stores(machine_id: str) -> Iterator[tuple[Any, Any, tuple[Any, ...], Any]]:
    """Each table's rows of the machine that hold a message: (model, key, columns, query)."""
    for model, key, columns in (
            (Target, Target.id, (Target.error_msg, Target.status_msg)),
            (Run, Run.id, (Run.message,)),
            (BackupMachine, BackupMachine.id, (BackupMachine.error_msg, BackupMachine.left_out)),
            (MachineCheck, MachineCheck.machine_id, (MachineCheck.found,))):
        query = select(key, *columns).where(
            model.machine_id == machine_id, or_(*(c.is_not(None) for c in columns)))
        yield model, key, columns, query
    yield Attempt, Attempt.id, (Attempt.error_msg,), select(Attempt.id, Attempt.error_msg).join(
        Target, Attempt.target_id == Target.id).where(
        Target.machine_id == machine_id, Attempt.error_msg.is_not(None))


def _masked(value: Any, redactor: Redactor) -> Any:
    """`value` with the secrets masked in every text it holds (a JSON column's too)."""
    if isinstance(value, str):
        return redactor.text(value)
    if isinstance(value, list):
        return [_masked(item, redactor) for item in value]
    if isinstance(value, dict):
        return {k: _masked(item, redactor) for k, item in value.items()}
    return value
