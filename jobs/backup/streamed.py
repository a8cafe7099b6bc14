"""What backing up a machine's files takes: checking a target, and fetching its files.

2.6.13 backupFiles checks every target (machine, folder rules, file or folder present)
before the first byte is sent, so those errors come back as the contract's JSON; then the
workers fetch them (jobs.backup.download). A backup job's runner fetches its targets with
`fetch` into work files of deflated members (jobs.backup.store).
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, BinaryIO

from pydantic import BaseModel, ConfigDict, ValidationError
from sqlalchemy.orm import Session
from zlib_ng import zlib_ng

from jobs import service
from jobs.backup import archive_names, deflate
from jobs.backup_models import MachineBackupStatus
from jobs.errors import ContractError, ErrorCode, unknown_machine, validation_summary
from jobs.fleet import door, registry
from jobs.fleet.listing import LeftOut
from jobs.fleet.paths import Place, Root
from jobs.fleet.rules import FileRef, MachineFiles
from jobs.run import green
from jobs.run.slot import free_slots, machine_slot
from jobs.settings import Settings
from worker.transports.base import CHUNK_BYTES

CHECK_THREADS = 16  # machines checked at once


class BackupTarget(BaseModel):
    """One target of the request body; the contract's `DirAtCNC`/`SubDir` spellings too."""

    model_config = ConfigDict(extra="ignore")

    machineID: str
    fileName: str | None = None
    dirAtCNC: str | None = None
    subDir: str | None = None
    includeSubDir: bool = True

    @classmethod
    def parse(cls, raw: Any, position: int) -> BackupTarget:
        """A target from the body, or the contract's error naming it."""
        if isinstance(raw, dict):
            raw = service.target_fields(raw)
        try:
            return cls.model_validate(raw)
        except ValidationError as exc:  # name the field that is wrong, not always machineID
            found = validation_summary(exc.errors(), whole="target")
            raise ContractError(ErrorCode.BAD_PARAMETER,
                                f"target {position + 1}: {found}") from None


@dataclass
class Checked:
    """A target that passed the checks: where it is on its machine."""

    target: BackupTarget
    place: Place
    ref: FileRef | None  # the file, or None for the whole folder


@dataclass
class MachinePlan:
    """One machine's share of the backup, in request order."""

    spec: registry.MachineSpec
    targets: list[Checked] = field(default_factory=list)


@dataclass(frozen=True)
class Fetched:
    """A file fetched and deflated into its machine's spool, with what the manifest records
    of it."""

    archive_path: str  # inside the machine folder
    machine_path: str  # as the machine writes it
    size: int  # of the plain bytes
    mtime: float | None
    sha256: str  # of the plain bytes
    crc32: int  # of the plain bytes
    compressed_size: int  # of its raw deflate in the spool
    offset: int  # where its bytes start in the spool file


def left_out_entry(left_out: LeftOut) -> dict[str, Any]:
    """What the manifest and the backup's record say of a file or folder left out."""
    return {"path": left_out.path, "isDir": left_out.is_dir, "reason": left_out.reason}


def add_left_out(machine: dict[str, Any], left_out: list[dict[str, Any]]) -> None:
    """Add what a target left out to its machine's manifest entry, which is then partial."""
    known = {x["path"] for x in machine["leftOut"]}
    machine["leftOut"].extend(x for x in left_out if x["path"] not in known)
    if machine["leftOut"] and machine["status"] is MachineBackupStatus.OK:
        machine.update(status=MachineBackupStatus.PARTIAL, errorMsg=LEFT_OUT_MSG)


LEFT_OUT_MSG = "some files or folders could not be backed up; leftOut lists them"


Probed = tuple[list[Checked], tuple[int, ContractError] | None]
"""A machine's targets that passed, in order, and the position and error of the one that
failed (the last it probed), if any."""


def check(*, session: Session, settings: Settings, raw_targets: list[Any]) -> list[MachinePlan]:
    """Check every target; the first failing one, in request order, raises its error,
    naming it.

    The machines are probed at once (on up to CHECK_THREADS threads), each machine's
    targets one after another in one of its slots (those free taken together), so that no
    machine gets more operations at once than it allows, whoever else asks. Probed in
    turn, a request for many machines waited as many round trips before its answer began.
    """
    targets: list[BackupTarget] = []
    failed: tuple[int, ContractError] | None = None
    for position, raw in enumerate(raw_targets):
        try:
            targets.append(BackupTarget.parse(raw, position))
        except ContractError as exc:
            failed = (position, exc)  # no target after it can fail first
            break
    specs = registry.of_ids(session=session, machine_ids={t.machineID for t in targets})
    by_machine: dict[str, list[tuple[int, BackupTarget]]] = {}
    for position, target in enumerate(targets):
        if target.machineID not in specs:
            failed = (position, unknown_machine(target.machineID))
            break
        by_machine.setdefault(target.machineID, []).append((position, target))

    def probe(machine: tuple[str, list[tuple[int, BackupTarget]]]) -> Probed:
        machine_id, its_targets = machine
        return _probe(settings, specs[machine_id], its_targets, slot_held=machine_id in held)

    with free_slots(settings, [specs[machine_id] for machine_id in by_machine]) as held:
        if len(by_machine) > 1:
            with ThreadPoolExecutor(min(CHECK_THREADS, len(by_machine)),
                                    thread_name_prefix="backup-check") as pool:
                each = list(pool.map(probe, by_machine.items()))  # in the machines' order
        else:  # one machine needs no threads
            each = [probe(machine) for machine in by_machine.items()]
    failures = [failure for _, failure in each if failure is not None]
    if failed is not None:
        failures.append(failed)
    if failures:
        raise min(failures, key=lambda failure: failure[0])[1]
    return [MachinePlan(specs[machine_id], checked)
            for machine_id, (checked, _) in zip(by_machine, each, strict=True)]


def _probe(settings: Settings, spec: registry.MachineSpec,
           targets: list[tuple[int, BackupTarget]], *, slot_held: bool) -> Probed:
    """One machine's targets (with their positions) probed in order, up to the first that
    fails, whose error names it; in one of the machine's slots (waiting for one unless
    `slot_held`)."""
    checked: list[Checked] = []
    try:
        slot = contextlib.nullcontext() if slot_held else machine_slot(settings, spec,
                                                                      reading=True)
        with slot, door.open_files(spec, data_dir=settings.data_dir) as files:
            for _, target in targets:
                checked.append(check_one(files, target))
    except ContractError as exc:  # from the target being probed (or from opening: the first)
        position, target = targets[min(len(checked), len(targets) - 1)]
        where = target.fileName or target.dirAtCNC or target.subDir or "root"
        return checked, (position, ContractError(
            exc.code, f"{exc.status_msg or exc.code.name} ({target.machineID}: {where})"))
    return checked, None


def check_one(files: MachineFiles, target: BackupTarget, *, probe: bool = True) -> Checked:
    """Where the target is; its error (158, unsupported...) when it cannot be backed up.

    With `probe` off the machine is not asked: a fetch that follows finds a missing file
    or folder itself (with the same 158), which spares one operation per target.
    """
    place = files.paths.resolve(target.dirAtCNC, target.subDir)
    ref = files.ref(target.fileName, target.dirAtCNC, target.subDir) if target.fileName else None
    if probe and ref is not None:
        files.stat(ref)
    elif probe:
        files.list_program_dir(target.dirAtCNC, target.subDir)  # 158 when the folder is missing
    return Checked(target, place, ref)


def read_slice(spool: BinaryIO, offset: int, length: int) -> Iterator[bytes]:
    """`length` bytes of the spool from `offset` (read when the ZIP writer gets to them)."""
    spool.seek(offset)
    while length > 0:
        chunk = spool.read(min(length, CHUNK_BYTES))
        if not chunk:
            raise OSError(f"{spool.name} ends {length} bytes early")
        length -= len(chunk)
        yield chunk


def _archive_path(default_root: Root, ref: FileRef) -> str:
    """Where a file goes in its machine's folder: below the default root as it is there,
    however it was reached (`TNC:\\` walked down to `nc_prog\\PLATE.h` is `PLATE.h`, as
    `TNC:\\nc_prog` gives it, not a second copy under `@TNC/nc_prog`); below another root
    under `@<root>`."""
    place = ref.place
    if place.root == default_root:
        return archive_names.file_path(None, place.parts, ref.name)
    below = f"{default_root.storage}/"
    if default_root.storage and f"{place.storage}/".startswith(below):
        return archive_names.file_path(
            None, tuple(p for p in place.storage[len(below):].split("/") if p), ref.name)
    return archive_names.file_path(place.root.storage, place.parts, ref.name)


def fetch(files: MachineFiles, checked: Checked, spool: Path,
          fetched: dict[str, Fetched], *, level: int) -> None:
    """Deflate every file a checked target names into the file `spool`, once per archive path.

    The raw deflate of every file (a ZIP member's bytes) is appended to the spool file,
    and each record holds its offset, CRC-32 and both sizes, so that the ZIP
    writer only copies bytes. A file read in one chunk (most programs) deflates on a core
    while the next ones are read: a machine's reads wait on the machine, its deflates on
    the cores, and the two no longer take turns.
    """
    default_root = files.paths.default
    with open(spool, "ab") as members:
        spooled = _InOrder(members, fetched)
        for ref, mtime in _files_of(files, checked):
            archive = _archive_path(default_root, ref)
            if archive in spooled:
                continue  # named by two targets: once in the archive
            chunks = _marking_last(files.open(ref))
            first, last = next(chunks)
            if last:
                spooled.later(archive, files.display_path(ref), mtime, first,
                              green.start_on_a_core(deflate.whole, first, level))
                continue
            spooled.drain()  # a large file streams through its deflater in order
            rest = (chunk for chunk, _ in chunks)
            size, sha256, crc, packed = _deflate(itertools.chain([first], rest), members, level)
            spooled.record(Fetched(archive, files.display_path(ref), size,
                                   mtime, sha256, crc32=crc, compressed_size=packed,
                                   offset=spooled.offset))
        spooled.drain()


MEMBERS = "members.deflate"  # in a machine's spool folder: its deflated files, one after another
IN_FLIGHT = 4  # a machine's files being deflated while the next is read


class _InOrder:
    """Deflated files appended to the spool in the order they were read, up to IN_FLIGHT
    of them still deflating."""

    def __init__(self, members: BinaryIO, fetched: dict[str, Fetched]) -> None:
        self.members, self.fetched = members, fetched
        self.offset = members.tell()
        self._waiting: deque[tuple[Fetched, Callable[[], bytes]]] = deque()
        self._names: set[str] = set()

    def __contains__(self, archive: str) -> bool:
        return archive in self.fetched or archive in self._names

    def later(self, archive: str, machine_path: str, mtime: float | None, data: bytes,
              packed: Callable[[], bytes]) -> None:
        """A file read whole, `packed` its deflate under way; its hashes are made here."""
        # The hashes, a few dozen microseconds, cost less here than a hand-over (_deflate).
        record = Fetched(archive, machine_path, len(data), mtime,
                         hashlib.sha256(data).hexdigest(), crc32=zlib_ng.crc32(data),
                         compressed_size=0, offset=0)
        self._waiting.append((record, packed))
        self._names.add(archive)
        while len(self._waiting) > IN_FLIGHT:
            self._write_oldest()

    def drain(self) -> None:
        while self._waiting:
            self._write_oldest()

    def record(self, done: Fetched) -> None:
        """A file already written at `offset`, `compressed_size` long."""
        self.fetched[done.archive_path] = done
        self.offset += done.compressed_size

    def _write_oldest(self) -> None:
        pending, packed = self._waiting.popleft()
        written = self.members.write(packed())
        self._names.discard(pending.archive_path)
        self.record(replace(pending, compressed_size=written, offset=self.offset))


def _deflate(chunks: Iterable[bytes], out: BinaryIO, level: int) -> tuple[int, str, int, int]:
    """Raw deflate of the chunks into `out`: plain size, SHA-256, CRC-32, deflated size.

    Only the deflate goes to a core thread, in one call per chunk (a file of one chunk in
    one call of `compress`). Every call that drops the interpreter lock has to take it
    back, which on a busy worker waits for the loop's thread to let go of it; the hashes,
    a few dozen microseconds a chunk, cost less where they are. (In-process, 50 green
    machines with 0.6 ms of other Python per file: 1.24-1.32 s against 1.34-1.45 s with
    the hashes in the core threads; in bench/backup.py the difference is inside the host's
    noise, docs/performance.md.)
    """
    digest, size, crc, written = hashlib.sha256(), 0, 0, 0
    deflater: deflate.Deflater | None = None
    for chunk, last in _marking_last(chunks):
        digest.update(chunk)
        crc = zlib_ng.crc32(chunk, crc)
        if last and deflater is None:  # the whole file in one chunk
            packed = green.run_on_a_core(deflate.whole, chunk, level)
        else:
            deflater = deflater or deflate.stream(level)
            packed = green.run_on_a_core(_deflate_chunk, deflater, chunk, last)
        size += len(chunk)
        written += out.write(packed)
    return size, digest.hexdigest(), crc, written


def _deflate_chunk(deflater: deflate.Deflater, chunk: bytes, last: bool) -> bytes:
    packed = deflater.compress(chunk)
    return packed + deflater.flush() if last else packed


def _marking_last(chunks: Iterable[bytes]) -> Iterator[tuple[bytes, bool]]:
    """Each chunk with whether it is the last; an empty file is one empty last chunk."""
    rest = iter(chunks)
    held = next(rest, b"")
    for chunk in rest:
        yield held, False
        held = chunk
    yield held, True


def _files_of(files: MachineFiles, checked: Checked) -> Iterator[tuple[FileRef, float | None]]:
    if checked.ref is not None:
        yield checked.ref, files.stat(checked.ref).mtime
        return
    start = checked.place
    for found in files.walk(start, recursive=checked.target.includeSubDir):
        yield FileRef(Place(start.root, start.parts + found.parts), found.entry.name), \
            found.entry.mtime
