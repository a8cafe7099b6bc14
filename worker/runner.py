"""Runs one job's targets on one machine, in request order, under the machine's lease."""

from __future__ import annotations

import hashlib
import io
import logging
import os
import socket
import threading
import time
from collections import OrderedDict

from jobs import leases, machines, service
from jobs.db import session_scope
from jobs.errors import ContractError, ErrorCode
from jobs.models import JobKind, Payload, TargetState
from jobs.rules import FANUC_HEAD_BYTES, FileRef, MachineFiles
from jobs.settings import Settings

log = logging.getLogger(__name__)

WORKER_NAME = f"{socket.gethostname()}:{os.getpid()}"
PROGRESS_EVERY_S = 1.0  # how often a large transfer writes its progress


class PayloadCache:
    """Payload bytes by id, kept in memory up to `max_bytes` (payloads never change)."""

    def __init__(self, max_bytes: int = 64 * 1024 * 1024) -> None:
        self.max_bytes = max_bytes
        self._items: OrderedDict[str, bytes] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, url: str, payload_id: str) -> bytes:
        with self._lock:
            if payload_id in self._items:
                self._items.move_to_end(payload_id)
                return self._items[payload_id]
        with session_scope(url) as session:
            payload = session.get(Payload, payload_id)
            if payload is None:
                raise ContractError(ErrorCode.INTERNAL_ERROR, f"payload {payload_id} is gone")
            data = payload.data
        with self._lock:
            self._items[payload_id] = data
            while sum(len(v) for v in self._items.values()) > self.max_bytes and self._items:
                self._items.popitem(last=False)
        return data


PAYLOADS = PayloadCache()


def run_machine(settings: Settings, job_id: str, machine_id: str) -> None:
    """Run the job's due targets on the machine, one after another, then hand over the slot."""
    url = settings.resolved_database_url
    try:
        with session_scope(url) as session:
            spec = machines.get(session=session, machine_id=machine_id)
    except ContractError as exc:  # machine removed after the job was made
        _fail_all(settings, job_id, machine_id, exc)
        return
    holder = leases.acquire(url, machine_id=machine_id, max_concurrent=spec.max_concurrent,
                            group=f"job:{job_id}", ttl_s=settings.lease_ttl_s)
    if holder is None:
        service.mark_waiting(url=url, job_id=job_id, machine_id=machine_id)
        return
    retry_in: float | None = None
    try:
        with leases.Heartbeat(url, holder=holder, ttl_s=settings.lease_ttl_s,
                              on_renew=lambda: service.extend_running(
                                  url=url, job_id=job_id, machine_id=machine_id,
                                  lease_s=settings.lease_ttl_s)):
            retry_in = _run_targets(settings, spec, job_id)
    finally:
        leases.release(url, holder=holder)
        _hand_over(settings, machine_id, job_id, retry_in)


def _run_targets(settings: Settings, spec: machines.MachineSpec, job_id: str) -> float | None:
    url = settings.resolved_database_url
    files: MachineFiles | None = None
    try:
        while work := service.claim_next(url=url, job_id=job_id, machine_id=spec.id,
                                         worker=WORKER_NAME, lease_s=settings.lease_ttl_s):
            try:
                if files is None:
                    files = machines.open_files(spec, data_dir=settings.data_dir)
                outcome = execute(settings, files, work)
            except ContractError as exc:
                outcome = Outcome(error=exc)
            except Exception as exc:  # a bug must not leave the target running forever
                log.exception("target %s of job %s failed unexpectedly", work.target_id, job_id)
                outcome = Outcome(error=ContractError(ErrorCode.INTERNAL_ERROR,
                                                      type(exc).__name__))
            retry_in = service.finish(settings=settings, work=work, error=outcome.error,
                                      state=outcome.state, status_msg=outcome.status_msg,
                                      replaced_payload_id=outcome.replaced_payload_id)
            if retry_in is not None:
                return retry_in  # later targets on this machine keep their order behind it
    finally:
        if files is not None:
            files.close()
    return None


def _hand_over(settings: Settings, machine_id: str, job_id: str, retry_in: float | None) -> None:
    from jobs import queue

    if retry_in is not None:
        queue.enqueue_machine(settings, job_id, machine_id, countdown_s=retry_in)
    waiting = service.next_waiting_group(url=settings.resolved_database_url,
                                         machine_id=machine_id)
    if waiting:
        queue.enqueue_machine(settings, waiting, machine_id)


def _fail_all(settings: Settings, job_id: str, machine_id: str, error: ContractError) -> None:
    url = settings.resolved_database_url
    while work := service.claim_next(url=url, job_id=job_id, machine_id=machine_id,
                                     worker=WORKER_NAME, lease_s=settings.lease_ttl_s):
        service.finish(settings=settings, work=work, error=error)


class Outcome:
    """What one attempt came to."""

    def __init__(self, *, error: ContractError | None = None,
                 state: TargetState = TargetState.SUCCEEDED, status_msg: str | None = None,
                 replaced_payload_id: str | None = None) -> None:
        self.error, self.state, self.status_msg = error, state, status_msg
        self.replaced_payload_id = replaced_payload_id


def execute(settings: Settings, files: MachineFiles, work: service.Work) -> Outcome:
    """One attempt of one target."""
    p = work.params
    if work.kind is JobKind.DELETE:
        ref = files.ref(p.get("fileName"), p.get("dirAtCNC"), p.get("subDir"))
        try:
            files.delete(ref, force=work.options.force)
        except ContractError as exc:
            if exc.code is ErrorCode.PATH_NOT_FOUND and work.previous_interrupted:
                return Outcome(status_msg="already deleted by the interrupted attempt")
            raise
        return Outcome()
    assert work.payload_id is not None
    data = PAYLOADS.get(settings.resolved_database_url, work.payload_id)
    ref = files.send_ref(p.get("fileName"), p.get("dirAtCNC"), p.get("subDir"),
                         data[:FANUC_HEAD_BYTES])
    return _send(settings, files, work, ref, data)


def _send(settings: Settings, files: MachineFiles, work: service.Work, ref: FileRef,
          data: bytes) -> Outcome:
    replaced: str | None = None
    try:
        _write(settings, files, work, ref, data)
    except ContractError as exc:
        if exc.code is not ErrorCode.PATH_EXISTS:
            raise
        existing = b"".join(files.open(ref))
        if existing == data:
            if work.options.skip_identical:
                return Outcome(state=TargetState.SKIPPED, status_msg="identical file already there")
            if work.attempt > 1:  # our own earlier attempt got the file there
                return Outcome(status_msg="file already there from an earlier attempt")
        if not work.options.replace:
            raise
        if not work.options.force:
            files.refuse_if_running(ref)
        with session_scope(settings.resolved_database_url) as session:
            replaced = service.store_payload(session=session, data=existing)
        files.delete(ref, force=True)
        _write(settings, files, work, ref, data)
    if work.options.verify:
        back = b"".join(files.open(ref))
        if hashlib.sha256(back).digest() != hashlib.sha256(data).digest():
            raise ContractError(ErrorCode.VERIFY_MISMATCH, f"{len(back)} bytes read back")
    return Outcome(replaced_payload_id=replaced,
                   status_msg="replaced; the old file is kept with the job" if replaced else None)


def _write(settings: Settings, files: MachineFiles, work: service.Work, ref: FileRef,
           data: bytes) -> None:
    url = settings.resolved_database_url
    last = [0.0]

    def progress(done: int, _total: int | None) -> None:
        now = time.monotonic()
        if now - last[0] >= PROGRESS_EVERY_S:
            last[0] = now
            service.report_bytes(url=url, target_id=work.target_id, done=done, total=len(data))

    files.send(ref, io.BytesIO(data), progress=progress if len(data) > 1 << 20 else None)
