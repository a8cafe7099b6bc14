"""A machine's files behind its model's rules: every operation of the contract, once.

`MachineFiles` turns the contract's parameters into transport calls: it resolves
folders (jobs.fleet.paths), applies naming and the model's capabilities, refuses what
the model cannot do before touching the machine, and maps transport failures to
the contract's error codes (jobs.fleet.failures). Walk and search are written here, on
the primitives, giving the names of a listing it can (jobs.fleet.listing). A file's
bytes as 2.6.3's body, and two streams compared, are jobs.fleet.file_bytes. What the
machine's control does beyond its files (locks, free space, its link, drip-feed, requests)
is jobs.fleet.control, which `MachineFiles` builds on.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Generator, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, BinaryIO

from jobs.errors import ContractError, ErrorCode
from jobs.fleet.control import MachineControl
from jobs.fleet.failures import mapped
from jobs.fleet.file_bytes import same_bytes
from jobs.fleet.listing import (
    NOT_A_FILE_NAME,
    NOT_A_FOLDER_NAME,
    NOT_TEXT,
    LeftOut,
    WalkedFile,
    as_bytes,
    is_file_name,
    is_folder_name,
    is_text,
    nameable,
)
from jobs.fleet.paths import (
    MachinePaths,
    MissingParameter,
    Place,
    Root,
    bad,
    check_name,
    fanuc_name_from_content,
)
from worker.transports.base import (
    CHUNK_BYTES,
    Entry,
    ProgressFn,
    Transport,
    first_chunk_then,
)
from worker.transports.optional import PartsOfFiles

log = logging.getLogger(__name__)

FANUC_HEAD_BYTES = 4096  # the program name sits in the first lines
MAX_WALK_DEPTH = 32  # deeper than any controller's folders: a server answering in circles


@dataclass(frozen=True)
class FileRef:
    """A file a request names: its folder and its stored name."""

    place: Place
    name: str

    @property
    def storage(self) -> str:
        """Transport path of the file."""
        return self.place.file(self.name)


class MachineFiles(MachineControl):
    """One machine's files, with the rules of the catalogue row that governs it."""

    def __init__(self, transport: Transport, paths: MachinePaths, *, encoding: str) -> None:
        super().__init__(transport, paths.row)
        self.paths = paths
        self.encoding = encoding
        self.left_out: list[LeftOut] = []  # what `walk` found but could not give

    def close(self) -> None:
        """Release the transport."""
        self.transport.close()

    def __enter__(self) -> MachineFiles:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- naming --------------------------------------------------------------

    def ref(self, file_name: str | None, dir_at_cnc: str | None, sub_dir: str | None) -> FileRef:
        """The file a request names by `fileName`, `dirAtCNC` and `subDir`."""
        place = self.paths.resolve(dir_at_cnc, sub_dir)
        return FileRef(place, self.paths.stored_name(file_name))

    def listed_ref(self, file_name: str, dir_at_cnc: str | None, sub_dir: str | None
                   ) -> FileRef:
        """A file by the name this machine's own listing gave it (a restore puts a file back
        under it): `\\` or `:` may be letters of it there, where a request's `fileName`
        must be a plain name; a path or a step (`..`) is still refused."""
        if not is_file_name(file_name):
            raise bad(f"fileName {file_name!r} names no file of a folder")
        return FileRef(self.paths.resolve(dir_at_cnc, sub_dir), file_name)

    def send_ref(
        self, file_name: str | None, dir_at_cnc: str | None, sub_dir: str | None, head: bytes
    ) -> FileRef:
        """Where a send puts its file: Fanuc takes the name from the content, others `fileName`."""
        place = self.paths.resolve(dir_at_cnc, sub_dir)
        if self.row.is_fanuc:
            if file_name:  # ignored, but a path is refused as on every model
                check_name(file_name)
            return FileRef(place, fanuc_name_from_content(head))
        return FileRef(place, self.paths.stored_name(file_name))

    # -- 2.6.1 readProgramList and 2.6.16 searchFile ---------------------------

    def list_program_dir(self, dir_at_cnc: str | None, sub_dir: str | None) -> dict[str, Any]:
        """`{"dirAtCNC", "programs", "subDirs"}` of one folder."""
        return self._listing(self.paths.resolve(dir_at_cnc, sub_dir))

    def _listing(self, place: Place) -> dict[str, Any]:
        with mapped(self._shown(place)):
            entries = nameable(self.transport.list_dir(place.storage))
        return {
            "dirAtCNC": self.paths.display(place),
            "programs": [self.paths.listed_name(e.name) for e in entries if not e.is_dir],
            "subDirs": [e.name for e in entries if e.is_dir] if self._subfolders else [],
        }

    @property
    def _subfolders(self) -> bool:
        return self.row.list_subdirs and self.caps.folders

    def search(self, file_name: str | None, dir_at_cnc: str | None,
               sub_dir: str | None) -> dict[str, Any]:
        """The listing of the first folder, below the requested one, that holds `fileName`."""
        ref = self.ref(file_name, dir_at_cnc, sub_dir)
        for found in self.walk(ref.place):
            if found.entry.name == ref.name:
                return self._listing(Place(ref.place.root, ref.place.parts + found.parts))
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"{file_name} not found")

    # -- walking -------------------------------------------------------------

    def walk(self, start: Place, *, recursive: bool = True) -> Iterator[WalkedFile]:
        """Every file below `start`, a folder's files before its subfolders, sorted by name."""
        recursive = recursive and self._subfolders
        pending: list[tuple[str, ...]] = [()]
        while pending:
            parts = pending.pop()
            place = Place(start.root, start.parts + parts)
            with mapped(self._shown(place)):
                entries = self.transport.list_dir(place.storage)
            subdirs = []
            for entry in sorted(entries, key=lambda e: e.name):
                if not is_text(entry.name):
                    self._leave_out(place, as_bytes(entry.name), entry.is_dir, NOT_TEXT)
                elif entry.is_dir:
                    if is_folder_name(entry.name):  # ".", "" or "a/b" would walk in circles
                        subdirs.append(parts + (entry.name,))
                    elif entry.name not in ("", ".", ".."):  # those are the listing's own
                        self._leave_out(place, entry.name, True, NOT_A_FOLDER_NAME)
                elif is_file_name(entry.name):
                    yield WalkedFile(parts, entry, place.file(entry.name))
                else:  # read, it would be another file or none: the target would fail whole
                    self._leave_out(place, entry.name, False, NOT_A_FILE_NAME)
            if recursive and subdirs and len(parts) >= MAX_WALK_DEPTH:
                raise ContractError(ErrorCode.CONNECTION_FAILED,
                                    f"folders nest deeper than {MAX_WALK_DEPTH} levels")
            if recursive:
                pending.extend(reversed(subdirs))  # depth first, in name order

    def _leave_out(self, place: Place, name: str, is_dir: bool, reason: str) -> None:
        path = self.display_path(FileRef(place, name))
        log.warning("left %s %r out: %s", "the folder" if is_dir else "the file", path, reason)
        self.left_out.append(LeftOut(path, is_dir, reason))

    def read_all(self, dir_at_cnc: str | None, sub_dir: str | None) -> dict[str, Any]:
        """2.6.15: every file below the folder with its folder relative to it."""
        place = self.paths.resolve(dir_at_cnc, sub_dir)
        return {
            "programs": [
                {"dirAtCNC": self.paths.relative_display(f.parts),
                 "fileName": self.paths.listed_name(f.entry.name)}
                for f in self.walk(place)
            ]
        }

    # -- reading ---------------------------------------------------------------

    def stat(self, ref: FileRef) -> Entry:
        """The file's entry; 158 if it is missing or a folder."""
        with mapped(self._shown(ref)):
            entry = self.transport.stat(ref.storage)
        if entry.is_dir:
            raise ContractError(ErrorCode.PATH_NOT_FOUND, f"{ref.name} is a folder")
        return entry

    def open(self, ref: FileRef, *, progress: ProgressFn | None = None
             ) -> Generator[bytes, None, None]:
        """The file's bytes; failures before the first byte are raised here."""
        with mapped(self._shown(ref)):
            chunks = first_chunk_then(self.transport.read(ref.storage, progress=progress))

        def guarded() -> Generator[bytes, None, None]:
            with mapped(self._shown(ref)):
                yield from chunks

        return guarded()

    def read_bytes(self, ref: FileRef, *, max_bytes: int) -> bytes:
        """The whole file, refused when larger than `max_bytes`."""
        entry = self.stat(ref)
        if entry.size is not None and entry.size > max_bytes:
            raise ContractError(
                ErrorCode.FILE_TOO_LARGE,
                f"{entry.size} bytes; use receiveFileStream for files over {max_bytes} bytes",
            )
        data = bytearray()
        with contextlib.closing(self.open(ref)) as chunks:
            for chunk in chunks:  # stops at the limit, whatever size the machine gave
                data += chunk
                if len(data) > max_bytes:
                    raise ContractError(ErrorCode.FILE_TOO_LARGE, "use receiveFileStream")
        return bytes(data)

    def holds(self, ref: FileRef, size: int, chunks: Iterable[bytes]) -> bool:
        """Whether the file holds exactly the `size` bytes of `chunks`: sizes first, then
        chunk by chunk, stopping at the first difference (neither is ever held whole)."""
        entry = self.stat(ref)
        if entry.size is not None and entry.size != size:
            return False
        with contextlib.closing(self.open(ref)) as there:
            return same_bytes(there, chunks)

    # -- 2.6.4 readCurrentProgram ----------------------------------------------

    def current_program(self) -> FileRef | None:
        """The running program, or None when nothing runs."""
        if not self.caps.current_program:
            raise ContractError(ErrorCode.UNSUPPORTED, "this machine cannot tell its program")
        with mapped():
            path = self.transport.current_program()
        if not path:
            return None
        folded = path.replace("\\", "/")
        folder, _, name = folded.rpartition("/")
        place = self.paths.parse(folder) if folder else self.paths.resolve(None, None)
        return FileRef(place, self.paths.stored_name(name))

    def _shown(self, where: FileRef | Place) -> tuple[str, str]:
        """`where` in storage and in the controller's notation, for `mapped`'s messages."""
        if isinstance(where, FileRef):
            return where.storage, self.display_path(where)
        return where.storage, self.paths.display(where)

    def display_path(self, ref: FileRef) -> str:
        """The file's full path in the model's notation."""
        folder = self.paths.display(ref.place)
        if folder and not folder.endswith(("/", "\\")):
            folder += self.row.separator
        return folder + ref.name

    # -- 2.6.5/2.6.6 sending -----------------------------------------------------

    def send(self, ref: FileRef, source: BinaryIO, *, progress: ProgressFn | None = None) -> int:
        """Store `source` as a new file; 142 if the name is taken. Returns bytes written."""

        def chunks() -> Iterator[bytes]:
            while chunk := source.read(CHUNK_BYTES):
                yield chunk

        return self.send_chunks(ref, chunks(), progress=progress)

    def send_chunks(self, ref: FileRef, chunks: Iterable[bytes], *,
                    progress: ProgressFn | None = None) -> int:
        """`send` from chunks; an exception the chunks raise leaves no file behind."""
        with mapped(self._shown(ref)):
            return self.transport.write(ref.storage, chunks, progress=progress)

    def remove_parts_of(self, ref: FileRef) -> None:
        """After `ref` was sent, remove the temporary files earlier writes of it left, where
        the transport can tell them (best effort: the file sent stays sent)."""
        if isinstance(self.transport, PartsOfFiles):
            self.transport.remove_parts_of(ref.storage)

    # -- 2.6.8 deleteFile --------------------------------------------------------

    def delete(self, ref: FileRef, *, force: bool = False) -> None:
        """Delete a file; the running program only with `force`."""
        if not force:
            self.refuse_if_running(ref)
        with mapped(self._shown(ref)):
            self.transport.delete(ref.storage)

    def refuse_if_running(self, ref: FileRef) -> None:
        """Raise 20008 when `ref` is the program the machine is running."""
        if not self.caps.current_program:
            return
        running = self.current_program()
        if running is not None and running.storage.lower() == ref.storage.lower():
            raise ContractError(
                ErrorCode.PROGRAM_RUNNING,
                f"{self.paths.listed_name(ref.name)} is running; "
                "add force=true (--force on the command line) to go ahead",
            )

    # -- 2.6.11/2.6.12 folders ---------------------------------------------------

    def make_dir(self, dir_name: str | None, dir_at_cnc: str | None, sub_dir: str | None) -> None:
        """Create the folder `dirName` in the requested folder."""
        place = self._dir_place(dir_name, dir_at_cnc, sub_dir)
        with mapped(self._shown(place)):
            self.transport.make_dir(place.storage)

    def ensure_dir(self, place: Place) -> None:
        """Create `place` and any missing folder above it (where the model allows)."""
        for depth in range(1, len(place.parts) + 1):
            here = Place(place.root, place.parts[:depth])
            try:
                self.make_dir(here.parts[-1], self.paths.display(
                    Place(place.root, here.parts[:-1])), None)
            except ContractError as exc:
                if exc.code is not ErrorCode.PATH_EXISTS:
                    raise

    def remove_dir(self, dir_name: str | None, dir_at_cnc: str | None,
                   sub_dir: str | None) -> None:
        """Remove the empty folder `dirName` from the requested folder."""
        place = self._dir_place(dir_name, dir_at_cnc, sub_dir)
        with mapped(self._shown(place)):
            self.transport.remove_dir(place.storage)

    def _dir_place(self, dir_name: str | None, dir_at_cnc: str | None,
                   sub_dir: str | None) -> Place:
        if not dir_name:
            raise MissingParameter("dirName")
        check_name(dir_name, what="dirName")
        place = self.paths.resolve(dir_at_cnc, sub_dir)
        allowed = self.row.make_dirs_roots
        if allowed is not None:
            # Below counts too: a machine's configured root may be a folder on the card.
            key = place.root.match_key
            if not any(key == k or key.startswith(k + "/")
                       for k in (Root.of(a).match_key for a in allowed)):
                raise ContractError(
                    ErrorCode.UNSUPPORTED,
                    f"{self.row.name} creates and deletes folders only on {', '.join(allowed)}",
                )
        elif not self.row.make_dirs:
            raise ContractError(ErrorCode.UNSUPPORTED, f"{self.row.name} cannot make folders")
        self._require(self.caps.make_dirs, "make folders")
        return place.child(dir_name)

    # -- 2.6.14 selectProgram ----------------------------------------------------

    def select_program(self, ref: FileRef) -> None:
        """Make `ref` the main program (Brother, listed Fanuc models, Mock)."""
        if not self.row.select_program:
            raise ContractError(ErrorCode.UNSUPPORTED, f"{self.row.name} cannot select programs")
        if self.row.select_is_noop:
            return  # the contract's Mock model: always success, nothing changes
        self._require(self.caps.select_program, "select programs")
        self.stat(ref)
        with mapped():
            self.transport.select_program(self.display_path(ref))


def exists(files: MachineFiles, ref: FileRef) -> bool:
    """Whether the file is there."""
    try:
        files.stat(ref)
    except ContractError as exc:
        if exc.code is ErrorCode.PATH_NOT_FOUND:
            return False
        raise
    return True
