"""Programs stored for drip-feed runs: streamed in, kept once by content, read a line at a time."""

from __future__ import annotations

import hashlib

import pytest

from jobs.dnc import programs
from jobs.errors import ContractError, ErrorCode
from jobs.library import blobs

PROGRAM = b"%\r\nO0010\r\nG0 X0 Y0\r\nG1 X10 F200\r\nM30\r\n%"  # no newline after the last %


def test_a_stored_program_is_named_by_its_sha256_and_counts_its_lines(settings) -> None:
    stored = programs.store(settings, iter([PROGRAM[:7], PROGRAM[7:]]))

    assert stored.id == hashlib.sha256(PROGRAM).hexdigest()
    assert (stored.size, stored.lines) == (len(PROGRAM), 6)
    assert programs.info(settings, stored.id) == stored


@pytest.mark.parametrize("cut", [1, 5, 9, 4097, 4100, 4102])
def test_the_longest_line_is_measured_across_chunks_without_its_line_ending(settings, cut):
    data = b"G0 X0\r\n" + b"(" + b"A" * 4098 + b")\r\nM30\r\n"  # line 2: 4,100 bytes
    stored = programs.store(settings, iter([data[:cut], data[cut:]]))

    assert (stored.lines, stored.longest_line, stored.longest_line_at) == (3, 4100, 2)
    assert stored.refusal() == "line 2 is 4,100 bytes long, more than the 4,096 a run " \
                               "sends as one line"


def test_an_empty_program_is_refused_and_an_ordinary_one_is_not(settings) -> None:
    assert programs.store(settings, iter([b""])).refusal() == "the program is empty"
    assert programs.store(settings, iter([PROGRAM])).refusal() is None


def test_a_program_recorded_before_lines_were_measured_is_measured_again(settings) -> None:
    import json

    stored = programs.store(settings, iter([b"G0\n" + b"X" * 5000]))
    record = programs.program_dir(settings) / f"{stored.id}.json"
    record.write_text(json.dumps({"id": stored.id, "size": stored.size, "lines": 2}))

    assert programs.info(settings, stored.id) == stored  # longest: 5000, at line 2


def test_lines_come_back_without_their_endings_from_the_start_line(settings) -> None:
    stored = programs.store(settings, iter([PROGRAM]))

    assert list(programs.lines(settings, stored.id, start_line=3)) == [
        b"G0 X0 Y0", b"G1 X10 F200", b"M30", b"%"]


@pytest.mark.parametrize("ends", [[b"\r\n"] * 6, [b"\n"] * 6, [b"\r"] * 6, [b"\n\r"] * 6,
                                  [b"\r\n", b"\n\r", b"\r", b"\r\n", b"\n", b"\n\r"]],
                         ids=["CR LF", "LF", "CR", "LF CR", "mixed"])
def test_lines_end_at_cr_lf_lf_cr_and_lf_cr_alike_even_across_chunks(settings, ends) -> None:
    lines = [b"%", b"O0010", b"G0 X0 Y0", b"", b"M30", b"%"]
    data = b"".join(line + end for line, end in zip(lines, ends, strict=True))
    cut = len(b"%") + 1  # inside the first line end when it is two bytes
    stored = programs.store(settings, iter([data[:cut], data[cut:]]))

    assert (stored.lines, stored.longest_line, stored.longest_line_at) == (6, 8, 3)
    assert list(programs.lines(settings, stored.id, start_line=3)) == [
        b"G0 X0 Y0", b"", b"M30", b"%"]


def test_a_program_of_cr_line_ends_counted_as_one_line_before_is_counted_again(
        settings) -> None:
    import json

    data = b"\r".join(b"N%d G1 X%d." % (n, n) for n in range(1, 1001)) + b"\r"
    stored = programs.store(settings, iter([data]))
    record = programs.program_dir(settings) / f"{stored.id}.json"
    record.write_text(json.dumps({"id": stored.id, "size": len(data), "lines": 1,
                                  "longest_line": len(data) - 1, "longest_line_at": 1}))

    assert programs.info(settings, stored.id) == stored  # 1,000 lines: no longer refused
    assert (stored.lines, stored.refusal()) == (1000, None)


def test_the_same_program_stored_twice_is_kept_once(settings) -> None:
    first = programs.store(settings, iter([PROGRAM]))
    second = programs.store(settings, iter([PROGRAM[:3], PROGRAM[3:]]))

    assert first == second
    kept = [p for p in blobs.blob_dir(settings).rglob("*") if p.is_file()]
    assert [p.name for p in kept] == [first.id]


def test_a_program_whose_upload_breaks_leaves_nothing_behind(settings) -> None:
    def broken():
        yield b"G0 X0\n"
        raise ConnectionError("client went away")

    with pytest.raises(ConnectionError):
        programs.store(settings, broken())

    assert [p for p in blobs.blob_dir(settings).rglob("*") if p.is_file()] == []
    assert not programs.program_dir(settings).exists()


def test_an_unknown_or_malformed_program_id_is_refused(settings) -> None:
    with pytest.raises(ContractError) as missing:
        programs.info(settings, "0" * 64)
    with pytest.raises(ContractError) as malformed:
        programs.info(settings, "../../api-key")

    assert missing.value.code is ErrorCode.PATH_NOT_FOUND
    assert malformed.value.code is ErrorCode.BAD_PARAMETER


def test_the_api_stores_a_raw_body_and_answers_its_id_size_and_lines(client) -> None:
    answer = client.post("/api/programs", content=PROGRAM,
                         headers={"content-type": "application/octet-stream"})

    assert answer.status_code == 201
    assert answer.json() == {"id": hashlib.sha256(PROGRAM).hexdigest(), "size": len(PROGRAM),
                             "lines": 6}
    assert client.get(f"/api/programs/{answer.json()['id']}").json()["lines"] == 6


def test_content_stored_in_the_library_runs_as_a_program_without_a_copy(settings) -> None:
    blob = blobs.put(settings, iter([PROGRAM]))

    assert programs.info(settings, blob.sha256) == programs.ProgramInfo(
        blob.sha256, len(PROGRAM), 6, longest_line=len("G1 X10 F200"), longest_line_at=4)
    assert list(programs.lines(settings, blob.sha256))[1] == b"O0010"
    assert [p for p in blobs.blob_dir(settings).rglob("*") if p.is_file()] == [
        blobs.path(settings, blob.sha256)]
