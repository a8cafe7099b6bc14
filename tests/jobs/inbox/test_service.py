"""The inbox's operations on a real database (SQLite and PostgreSQL)."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from datetime import UTC, timedelta

import pytest
from sqlalchemy import delete, event, update
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session

from jobs import db
from jobs.errors import ContractError, ErrorCode
from jobs.inbox import service as inbox
from jobs.inbox.models import InboxItem, InboxState
from jobs.library import blobs
from jobs.library import service as library
from jobs.library.models import LibraryAssignment, LibraryProgram, VersionState
from jobs.models import utcnow
from jobs.settings import Settings

APPROVED = b"%\nO0010 (BRACKET)\nG0 X0\nM30\n%\n"
PUNCHED = b"%\nO0010 (BRACKET)\nG0 X0\nG1 X10 F200\nM30\n%\n"


@pytest.fixture
def session(database_url: str) -> Iterator[Session]:
    """A session on a migrated database whose inbox and library start empty."""
    with db.session_scope(database_url) as s:
        s.execute(delete(InboxItem))
        s.execute(delete(LibraryAssignment))
        s.execute(delete(LibraryProgram))
        yield s


def _approved(session: Session, settings: Settings, data: bytes = APPROVED,
              name: str = "O0010") -> library.Added:
    return library.add(session=session, folder="VIPROS", name=name,
                       blob=blobs.put(settings, [data]), approve=True)


def _receive(session: Session, settings: Settings, data: bytes = PUNCHED,
             machine_id: str = "m1", name: str | None = None) -> InboxItem:
    return inbox.receive(session=session, settings=settings, machine_id=machine_id,
                         data=data, name=name, folder="VIPROS")


def _age_blobs(settings: Settings) -> None:
    """Make every blob older than the grace a removal gives one written or reused lately."""
    aged = time.time() - blobs.REUSE_GRACE_S - 60
    for file in blobs.blob_dir(settings).rglob("*"):
        os.utime(file, (aged, aged))


def _failed(session: Session, settings: Settings, machine_id: str, data: bytes) -> InboxItem:
    return inbox.receive_failed(session=session, settings=settings, machine_id=machine_id,
                                data=data, reason="no end mark")


def test_a_received_program_waits_pending_with_its_number_comment_and_bytes(
        session, settings) -> None:
    item = inbox.receive(session=session, settings=settings, machine_id="m1", data=PUNCHED,
                         name=None, folder="VIPROS", job_id="j1")

    assert (item.state, item.name, item.program_number, item.comment, item.folder,
            item.job_id) == (InboxState.PENDING, "O0010", "O0010", "BRACKET", "VIPROS", "j1")
    assert blobs.read_all(settings, item.sha256) == PUNCHED
    assert item.size == len(PUNCHED)


def test_a_program_without_a_number_is_named_for_when_it_came(session, settings) -> None:
    item = _receive(session, settings, b"G0 X0\nM30\n")

    assert item.name.startswith("RECEIVED-")
    assert item.program_number is None


def test_the_name_it_came_with_is_its_name(session, settings) -> None:
    assert _receive(session, settings, name="BRACKET.NC").name == "BRACKET.NC"


def test_the_diff_is_against_the_approved_copy_not_a_newer_pending_one(
        session, settings) -> None:
    _approved(session, settings)
    library.add(session=session, folder="VIPROS", name="O0010",
                blob=blobs.put(settings, [b"O0010\nPENDING\n"]))
    item = _receive(session, settings)

    text = inbox.diff(session=session, settings=settings, item_id=item.id)

    assert text.splitlines()[0] == "--- VIPROS/O0010 v1 (approved)"
    assert "+G1 X10 F200" in text.splitlines()
    assert "PENDING" not in text


def test_the_diffs_header_says_when_the_item_came_in_utc(session, settings) -> None:
    _approved(session, settings)
    item = _receive(session, settings)

    text = inbox.diff(session=session, settings=settings, item_id=item.id)

    assert text.splitlines()[1] == (f"+++ inbox {item.id} from m1 at "
                                    f"{item.received_at.astimezone(UTC):%Y-%m-%d %H:%M} UTC")


def test_without_an_approved_copy_the_diff_says_so(session, settings) -> None:
    item = _receive(session, settings)

    assert inbox.diff(session=session, settings=settings, item_id=item.id) == (
        "no approved copy of VIPROS/O0010 in the library\n")


def test_the_same_bytes_as_the_approved_copy_say_so(session, settings) -> None:
    _approved(session, settings)
    item = _receive(session, settings, APPROVED)

    assert inbox.diff(session=session, settings=settings, item_id=item.id) == (
        "the same bytes as the approved VIPROS/O0010 v1\n")


def test_a_received_program_never_changes_the_approved_one(session, settings) -> None:
    before = _approved(session, settings).version

    _receive(session, settings)
    _receive(session, settings, name="O0010")

    program = library.find(session=session, folder="VIPROS", name="O0010")
    assert [v.number for v in program.versions] == [1]
    assert library.approved(program) is before
    assert library.for_send(session=session, folder="VIPROS", name="O0010",
                            number=None).sha256 == before.sha256


def test_approve_makes_a_new_approved_version_and_keeps_the_previous(
        session, settings) -> None:
    first = _approved(session, settings).version
    item = _receive(session, settings)

    made = inbox.approve(session=session, settings=settings, item_id=item.id,
                         decided_by="anna")

    history = library.history(session=session, folder="VIPROS", name="O0010")
    assert [(v.number, v.state) for v in history] == [
        (2, VersionState.APPROVED), (1, VersionState.APPROVED)]
    assert (made.number, made.sha256, made.created_by) == (2, item.sha256, "anna")
    assert blobs.read_all(settings, first.sha256) == APPROVED
    assert (item.state, item.library_version, item.decided_by) == (
        InboxState.APPROVED, 2, "anna")
    assert made.source == f"inbox {item.id} from m1"


def test_approve_as_another_folder_and_name(session, settings) -> None:
    item = _receive(session, settings)

    made = inbox.approve(session=session, settings=settings, item_id=item.id,
                         folder="LATHE/NEW", name="0010", decided_by="anna", note="kept")

    assert (made.program.path, made.note) == ("LATHE/NEW/0010", "kept")
    assert item.path == "LATHE/NEW/0010"


@pytest.mark.parametrize("how", ["approved", "failed"])
def test_approving_an_approved_item_or_a_failed_reception_is_refused(
        session, settings, how) -> None:
    if how == "approved":
        item = _receive(session, settings)
        inbox.approve(session=session, settings=settings, item_id=item.id, decided_by="a")
    else:
        item = _failed(session, settings, "m1", b"O0010\nG0 X")

    with pytest.raises(inbox.Undecidable, match="approved already|failed reception"):
        inbox.approve(session=session, settings=settings, item_id=item.id, decided_by="b")
    assert len(library.list_programs(session=session)) == (how == "approved")


def test_a_name_the_library_refuses_is_kept_and_approve_takes_another(
        session, settings) -> None:
    item = _receive(session, settings, name="..")

    with pytest.raises(ContractError) as refused:
        inbox.approve(session=session, settings=settings, item_id=item.id, decided_by="a")
    assert refused.value.code is ErrorCode.BAD_PARAMETER
    assert item.state is InboxState.PENDING
    made = inbox.approve(session=session, settings=settings, item_id=item.id,
                         name="O0010", decided_by="a")
    assert made.program.path == "VIPROS/O0010"


def test_a_rejected_item_is_kept_until_pruned_after_the_configured_days(
        session, settings) -> None:
    kept_days = settings.model_copy(update={"inbox_rejected_keep_days": 7})
    item = _receive(session, settings)
    inbox.reject(session=session, item_id=item.id, decided_by="anna", reason="wrong part")
    assert (item.state, item.reason) == (InboxState.REJECTED, "wrong part")

    session.execute(update(InboxItem).values(decided_at=utcnow() - timedelta(days=6)))
    assert inbox.prune(session=session, settings=kept_days) == 0
    assert inbox.get(session=session, item_id=item.id).state is InboxState.REJECTED

    session.execute(update(InboxItem).values(decided_at=utcnow() - timedelta(days=8)))
    assert inbox.prune(session=session, settings=kept_days) == 1
    with pytest.raises(ContractError) as gone:
        inbox.get(session=session, item_id=item.id)
    assert gone.value.code is ErrorCode.PATH_NOT_FOUND


def test_a_prune_keeps_an_item_approved_while_it_ran(session, database_url, settings) -> None:
    item = _receive(session, settings)
    inbox.reject(session=session, item_id=item.id, decided_by="anna")
    session.execute(update(InboxItem).values(decided_at=utcnow() - timedelta(days=400)))
    session.commit()

    def approve_first(conn, cursor, statement: str, *args) -> None:
        # another programmer approves it the moment before the prune deletes
        if statement.startswith("DELETE FROM inbox_items") and not approved:
            approved.append(True)
            with db.session_scope(database_url) as other:
                inbox.approve(session=other, settings=settings, item_id=item.id,
                              decided_by="bob")

    approved: list[bool] = []
    event.listen(Engine, "before_cursor_execute", approve_first)
    try:
        with db.session_scope(database_url) as pruning:
            pruned = inbox.prune(session=pruning, settings=settings)
    finally:
        event.remove(Engine, "before_cursor_execute", approve_first)

    session.expire_all()
    assert (approved, pruned) == ([True], 0)
    assert inbox.get(session=session, item_id=item.id).state is InboxState.APPROVED
    assert blobs.exists(settings, item.sha256)


def test_a_rejected_item_may_still_be_approved_but_not_rejected_again(
        session, settings) -> None:
    item = _receive(session, settings)
    inbox.reject(session=session, item_id=item.id, decided_by="anna")

    with pytest.raises(inbox.Undecidable, match="rejected already"):
        inbox.reject(session=session, item_id=item.id, decided_by="anna")
    assert inbox.approve(session=session, settings=settings, item_id=item.id,
                         decided_by="bob").number == 1


def test_failed_receptions_are_capped_per_machine_and_their_content_goes(
        session, settings) -> None:
    three = settings.model_copy(update={"inbox_failed_keep": 3})
    failed = [_failed(session, three, "m1", f"O{n:04d}\nG0 X".encode()) for n in range(5)]
    other = _failed(session, three, "m2", b"O0099\nG0 X")
    pending = _receive(session, three, machine_id="m1")
    _age_blobs(settings)
    session.commit()

    kept = inbox.list_items(session=session, machine_id="m1", state=InboxState.FAILED)
    assert [i.id for i in kept] == [f.id for f in reversed(failed[2:])]
    assert inbox.get(session=session, item_id=other.id).state is InboxState.FAILED
    assert inbox.get(session=session, item_id=pending.id).state is InboxState.PENDING
    assert not blobs.exists(settings, failed[0].sha256)
    assert blobs.exists(settings, failed[2].sha256)


def test_content_a_removal_spared_as_fresh_goes_at_a_reception_after_the_grace(
        session, settings) -> None:
    one = settings.model_copy(update={"inbox_failed_keep": 1})
    failed = []
    for n in range(3):  # each removes the one before, written a moment ago: spared
        failed.append(_failed(session, one, "m1", f"O{n:04d}\nG0 X".encode()))
        session.commit()
    assert all(blobs.exists(settings, f.sha256) for f in failed)

    _age_blobs(settings)  # an hour later, the next reception
    _receive(session, settings)
    session.commit()

    assert [blobs.exists(settings, f.sha256) for f in failed] == [False, False, True]


def test_content_spared_stays_marked_when_the_prune_that_looked_again_rolls_back(
        session, settings) -> None:
    one = settings.model_copy(update={"inbox_failed_keep": 1})
    failed = [_failed(session, one, "m1", f"O{n:04d}\nG0 X".encode()) for n in range(2)]
    session.commit()  # the first one's content, fresh, spared
    _age_blobs(settings)

    inbox.prune(session=session, settings=settings)
    session.rollback()  # a database lost at the commit
    inbox.prune(session=session, settings=settings)
    session.commit()

    assert not blobs.exists(settings, failed[0].sha256)


def test_a_prune_keeps_content_an_upload_reuses_before_its_version_is_committed(
        session, database_url, settings) -> None:
    item = _receive(session, settings)
    inbox.reject(session=session, item_id=item.id, decided_by="anna")
    session.execute(update(InboxItem).values(decided_at=utcnow() - timedelta(days=400)))
    session.commit()
    _age_blobs(settings)

    with db.session_scope(database_url) as pruning:
        assert inbox.prune(session=pruning, settings=settings) == 1
        uploaded = blobs.put(settings, [PUNCHED])  # the same bytes, their version not added yet
    added = library.add(session=session, folder="VIPROS", name="O0010", blob=uploaded)
    session.commit()

    assert blobs.read_all(settings, added.version.sha256) == PUNCHED


def test_pruned_content_the_library_uses_stays(session, settings) -> None:
    one = settings.model_copy(update={"inbox_failed_keep": 1})
    _approved(session, settings, b"O0010\nG0 X")
    first = _failed(session, one, "m1", b"O0010\nG0 X")
    _failed(session, one, "m1", b"O0011\nG0 X")
    session.commit()

    assert inbox.list_items(session=session, state=InboxState.FAILED)[0].id != first.id
    assert blobs.exists(settings, first.sha256)


def test_content_to_remove_stays_when_the_removal_is_rolled_back(session, settings) -> None:
    one = settings.model_copy(update={"inbox_failed_keep": 1})
    first = _failed(session, one, "m1", b"O0010\nG0 X")
    session.commit()

    _failed(session, one, "m1", b"O0011\nG0 X")
    session.rollback()
    session.commit()

    assert inbox.get(session=session, item_id=first.id).state is InboxState.FAILED
    assert blobs.exists(settings, first.sha256)


def test_items_list_newest_first_by_machine_and_state(session, settings) -> None:
    a = _receive(session, settings, machine_id="m1")
    b = _receive(session, settings, machine_id="m2")
    c = _receive(session, settings, machine_id="m1")
    inbox.reject(session=session, item_id=c.id, decided_by="anna")

    assert [i.id for i in inbox.list_items(session=session)] == [c.id, b.id, a.id]
    assert [i.id for i in inbox.list_items(session=session, machine_id="m1",
                                           state=InboxState.PENDING)] == [a.id]


def test_a_missing_item_is_158(session) -> None:
    with pytest.raises(ContractError) as missing:
        inbox.get(session=session, item_id=999999)

    assert missing.value.code is ErrorCode.PATH_NOT_FOUND
