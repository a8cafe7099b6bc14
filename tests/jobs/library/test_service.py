"""The library's operations on a real database (SQLite and PostgreSQL)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from jobs import db
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import registry
from jobs.library import blobs
from jobs.library import service as library
from jobs.library.models import LibraryAssignment, LibraryProgram, VersionState
from jobs.settings import Settings

V1 = b"%\nO0010\nG0 X0\nM30\n%\n"
V2 = b"%\nO0010\nG0 X0\nG1 X10 F200\nM30\n%\n"


@pytest.fixture
def session(database_url: str) -> Iterator[Session]:
    """A session on a migrated database whose library starts empty."""
    with db.session_scope(database_url) as s:
        s.execute(delete(LibraryAssignment))
        s.execute(delete(LibraryProgram))
        yield s


def _add(session: Session, settings: Settings, data: bytes, name: str = "0010",
         folder: str = "VIPROS", **kwargs) -> library.Added:
    return library.add(session=session, folder=folder, name=name,
                       blob=blobs.put(settings, iter([data])), **kwargs)


def _machines(session: Session, settings: Settings, *machine_ids: str) -> None:
    for machine_id in machine_ids:
        registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(
            {"id": machine_id, "name": machine_id, "model": "Mock"}), data_dir=settings.data_dir)


def test_versions_are_numbered_and_the_same_bytes_add_none(session, settings) -> None:
    first = _add(session, settings, V1, note="first cut", created_by="anna")
    second = _add(session, settings, V2, note="finish pass")
    again = _add(session, settings, V2)

    assert (first.version.number, second.version.number) == (1, 2)
    assert (again.created, again.version.number) == (False, 2)
    assert [(v.number, v.note, v.state) for v in library.history(
        session=session, folder="VIPROS", name="0010")] == [
        (2, "finish pass", VersionState.PENDING), (1, "first cut", VersionState.PENDING)]
    assert first.version.created_by == "anna"


def test_two_programs_of_the_same_bytes_share_one_blob(session, settings) -> None:
    a = _add(session, settings, V1, name="0010")
    b = _add(session, settings, V1, name="0011", folder="VIPROS/OLD")

    assert a.version.sha256 == b.version.sha256
    assert len([p for p in blobs.blob_dir(settings).rglob("*") if p.is_file()]) == 1


def test_the_diff_between_two_versions_is_a_unified_diff(session, settings) -> None:
    _add(session, settings, V1)
    _add(session, settings, V2)

    text = library.diff(session=session, settings=settings, folder="VIPROS", name="0010",
                        old=1, new=2)

    assert text.splitlines()[:2] == ["--- VIPROS/0010 v1", "+++ VIPROS/0010 v2"]
    assert "+G1 X10 F200" in text.splitlines()


def test_a_restore_is_a_new_version_with_the_old_bytes(session, settings) -> None:
    one = _add(session, settings, V1).version
    _add(session, settings, V2)

    restored = library.restore(session=session, folder="VIPROS", name="0010", number=1)

    assert (restored.version.number, restored.version.sha256) == (3, one.sha256)
    assert (restored.version.note, restored.version.source) == ("restore of v1", "restore of v1")


def test_a_deleted_program_keeps_its_history_and_can_be_added_again(session, settings) -> None:
    _add(session, settings, V1)
    library.delete(session=session, folder="VIPROS", name="0010")

    assert library.list_programs(session=session) == []
    assert [v.number for v in library.history(session=session, folder="VIPROS",
                                              name="0010")] == [1]
    with pytest.raises(ContractError) as gone:
        library.find(session=session, folder="VIPROS", name="0010")
    assert gone.value.code is ErrorCode.PATH_NOT_FOUND

    back = _add(session, settings, V2)
    assert (back.version.number, back.version.program.deleted) == (2, False)
    assert back.restored  # the upload's answer says it is back


def test_the_current_approved_version_is_the_highest_approved_one(session, settings) -> None:
    _add(session, settings, V1, approve=True, created_by="anna")
    _add(session, settings, V2)
    program = library.find(session=session, folder="VIPROS", name="0010")
    assert library.for_send(session=session, folder="VIPROS", name="0010",
                            number=None).number == 1

    library.decide(session=session, folder="VIPROS", name="0010", number=2,
                   state=VersionState.APPROVED, decided_by="ben")
    assert library.approved(program).number == 2
    assert program.versions[1].decided_by == "ben"

    library.decide(session=session, folder="VIPROS", name="0010", number=2,
                   state=VersionState.REJECTED)
    assert library.approved(program).number == 1
    # a rejected version goes out only when asked for by number
    assert library.for_send(session=session, folder="VIPROS", name="0010",
                            number=2).state is VersionState.REJECTED


def test_a_program_without_an_approved_version_is_not_sent_by_default(session, settings):
    _add(session, settings, V1)

    with pytest.raises(ContractError) as refused:
        library.for_send(session=session, folder="VIPROS", name="0010", number=None)

    assert refused.value.code is ErrorCode.BAD_PARAMETER


def test_a_machine_lists_the_approved_programs_of_its_folders(session, settings) -> None:
    _add(session, settings, V1, approve=True)
    _add(session, settings, V2, name="0011")  # pending: not listed
    _add(session, settings, V2, name="0012", folder="LATHE", approve=True)
    _machines(session, settings, "1010", "1011")
    library.assign(session=session, folder="VIPROS", machine_ids=["1010", "1011"])

    assert [(p.path, v.number) for p, v in library.machine_programs(
        session=session, machine_id="1010")] == [("VIPROS/0010", 1)]
    assert library.machine_programs(session=session, machine_id="2000") == []
    assert library.unassign(session=session, folder="VIPROS", machine_ids=["1011"]) == 1
    assert [a.machine_id for a in library.assignments(session=session)] == ["1010"]


@pytest.mark.parametrize("folder, name", [
    ("../etc", "0010"), ("/abs", "0010"), ("C:/NC", "0010"), ("VIPROS//OLD", "0010"),
    ("VIPROS", "a/b"), ("VIPROS", "bad\x07name"), ("VIPROS", ".."), ("", "0010"),
    ("VIPROS", ""), ("VIPROS", "．．")])
def test_bad_folders_and_names_are_refused(session, settings, folder, name) -> None:
    with pytest.raises(ContractError) as refused:
        _add(session, settings, V1, name=name, folder=folder)

    assert refused.value.code is ErrorCode.BAD_PARAMETER


def test_two_adds_of_one_new_program_at_the_same_moment_both_land(
        settings, postgres_url) -> None:
    """On PostgreSQL (the distributed mode, where API processes write at once), each add in
    its own transaction, both past their reads before either commits: the one whose program
    row or version number the other took reads again and numbers after it."""
    import threading

    with db.session_scope(postgres_url) as s:
        s.execute(delete(LibraryAssignment))
        s.execute(delete(LibraryProgram))
    blobs_of = [blobs.put(settings, iter([data])) for data in (V1, V2)]
    both_read = threading.Barrier(2)
    errors: list[BaseException] = []

    def add(blob: blobs.BlobInfo) -> None:
        try:
            with db.session_scope(postgres_url) as own:
                # hold the transaction open until the other one has started too
                own.execute(select(LibraryProgram.id)).all()
                both_read.wait(timeout=10)
                library.add(session=own, folder="VIPROS", name="0020", blob=blob)
        except BaseException as exc:  # reported below, in the test's thread
            errors.append(exc)

    threads = [threading.Thread(target=add, args=(b,)) for b in blobs_of]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)

    assert errors == []
    with db.session_scope(postgres_url) as s:
        history = library.history(session=s, folder="VIPROS", name="0020")
        assert sorted(v.number for v in history) == [1, 2]
        assert {v.sha256 for v in history} == {b.sha256 for b in blobs_of}


def test_a_decision_read_before_another_committed_is_refused_leaving_the_other_whole(
        postgres_url, settings) -> None:
    """An approver read the version approved; a reviewer then rejected it and committed;
    the approver's decision came last. It is refused, saying so, and the record is the
    reviewer's decision, whole: never rejected "decided by" the approver."""
    with db.session_scope(postgres_url) as s:
        s.execute(delete(LibraryAssignment))
        s.execute(delete(LibraryProgram))
        _add(s, settings, V1, approve=True, created_by="ap1")
    with db.session_scope(postgres_url) as approver:
        seen = library.find(session=approver, folder="VIPROS", name="0010").versions[0]
        assert seen.state is VersionState.APPROVED  # what the approver read
        with db.session_scope(postgres_url) as reviewer:
            library.decide(session=reviewer, folder="VIPROS", name="0010", number=1,
                           state=VersionState.REJECTED, decided_by="rj1")
        with pytest.raises(library.DecidedMeanwhile, match="rejected meanwhile by rj1"):
            library.decide(session=approver, folder="VIPROS", name="0010", number=1,
                           state=VersionState.APPROVED, decided_by="ap2")

    with db.session_scope(postgres_url) as s:
        [kept] = library.history(session=s, folder="VIPROS", name="0010")
        assert (kept.state, kept.decided_by) == (VersionState.REJECTED, "rj1")


def test_assigning_a_folder_to_ids_no_machine_has_is_refused_and_gives_none(
        session, settings) -> None:
    _machines(session, settings, "1010")

    with pytest.raises(ContractError) as refused:
        library.assign(session=session, folder="VIPROS", machine_ids=["1010", "1O10", "x" * 100])

    assert refused.value.code is ErrorCode.MACHINE_NOT_FOUND
    assert "no machine 1O10 (did you mean 1010?)" in refused.value.status_msg
    assert library.assignments(session=session) == []
