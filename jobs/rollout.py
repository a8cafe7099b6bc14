"""Batch requests into jobs: targets from a list or a fleet selector, payloads, dry runs."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy import select
from sqlalchemy.orm import Session

from jobs import folders, service
from jobs.backup import streamed
from jobs.errors import ContractError, ErrorCode, hint, result, unknown_machine
from jobs.fleet import door, registry
from jobs.fleet.paths import bad
from jobs.fleet.rules import FANUC_HEAD_BYTES, exists
from jobs.job_options import JobOptions
from jobs.models import Job, JobKind, Machine
from jobs.run import queue
from jobs.run.slot import machine_slot
from jobs.settings import Settings

DRY_RUN_THREADS = 16


class Selector(BaseModel):
    """Machines picked by id, by tag, or all of them."""

    model_config = ConfigDict(extra="forbid")

    ids: list[str] = Field(default_factory=list)
    tags: list[str] = Field(default_factory=list)
    all: bool = False


def select_targets(*, session: Session, selector: Selector, file_name: str | None,
                   dir_at_cnc: str | None, sub_dir: str | None) -> list[service.TargetIn]:
    """One target per selected machine: listed ids in their order, then tagged/all by id."""
    chosen: list[str] = list(dict.fromkeys(selector.ids))
    if selector.all or selector.tags:
        named, wanted = set(chosen), set(selector.tags)
        # Two columns of the fleet, not its machines: 100,000 of those took 3.3 s.
        for machine_id, tags in session.execute(
                select(Machine.id, Machine.tags).order_by(Machine.id)):
            if machine_id not in named and (selector.all or wanted & set(tags or ())):
                chosen.append(machine_id)
    if not chosen:
        raise bad("no machine selected: give targets, ids, tags or all")
    return [service.TargetIn(machineID=m, fileName=file_name, dirAtCNC=dir_at_cnc,
                             subDir=sub_dir) for m in chosen]


@dataclass(frozen=True)
class Unknown:
    """What a selector names that the registry does not have."""

    ids: list[str]  # machine ids no machine has
    tags: list[str]  # tags no machine carries
    hints: dict[str, str]  # " (did you mean 1010?)" for a name, when one is close (errors.hint)

    def __bool__(self) -> bool:
        return bool(self.ids or self.tags)

    def message(self) -> str:
        """Names them, with a known one each may have been meant as."""
        def named(values: list[str]) -> str:
            return ", ".join(v + self.hints.get(v, "") for v in values)

        parts = ([f"no machine {named(self.ids)}"] if self.ids else []) + (
            [f"no machine tagged {named(self.tags)}"] if self.tags else [])
        return "; ".join(parts)


def unknown(*, session: Session, selector: Selector) -> Unknown:
    """The ids and tags of `selector` that no registered machine has (typos, removed ones).

    Only the named machines are read; the whole fleet's ids only to hint at a missing one
    (in a fleet of up to registry.HINTED_FLEET machines, as a single request's miss), its
    tags only when tags are named. The first registry.HINTED_NAMES missing of each get a hint.
    """
    named = list(dict.fromkeys(selector.ids))
    registered = registry.of_ids(session=session, machine_ids=named)
    missing_ids = [i for i in named if i not in registered]
    tags = sorted({t for row in session.scalars(select(Machine.tags)) for t in row or ()}) \
        if selector.tags else []
    missing_tags = [t for t in dict.fromkeys(selector.tags) if t not in tags]
    hints = registry.hints(session=session, names=missing_ids) | {
        tag: hint(tag, tags) for tag in missing_tags[:registry.HINTED_NAMES]}
    return Unknown(missing_ids, missing_tags, hints)


def refuse_unknown(found: Unknown) -> ContractError:
    """The error that refuses a whole request for the unknown ids and tags it names."""
    code = ErrorCode.MACHINE_NOT_FOUND if found.ids else ErrorCode.BAD_PARAMETER
    # allow_unknown queues the job for the machines that are there
    return ContractError(code, f"{found.message()}; nothing was queued")


def payloads(*, session: Session, targets: list[service.TargetIn], content: str | None,
             data: bytes | None
             ) -> tuple[str, dict[int, str | ContractError]]:
    """Store the file once: `data` as given, or `content` (text with no encoding given) once
    per encoding the target machines are configured with.

    Returns the job's payload id and the per-position exceptions to it.
    """
    if data is not None:
        return service.store_payload(session=session, data=data), {}
    assert content is not None
    if content.isascii():  # the same bytes in every encoding a machine may have
        return service.store_payload(session=session, data=content.encode("ascii")), {}
    # No encoding given: each machine's configured encoding (contract 2.6.6).
    encodings = registry.column_of(session=session, column=Machine.encoding,
                                   machine_ids=[t.machineID for t in targets])
    default = service.store_payload(session=session, data=content.encode("utf-8"))
    per_target: dict[int, str | ContractError] = {}
    for position, t in enumerate(targets):
        enc = encodings.get(t.machineID, "utf-8")
        try:
            per_target[position] = service.store_payload(session=session,
                                                         data=content.encode(enc))
        except UnicodeEncodeError:
            per_target[position] = ContractError(ErrorCode.BAD_PARAMETER,
                                                 f"content cannot be written in {enc}")
    return default, per_target


def submit(*, session: Session, settings: Settings, kind: JobKind,
           targets: list[service.TargetIn], options: JobOptions,
           payload_id: str | None = None,
           target_payloads: dict[int, str | ContractError] | None = None,
           created_by: str = "api", recorded: Callable[[Job], None] | None = None) -> Job:
    """Create the job, commit it, and queue one task per machine.

    Args:
        recorded: called with the job before the commit, to record what started it in the
            same transaction.
    """
    file_name = next((t.fileName for t in targets if t.fileName), None)
    job = service.create(session=session, kind=kind, targets=targets, options=options,
                         payload_id=payload_id, target_payloads=target_payloads,
                         file_name=file_name, created_by=created_by)
    if recorded is not None:
        recorded(job)
    session.commit()  # the runners read it from their own sessions
    if kind is JobKind.BACKUP:  # a folder that cannot be made fails each target, saying why
        with contextlib.suppress(OSError):
            folders.job_folder(settings, job.id).mkdir(parents=True, exist_ok=True)
    queued = service.dispatch(settings=settings, job_id=job.id, fresh=True)
    if kind is JobKind.BACKUP and not queued:  # every target failed at once: record that
        queue.enqueue_assembly(settings, job.id)
    return job


def restore_replaced(*, session: Session, settings: Settings, job: Job,
                     created_by: str) -> Job:
    """A restore job that puts back every file `job` replaced, from the copies it kept."""
    replaced = [t for t in job.targets if t.replaced_payload_id]
    if not replaced:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"job {job.id} replaced no file")
    targets = [service.TargetIn(machineID=t.machine_id, **{  # the kept copies, not a backup's
        k: v for k, v in t.params.items() if k != "archivePath"}) for t in replaced]
    per_target: dict[int, str | ContractError] = {
        i: t.replaced_payload_id for i, t in enumerate(replaced)}  # type: ignore[misc]
    return submit(session=session, settings=settings, kind=JobKind.RESTORE, targets=targets,
                  options=JobOptions(replace=True, force=bool(job.options.get("force"))),
                  payload_id=replaced[0].replaced_payload_id, target_payloads=per_target,
                  created_by=created_by)


def dry_run(*, session: Session, settings: Settings, kind: JobKind,
            targets: list[service.TargetIn], options: JobOptions,
            data: bytes | None) -> list[dict[str, Any]]:
    """What each target would do, read from the machines without changing anything."""
    specs = registry.of_ids(session=session, machine_ids=[t.machineID for t in targets])

    def plan(position: int, t: service.TargetIn) -> dict[str, Any]:
        row: dict[str, Any] = {"position": position, "machineID": t.machineID, **t.params()}
        spec = specs.get(t.machineID)
        try:
            if spec is None:
                raise unknown_machine(t.machineID)
            with machine_slot(settings, spec, reading=True), door.open_files(
                    spec, data_dir=settings.data_dir) as files:
                row["action"] = _action(files, kind, t, options, data)
            row.update(result(ErrorCode.SUCCESS))
        except ContractError as exc:
            row.update(action="fail", **exc.body())
        return row

    with ThreadPoolExecutor(DRY_RUN_THREADS) as pool:
        return list(pool.map(plan, range(len(targets)), targets))


def _action(files: Any, kind: JobKind, t: service.TargetIn, options: JobOptions,
            data: bytes | None) -> str:
    if kind is JobKind.BACKUP:
        streamed.check_one(files, streamed.BackupTarget(machineID=t.machineID, **t.params()))
        return "back up"
    if kind is JobKind.DELETE:
        ref = files.ref(t.fileName, t.dirAtCNC, t.subDir)
        files.stat(ref)
        if not options.force:
            files.refuse_if_running(ref)
        return "delete"
    assert data is not None
    ref = files.send_ref(t.fileName, t.dirAtCNC, t.subDir, data[:FANUC_HEAD_BYTES])
    if not exists(files, ref):
        return f"send as {files.paths.listed_name(ref.name)}"
    # As the runner decides (worker.operations._send): the same bytes are never replaced.
    same = (options.skip_identical or options.replace) and files.holds(ref, len(data), [data])
    if same and options.skip_identical:
        return "skip (identical)"
    if not options.replace:
        raise ContractError(ErrorCode.PATH_EXISTS, f"{ref.name} is there; use replace")
    if same:
        return "nothing to replace (the same file is there)"
    if not options.force:
        files.refuse_if_running(ref)
    return "replace (old file kept)"
