"""The blob store: content kept once by SHA-256, 0600, streamed, never half written."""

from __future__ import annotations

import hashlib
import stat

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


def test_a_missing_or_malformed_content_id_is_refused(settings) -> None:
    with pytest.raises(ContractError) as missing:
        blobs.read_all(settings, "0" * 64)
    with pytest.raises(ContractError) as malformed:
        blobs.path(settings, "../api-key")

    assert missing.value.code is ErrorCode.PATH_NOT_FOUND
    assert malformed.value.code is ErrorCode.BAD_PARAMETER
