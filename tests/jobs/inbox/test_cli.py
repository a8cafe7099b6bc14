"""`dncq inbox ...` against the API on loopback."""

from __future__ import annotations

from jobs import db
from jobs.inbox import service as inbox
from jobs.library import blobs
from jobs.library import service as library
from jobs.settings import Settings
from tests.jobs.cli.runner import dncq

APPROVED = b"%\nO0010 (BRACKET)\nG0 X0\nM30\n%\n"
PUNCHED = b"%\nO0010 (BRACKET)\nG0 X0\nG1 X10 F200\nM30\n%\n"


def _received(settings: Settings, *, approved_first: bool = True) -> int:
    with db.session_scope(settings.resolved_database_url) as session:
        if approved_first:
            library.add(session=session, folder="VIPROS", name="O0010",
                        blob=blobs.put(settings, [APPROVED]), approve=True)
        return inbox.receive(session=session, settings=settings, machine_id="1010",
                             data=PUNCHED, name=None, folder="VIPROS").id


def test_list_shows_the_received_programs_and_filters_by_state(elsewhere, settings) -> None:
    item_id = _received(settings)
    with db.session_scope(settings.resolved_database_url) as session:
        inbox.receive_failed(session=session, settings=settings, machine_id="1011",
                             data=b"O0020\nG0", reason="no end mark")

    listed = dncq("inbox", "list")
    pending = dncq("inbox", "list", "--state", "pending")

    assert listed.exit_code == 0, listed.output
    assert "VIPROS/O0010" in listed.output and "BRACKET" in listed.output
    assert "no end mark" in listed.output
    assert str(item_id) in pending.output and "no end mark" not in pending.output
    assert dncq("inbox", "list", "--state", "lost").exit_code == 2


def test_show_and_diff_against_the_approved_copy(elsewhere, settings) -> None:
    item_id = _received(settings)

    shown = dncq("inbox", "show", str(item_id))
    diff = dncq("inbox", "diff", str(item_id))

    assert shown.exit_code == 0, shown.output
    assert "1010" in shown.output and "approved v1" in shown.output
    assert diff.exit_code == 0, diff.output
    assert "--- VIPROS/O0010 v1 (approved)" in diff.output
    assert "+G1 X10 F200" in diff.output


def test_approve_makes_the_next_version_and_says_the_previous_is_kept(
        elsewhere, settings) -> None:
    item_id = _received(settings)

    approved = dncq("inbox", "approve", str(item_id))
    again = dncq("inbox", "approve", str(item_id))

    assert approved.exit_code == 0, approved.output
    assert f"Inbox item {item_id} approved as VIPROS/O0010 v2; v1 kept." in approved.output
    assert again.exit_code == 1
    assert f"error: 20409 Already decided: inbox item {item_id} is approved already" \
        in again.output
    with db.session_scope(settings.resolved_database_url) as session:
        program = library.find(session=session, folder="VIPROS", name="O0010")
        assert [v.number for v in program.versions] == [1, 2]
        assert library.approved(program).sha256 == blobs.put(settings, [PUNCHED]).sha256


def test_approve_as_another_program(elsewhere, settings) -> None:
    item_id = _received(settings, approved_first=False)

    approved = dncq("inbox", "approve", str(item_id), "--as", "LATHE/0010")

    assert approved.exit_code == 0, approved.output
    assert "approved as LATHE/0010 v1." in approved.output
    assert dncq("inbox", "approve", "1", "--as", "NOSLASH").exit_code == 2


def test_reject_keeps_it_as_rejected_with_its_reason(elsewhere, settings) -> None:
    item_id = _received(settings)

    rejected = dncq("inbox", "reject", str(item_id), "--reason", "wrong part")

    assert rejected.exit_code == 0, rejected.output
    assert "rejected; kept until pruned" in rejected.output
    listed = dncq("inbox", "list", "--state", "rejected").output
    assert "wrong part" in listed


def test_a_missing_item_ends_the_command_with_its_error(elsewhere) -> None:
    missing = dncq("inbox", "show", "424242")

    assert missing.exit_code == 1
    assert "no inbox item 424242" in missing.output
