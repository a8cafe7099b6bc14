"""`dncq library ...` and `dncq send --library` against a live API and worker."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import pytest
from typer.testing import Result

from jobs import db
from jobs.api.app import create_app
from jobs.auth import audit
from jobs.cli import common
from jobs.library import service as library
from jobs.library.models import VersionState
from jobs.settings import get_settings
from tests.jobs.cli.runner import dncq
from tests.jobs.helpers import on_machine
from tests.live_server import serving

V1 = "%\nO0010\nG0 X0\nM30\n%\n"
V2 = "%\nO0010\nG0 X0\nG1 X10 F200\nM30\n%\n"


def _file(folder: Path, text: str) -> Path:
    path = folder / "0010"
    path.write_text(text)
    return path


def test_add_approve_history_diff_restore_and_send_from_the_command_line(
        live_with_worker, queue_settings, tmp_path) -> None:
    first = dncq("library", "add", str(_file(tmp_path, V1)), "--folder", "VIPROS",
                 "--note", "first cut", "--approve")
    assert first.exit_code == 0, first.output
    assert "VIPROS/0010 v1 added (approved" in first.output
    second = dncq("library", "add", str(_file(tmp_path, V2)), "--folder", "VIPROS")
    assert "v2 added (pending" in second.output
    assert "no new version" in dncq("library", "add", str(_file(tmp_path, V2)),
                                    "--folder", "VIPROS").output

    listed = dncq("library", "list")
    assert "VIPROS/0010" in listed.output and "pending" in listed.output
    assert "first cut" in dncq("library", "history", "VIPROS/0010").output
    diff = dncq("library", "diff", "VIPROS/0010", "1", "2")
    assert diff.exit_code == 0 and "+G1 X10 F200" in diff.output

    sent = dncq("send", "--library", "VIPROS/0010", "--tag", "lathes", "--wait")
    assert sent.exit_code == 0, sent.output
    assert "library VIPROS/0010 v1" in sent.output
    assert on_machine(queue_settings, "m0", "0010").read_text() == V1

    again = dncq("send", "--library", "VIPROS/0010@2", "--to", "m2", "--name", "P2.NC",
                 "--wait")
    assert again.exit_code == 0, again.output
    assert on_machine(queue_settings, "m2", "P2.NC").read_text() == V2

    assert dncq("library", "reject", "VIPROS/0010", "2").exit_code == 0
    restored = dncq("library", "restore", "VIPROS/0010", "1")
    assert "VIPROS/0010 v3 added" in restored.output
    assert "approved" in dncq("library", "approve", "VIPROS/0010").output
    assert dncq("library", "assign", "VIPROS", "--to", "m0,m1").exit_code == 0
    assert "m1" in dncq("library", "assignments").output
    assert "versions are kept" in dncq("library", "rm", "VIPROS/0010").output
    assert "VIPROS/0010" not in dncq("library", "list").output


def test_a_deleted_program_added_again_with_its_last_bytes_is_said_to_be_back(
        live_with_worker, tmp_path) -> None:
    dncq("library", "add", str(_file(tmp_path, V1)), "--folder", "VIPROS", "--approve")
    dncq("library", "rm", "VIPROS/0010")

    again = dncq("library", "add", str(_file(tmp_path, V1)), "--folder", "VIPROS")

    assert again.exit_code == 0, again.output
    assert "VIPROS/0010: back in the library, the same bytes as v1 (approved)" in again.output
    assert "VIPROS/0010" in dncq("library", "list").output


def test_a_deleted_program_sent_says_it_was_deleted_and_how_to_bring_it_back(
        live_with_worker, tmp_path) -> None:
    dncq("library", "add", str(_file(tmp_path, V1)), "--folder", "VIPROS", "--approve")
    dncq("library", "rm", "VIPROS/0010")

    refused = dncq("send", "--library", "VIPROS/0010", "--to", "m0")
    back = dncq("library", "restore", "VIPROS/0010", "1")

    assert refused.exit_code == 1
    assert refused.output == ("error: 158 Path is not found: VIPROS/0010 was deleted from the "
                              "library; dncq library restore VIPROS/0010 VERSION brings it "
                              "back\n")
    assert back.exit_code == 0, back.output
    assert dncq("send", "--library", "VIPROS/0010", "--to", "m0", "--wait").exit_code == 0


def test_a_bad_name_or_a_missing_program_ends_the_command_with_its_error(
        live_with_worker, tmp_path) -> None:
    bad = dncq("library", "add", str(_file(tmp_path, V1)), "--folder", "../up")
    missing = dncq("library", "show", "VIPROS/NOPE")
    neither = dncq("send", "--to", "m0")

    assert (bad.exit_code, missing.exit_code, neither.exit_code) == (1, 1, 2)
    assert "20001" in bad.output and "158" in missing.output


def test_an_empty_file_added_ends_with_its_error_alone(live_with_worker, tmp_path) -> None:
    # A blank line followed the error: it was printed under the upload's bar.
    empty = tmp_path / "0010"
    empty.write_bytes(b"")

    refused = dncq("library", "add", str(empty), "--folder", "VIPROS")

    assert refused.exit_code == 1
    assert refused.output == ("error: 20001 Bad parameter: VIPROS/0010: an empty program is "
                              "no program; nothing added\n")


@pytest.mark.parametrize(("asked", "meanwhile"), [("reject", VersionState.APPROVED),
                                                  ("approve", VersionState.REJECTED)])
def test_a_version_decided_the_other_way_meanwhile_ends_the_command_saying_by_whom(
        elsewhere, settings, tmp_path, monkeypatch, asked, meanwhile) -> None:
    dncq("library", "add", str(_file(tmp_path, V1)), "--folder", "VIPROS")
    read, version = threading.Event(), library.version
    answered: dict[str, Result] = {}
    command = threading.Thread(
        target=lambda: answered.update(refused=dncq("library", asked, "VIPROS/0010", "1")))

    def read_by_dncq(**kwargs: Any) -> Any:
        found = version(**kwargs)
        read.set()
        return found

    with db.session_scope(settings.resolved_database_url) as session:
        library.decide(session=session, folder="VIPROS", name="0010", number=1,
                       state=meanwhile, decided_by="anna")
        monkeypatch.setattr(library, "version", read_by_dncq)
        command.start()
        assert read.wait(30)  # dncq read it pending, before anna's decision is committed
    command.join(30)

    refused = answered["refused"]
    assert refused.exit_code == 1
    assert refused.output == (f"error: 20409 Already decided: VIPROS/0010 v1 was "
                              f"{meanwhile.value} meanwhile by anna; it was not "
                              f"{'approved' if asked == 'approve' else 'rejected'}\n")
    with db.session_scope(settings.resolved_database_url) as session:
        kept = version(session=session, folder="VIPROS", name="0010", number=1)
        assert (kept.state, kept.decided_by) == (meanwhile, "anna")  # anna's decision stands


def test_a_program_over_the_limit_of_an_upload_is_refused_before_it_is_read_or_sent(
        settings, env, tmp_path, monkeypatch) -> None:
    # A program over the limit was read and sent whole, to be refused once the limit's worth
    # of it had come in (300 MB read for a 1 MB limit); `dncq run FILE` uploads as it does.
    small = settings.model_copy(update={"max_stream_body_bytes": 16})

    def unreadable(*_: object, **__: object) -> None:
        raise AssertionError("the file was read to be sent")

    with serving(create_app(small)) as server:
        monkeypatch.setenv("DNCQ_URL", server.url)
        get_settings.cache_clear()
        monkeypatch.setattr(common, "open", unreadable, raising=False)
        refused = dncq("library", "add", str(_file(tmp_path, V1)), "--folder", "VIPROS")

    assert refused.exit_code == 1
    assert refused.output == ("error: 20013 Request body is too large: request body over 16 "
                              "bytes\n")
    with db.session_scope(small.resolved_database_url) as session:
        assert audit.list_events(session=session) == []  # no upload reached dncq
        assert library.list_programs(session=session) == []
