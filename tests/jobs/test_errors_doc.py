"""docs/errors.md lists every error code with its exact message and retry class."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from jobs.errors import MESSAGES, TRANSIENT_CODES, ErrorCode

DOC = Path(__file__).resolve().parents[2] / "docs" / "errors.md"
ROW = re.compile(r"^\|\s*(\d+)\s*\|\s*`([^`]*)`\s*\|(.*)\|\s*(yes|no)\s*\|\s*$")


def documented() -> dict[int, tuple[str, bool]]:
    """code -> (errorMsg, retried) from the table in docs/errors.md."""
    rows = [ROW.match(line) for line in DOC.read_text().splitlines()]
    return {int(m[1]): (m[2], m[4] == "yes") for m in rows if m}


@pytest.mark.parametrize("code", list(ErrorCode), ids=lambda c: f"{c.name}-{int(c)}")
def test_every_error_code_is_documented_with_its_exact_message(code):
    assert documented().get(int(code), ("(missing)", False))[0] == MESSAGES[code]


@pytest.mark.parametrize("code", list(ErrorCode), ids=lambda c: f"{c.name}-{int(c)}")
def test_documented_retry_class_matches_the_transient_codes(code):
    assert documented()[int(code)][1] == (code in TRANSIENT_CODES)


def test_errors_doc_lists_no_code_that_does_not_exist():
    assert set(documented()) - {int(c) for c in ErrorCode} == set()
