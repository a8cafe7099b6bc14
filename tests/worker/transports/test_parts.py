"""Half-written files named after their writer: which are still being written."""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path
from typing import Any

from worker.transports import parts

PREFIX = ".assembling-"


def test_a_part_placed_while_the_folder_is_read_is_its_writer_at_work(
        tmp_path: Path, monkeypatch: Any) -> None:
    # Another assembly of the job placed its ZIP (removing its part) between the listing of
    # the folder and the look at the part's age: that one registers the backup (or records
    # why it could not), so the caller must leave the job to it, not fail it.
    placed = tmp_path / parts.part_name(PREFIX, "B-j1-b2.zip.part")
    placed.write_bytes(b"PK")
    scandir = os.scandir

    def listed_then_placed(folder: Any) -> Any:
        entries = list(scandir(folder))
        placed.unlink()
        return contextlib.nullcontext(entries)

    monkeypatch.setattr(parts.os, "scandir", listed_then_placed)

    assert parts.others_writing(tmp_path, PREFIX, "-j1-", besides="mine") is True


def test_a_part_of_another_host_counts_as_written_until_left_untouched(tmp_path: Path) -> None:
    other = tmp_path / f"{PREFIX}another_host-1-B-j1-b2.zip.part"
    other.write_bytes(b"PK")
    assert parts.others_writing(tmp_path, PREFIX, "-j1-", besides="mine")
    assert not parts.others_writing(tmp_path, PREFIX, "-j9-", besides="mine")  # another job
    assert not parts.others_writing(tmp_path, PREFIX, "-j1-", besides=other.name)  # its own
    long_ago = time.time() - parts.STILL_WRITING_S - 60
    os.utime(other, (long_ago, long_ago))
    assert not parts.others_writing(tmp_path, PREFIX, "-j1-", besides="mine")
