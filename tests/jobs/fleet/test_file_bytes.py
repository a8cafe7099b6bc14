"""A file's bytes: two streams compared."""

from __future__ import annotations

import pytest

from jobs.fleet.file_bytes import same_bytes


@pytest.mark.parametrize(("first", "second"), [
    ([b"abc", b"", b"def"], [b"abcdef"]),
    ([b"a"] * 5, [b"aa", b"aaa"]),
    ([], [b""]),
])
def test_same_bytes_cut_differently_are_the_same(first, second):
    assert same_bytes(first, second) and same_bytes(second, first)


@pytest.mark.parametrize(("first", "second"), [
    ([b"abc"], [b"abcd"]),  # one is longer
    ([b"ab", b"x"], [b"a", b"bc"]),  # the last byte differs
    ([b""], [b"\0"]),
])
def test_same_bytes_finds_any_difference(first, second):
    assert not same_bytes(first, second) and not same_bytes(second, first)


def test_same_bytes_stops_reading_at_the_first_difference():
    read = []

    def endless():
        while True:
            read.append(1)
            yield b"x" * 1024

    assert not same_bytes(endless(), [b"x" * 1500, b"y"])
    assert len(read) == 2
