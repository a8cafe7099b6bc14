"""The blob store: content kept once by SHA-256, 0600, streamed, never half written."""

from __future__ import annotations

import hashlib
import os
import stat
import time

import pytest

from jobs.errors import ContractError, ErrorCode
from jobs.library import blobs


def _files(settings) -> list:
    return [p for p in blobs.blob_dir(settings).rglob("*") if p.is_file()]


def test_a_blob_is_named_by_its_sha256_and_readable_only_by_its_owner(settings) -> None:
    stored = blobs.put(settings, iter([b"G0 X0\n", b"M30\n"]))

    assert stored == blobs.BlobInfo(hashlib.sha256(b"G0 X0\nM30\n").hexdigest(), 10)
    path = blobs.path(settings, stored.sha256)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert b"".join(blobs.read(settings, stored.sha256, chunk_bytes=3)) == b"G0 X0\nM30\n"


def test_the_same_content_put_twice_is_one_file(settings) -> None:
    first = blobs.put(settings, iter([b"abc"]))
    second = blobs.put(settings, iter([b"a", b"bc"]))

    assert first == second
    assert [p.name for p in _files(settings)] == [first.sha256]


def test_a_broken_upload_leaves_no_blob(settings) -> None:
    def broken():
        yield b"G0 X0\n"
        raise ConnectionError("client went away")

    with pytest.raises(ConnectionError):
        blobs.put(settings, broken())

    assert _files(settings) == []


def test_unused_content_goes_unless_stored_again_in_the_grace_even_as_it_is_removed(
        settings, monkeypatch: pytest.MonkeyPatch) -> None:
    aged = time.time() - blobs.REUSE_GRACE_S - 60
    idle, reused = (blobs.put(settings, [data]) for data in (b"G0 X1\n", b"G0 X2\n"))
    for stored in (idle, reused):
        os.utime(blobs.path(settings, stored.sha256), (aged, aged))
    replace = os.replace

    def stored_again_first(source, target) -> None:
        # an upload of the same bytes reuses it between the removal's look and its move
        monkeypatch.setattr(os, "replace", replace)
        blobs.put(settings, [b"G0 X2\n"])
        replace(source, target)

    assert blobs.remove_unused(blobs.path(settings, idle.sha256)) is True
    monkeypatch.setattr(os, "replace", stored_again_first)
    assert blobs.remove_unused(blobs.path(settings, reused.sha256)) is False

    assert not blobs.exists(settings, idle.sha256)
    assert blobs.read_all(settings, reused.sha256) == b"G0 X2\n"
    assert sorted(str(p.relative_to(blobs.blob_dir(settings))) for p in _files(settings)) == [
        f"{blobs.SPARED}/{reused.sha256}",  # looked at again by a later removal
        f"{reused.sha256[:2]}/{reused.sha256}"]


def test_what_a_killed_upload_left_a_day_ago_goes_at_the_next_upload(settings) -> None:
    blobs.put(settings, [b"G0 X0\n"])
    left, writing = (blobs.blob_dir(settings) / f".incoming-{n}" for n in ("1-a", "2-b"))
    left.write_bytes(b"G0 X1\n")
    writing.write_bytes(b"G0 X2\n")
    day_ago = time.time() - 25 * 3600
    os.utime(left, (day_ago, day_ago))

    blobs.put(settings, [b"M30\n"])

    assert (left.exists(), writing.exists()) == (False, True)


def test_a_missing_or_malformed_content_id_is_refused(settings) -> None:
    with pytest.raises(ContractError) as missing:
        blobs.read_all(settings, "0" * 64)
    with pytest.raises(ContractError) as malformed:
        blobs.path(settings, "../api-key")

    assert missing.value.code is ErrorCode.PATH_NOT_FOUND
    assert malformed.value.code is ErrorCode.BAD_PARAMETER
