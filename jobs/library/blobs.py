"""Content-addressed blobs under the data folder: each content stored once, by its SHA-256.

A blob is `blobs/<first two hex digits>/<hex>`, 0600, written under a temporary name and
renamed into place once whole, so a reader never sees half a blob and a broken upload
leaves none (what a killed process left goes a day later). A blob no row uses is removed
only once nothing wrote or reused it for REUSE_GRACE_S: an upload of the same bytes may be
about to commit its row. One spared for that is remembered (`.spared/<digest>`) and looked
at again by a later removal (`spared`). Library versions, drip-feed programs (and
later incremental backups) refer to blobs by digest; in the distributed mode the data
folder is shared between hosts, as the stored backups are.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import time
import uuid
from collections.abc import AsyncIterator, Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from jobs.errors import ContractError, ErrorCode
from jobs.folders import private_dir, private_opener
from jobs.settings import Settings

READ_BYTES = 256 * 1024
REUSE_GRACE_S = 3600  # a blob written or reused this recently may be about to gain its row
STALE_TEMP_S = 24 * 3600  # a temporary file nobody wrote to for this long: its writer was killed
_SHA256 = re.compile(r"[0-9a-f]{64}")
SPARED = ".spared"  # in the blob folder: one empty file per digest a removal spared


@dataclass(frozen=True)
class BlobInfo:
    """A stored blob: its digest and size."""

    sha256: str  # hex
    size: int  # bytes


def blob_dir(settings: Settings) -> Path:
    """Where blobs live."""
    return settings.data_dir / "blobs"


def path(settings: Settings, sha256: str) -> Path:
    """The blob's file (which may not exist); 20001 for anything but 64 hex digits."""
    if not _SHA256.fullmatch(sha256 or ""):
        raise ContractError(ErrorCode.BAD_PARAMETER,
                            "a content id is the SHA-256 of the content, 64 hex digits")
    return blob_dir(settings) / sha256[:2] / sha256


def exists(settings: Settings, sha256: str) -> bool:
    """Whether the blob is stored."""
    return path(settings, sha256).is_file()


class Intake:
    """A blob arriving in chunks: written to a temporary file and hashed as it comes.

    `keep` renames it under its digest; `discard` removes it. Callers that want more of
    the bytes (a line count) look at each chunk as they `add` it.
    """

    def __init__(self, settings: Settings) -> None:
        self.root = private_dir(blob_dir(settings))
        _remove_stale_temps(self.root)
        self.temp = self.root / f".incoming-{os.getpid()}-{id(self):x}"
        self.file: BinaryIO = open(self.temp, "wb", opener=private_opener)  # noqa: SIM115
        self.digest = hashlib.sha256()
        self.size = 0

    def add(self, chunk: bytes) -> None:
        """Write one chunk."""
        if chunk:
            self.file.write(chunk)
            self.digest.update(chunk)
            self.size += len(chunk)

    def keep(self) -> BlobInfo:
        """Move the file under its digest; content already stored is kept once."""
        self.file.close()
        info = BlobInfo(sha256=self.digest.hexdigest(), size=self.size)
        final = self.root / info.sha256[:2] / info.sha256
        private_dir(final.parent)
        try:
            # stored already: the first copy stays, touched so that a removal spares it
            # until the row that reuses it is committed (`remove_unused`)
            os.utime(final)
        except FileNotFoundError:
            os.replace(self.temp, final)  # a racing writer of the same bytes: harmless
        else:
            self.temp.unlink(missing_ok=True)
        return info

    def discard(self) -> None:
        """Drop what arrived; nothing is left behind."""
        self.file.close()
        self.temp.unlink(missing_ok=True)


def remove_unused(blob: Path, *, grace_s: float = REUSE_GRACE_S) -> bool:
    """Remove the blob file `blob`, which no row uses, unless it was written or reused in the
    last `grace_s` (then it is remembered for `spared`); returns whether it went."""
    aside = blob.parent.parent / f".removing-{uuid.uuid4().hex}"
    try:
        if _idle_s(blob) < grace_s:
            _spare(blob)
            return False
        os.replace(blob, aside)  # from here a keep finds no file and stores its own copy
        if _idle_s(aside) < grace_s:  # reused between the look and the move: it stays
            os.replace(aside, blob)
            _spare(blob)
            return False
        aside.unlink()
    except FileNotFoundError:  # removed by another removal meanwhile
        return False
    return True


def _spare(blob: Path) -> None:
    spared = private_dir(blob.parent.parent / SPARED)
    with open(spared / blob.name, "a", opener=private_opener):  # its time: when it was spared
        pass


def spared(settings: Settings, *, grace_s: float = REUSE_GRACE_S) -> frozenset[str]:
    """The digests a removal spared `grace_s` or more ago: the caller looks again whether a
    row uses each, removes it (`remove_unused`) if none does, and then `forget_spared`s them
    (once its transaction committed: a rollback leaves them to be looked at again). Without
    this a blob spared once, such as a failed reception's that the next one removed, stayed
    for ever."""
    found = set()
    for marker in (blob_dir(settings) / SPARED).glob("*"):
        with contextlib.suppress(FileNotFoundError):  # another removal forgot it meanwhile
            if _SHA256.fullmatch(marker.name) and _idle_s(marker) >= grace_s:
                found.add(marker.name)
    return frozenset(found)


def forget_spared(settings: Settings, digests: Iterable[str]) -> None:
    """Drop the digests' marks of `spared`, looked at again (one spared again is re-marked)."""
    for digest in digests:
        (blob_dir(settings) / SPARED / digest).unlink(missing_ok=True)


def _remove_stale_temps(root: Path) -> None:
    """Remove what a killed upload or removal left in `root` a day or more ago, in one look
    at the folder (an upload's first step)."""
    with os.scandir(root) as entries:
        temps = [Path(e.path) for e in entries
                 if e.name.startswith((".incoming-", ".removing-"))]
    for temp in temps:
        with contextlib.suppress(FileNotFoundError):  # another intake removed it first
            if _idle_s(temp) > STALE_TEMP_S:
                temp.unlink()


def _idle_s(file: Path) -> float:
    return time.time() - file.stat().st_mtime


def put(settings: Settings, chunks: Iterable[bytes]) -> BlobInfo:
    """Store content given as chunks; nothing is left behind if reading them fails."""
    intake = Intake(settings)
    try:
        for chunk in chunks:
            intake.add(chunk)
        return intake.keep()
    except BaseException:
        intake.discard()
        raise


async def put_stream(settings: Settings, chunks: AsyncIterator[bytes], *,
                     check: Callable[[int], None] | None = None) -> BlobInfo:
    """`put` for a request body arriving asynchronously; `check` may refuse its size in
    bytes (by raising) once it has all arrived: nothing is then kept."""
    intake = Intake(settings)
    try:
        async for chunk in chunks:
            intake.add(chunk)
        if check is not None:
            check(intake.size)
        return intake.keep()
    except BaseException:
        intake.discard()
        raise


def read(settings: Settings, sha256: str, *, chunk_bytes: int = READ_BYTES) -> Iterator[bytes]:
    """The blob's bytes in chunks; 158 when it is not stored."""
    with open_blob(settings, sha256) as source:
        while chunk := source.read(chunk_bytes):
            yield chunk


def read_all(settings: Settings, sha256: str) -> bytes:
    """The whole blob in memory: for what needs it whole (a job's payload, a diff)."""
    with open_blob(settings, sha256) as source:
        return source.read()


def open_blob(settings: Settings, sha256: str) -> BinaryIO:
    """The blob opened for reading (buffered); 158 when it is not stored."""
    try:
        return open(path(settings, sha256), "rb", buffering=READ_BYTES)  # noqa: SIM115
    except FileNotFoundError:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"no stored content {sha256}") from None
