"""ContractError: the message it carries can always be stored and sent."""

from __future__ import annotations

from jobs.errors import ContractError, ErrorCode


def test_status_message_with_a_lone_surrogate_is_kept_escaped_as_utf8_text():
    # A transport names the path it was given; one that is not text must not make the
    # error unstorable (the result of its target would be lost).
    error = ContractError(ErrorCode.PATH_NOT_FOUND, "\ud800/P")

    assert error.status_msg == "\\ud800/P"
    assert error.body()["statusMsg"].encode("utf-8") == b"\\ud800/P"
