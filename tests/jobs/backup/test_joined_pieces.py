"""The streamed ZIP leaves in pieces of a useful size, every byte in order."""

from __future__ import annotations

from jobs.backup.zipwriter import joined


def test_small_chunks_are_joined_into_pieces_of_at_least_the_size_in_order() -> None:
    chunks = [bytes([n % 251]) * (30 + n % 50) for n in range(500)]  # headers and members

    pieces = list(joined(chunks, 1000))

    assert b"".join(pieces) == b"".join(chunks)
    assert all(len(p) >= 1000 for p in pieces[:-1])
    assert 0 < len(pieces[-1])
    assert len(pieces) < len(chunks) / 10


def test_a_chunk_over_the_size_goes_alone_and_nothing_means_no_piece() -> None:
    assert list(joined([b"x" * 5000, b"y"], 1000)) == [b"x" * 5000, b"y"]
    assert list(joined([], 1000)) == []
