"""The stored analysis of a program numbers its lines as a drip-feed run does."""

from __future__ import annotations

import os

import pytest

from jobs.library import analyses, blobs
from jobs.settings import Settings

PROGRAM = ["O0010", "T1 M6", "G0 X0 Y0", "G1 X100 F1000", "T2 M6", "G1 Y100", "M30"]


@pytest.mark.parametrize("end", [b"\r", b"\n\r", b"\r\n"])
def test_a_program_of_any_line_end_is_analysed_as_the_same_program_with_lf(
        settings: Settings, end: bytes) -> None:
    # A CR-only program was one line to the analysis: no tools, no time, while its run and
    # its tool-break restart numbered seven.
    as_lf = blobs.put(settings, [("\n".join(PROGRAM) + "\n").encode()]).sha256
    other = blobs.put(settings, [end.join(line.encode() for line in PROGRAM) + end]).sha256

    got, expected = analyses.of_blob(settings, other), analyses.of_blob(settings, as_lf)

    assert got.lines == expected.lines == len(PROGRAM)
    assert [(t.number, t.first_line) for t in got.tools] == [(1, 2), (2, 5)]
    assert got.cycle_time_s == expected.cycle_time_s > 0


def test_two_first_reads_at_once_both_get_the_analysis(
        settings: Settings, monkeypatch: pytest.MonkeyPatch) -> None:
    sha256 = blobs.put(settings, [("\n".join(PROGRAM) + "\n").encode()]).sha256
    replace, inner = os.replace, []

    def other_read_first(source: str, target: str) -> None:
        # the other read writes and renames its cache file before this one renames its own
        monkeypatch.setattr(os, "replace", replace)
        inner.append(analyses.of_blob(settings, sha256))
        replace(source, target)

    monkeypatch.setattr(os, "replace", other_read_first)
    got = analyses.of_blob(settings, sha256)

    assert got.lines == inner[0].lines == len(PROGRAM)
    assert analyses.of_blob(settings, sha256).lines == len(PROGRAM)
    cached = [p.name for p in blobs.path(settings, sha256).parent.iterdir()]
    assert sorted(cached) == [sha256, f"{sha256}.analysis.json"]
