"""What a received text would trigger, row by row (`dncq requests test MACHINE FILE`)."""

from __future__ import annotations

from jobs.fleet.request_settings import RequestSettings, resolve
from jobs.requests.explain import explain

SEED = b"O8888\nN0010 (DIR=/VIPROS)\nN0020 (PRG=0010)\n%\n"


def test_the_seeds_example_explains_each_command_with_its_resolved_file():
    assert explain(SEED, resolve("Fanuc 0i-F", None)) == [
        {"line": 2, "where": "body", "command": "DIR", "body": "/VIPROS", "action": "set_path",
         "folder": "VIPROS", "file": None, "result": "folder for what follows: VIPROS"},
        {"line": 3, "where": "body", "command": "PRG", "body": "0010", "action": "send",
         "folder": "VIPROS", "file": "0010", "result": "send VIPROS/0010"},
    ]


def test_a_refused_request_says_which_command_and_why():
    rows = explain(b"O8888\n(DIR=../..)\n(PRG=1)\n%", RequestSettings())

    assert [row["result"] for row in rows] == [
        "refused: folder '../..' leaves the sources ('..')",
        "not run: the request is refused",
        "the request is refused: DIR=../.. (line 2): folder '../..' leaves the sources ('..')",
    ]


def test_an_unknown_command_is_shown_without_action():
    rows = explain(b"O8888\n(FETCH=1)\n(PRG=1)\n%", RequestSettings())

    assert (rows[0]["action"], rows[0]["result"]) == (None, "unknown command: not run")


def test_a_part_program_is_explained_as_received_into_the_receive_folder():
    assert explain(b"%\nO0010\nG0 X0\n%\n", RequestSettings())[-1]["result"] == (
        "not a request: received and kept as RECEIVED/0010")


def test_garbage_is_explained_as_refused():
    assert explain(b"\x00\x01\x02binary", RequestSettings())[-1]["result"].startswith(
        "refused: control character 0x01")
