"""ContractError: the message it carries can always be stored and sent."""

from __future__ import annotations

import pytest

from jobs import errors
from jobs.errors import ContractError, ErrorCode


def test_status_message_with_a_lone_surrogate_is_kept_escaped_as_utf8_text():
    # A transport names the path it was given; one that is not text must not make the
    # error unstorable (the result of its target would be lost).
    error = ContractError(ErrorCode.PATH_NOT_FOUND, "\ud800/P")

    assert error.status_msg == "\\ud800/P"
    assert error.body()["statusMsg"].encode("utf-8") == b"\\ud800/P"


@pytest.mark.parametrize(("typed", "known", "hinted"), [
    ("1O01", [str(i) for i in range(1000, 2000)], "1001"),  # not 1901: O is typed for 0
    ("mill-1O01", [f"mill-{i}" for i in range(10_000)], "mill-1001"),
    ("LATHE-I2", ["LATHE-12", "LATHE-22"], "LATHE-12"),
    ("1O10", ["1010", "1016"], "1010"),  # too far for difflib (0.5), but reads the same
    ("1O1O", ["1010", "1016"], "1010"),
    ("101O", ["1010", "1016"], "1010"),  # not 1016
    ("lathe-l", ["LATHE-1", "LATHE-2"], "LATHE-1"),
    ("1x01", ["1001", "1016"], "1001"),  # a character off
    ("m9", ["m0", "m1"], None),  # nothing close enough: no guess
])
def test_a_mistyped_name_is_hinted_at_as_the_one_it_looks_like(
        typed: str, known: list[str], hinted: str | None) -> None:
    assert errors.meant(typed, known) == hinted
