"""What a listing entry keeps of the size a far side gives: a byte count, or nothing."""

from __future__ import annotations

import pytest

from worker.transports import moonraker, octoprint
from worker.transports.base import Entry
from worker.transports.ftp_listing import parse_list_line, parse_mlsx

NONSENSE_SIZES = [-1, -5, 2**63, 10**30, True, 1.5, "12"]


@pytest.mark.parametrize("size", NONSENSE_SIZES)
def test_a_size_that_is_no_byte_count_is_unknown(size: object) -> None:
    assert Entry("O0001", False, size).size is None  # type: ignore[arg-type]


@pytest.mark.parametrize("size", [0, 42, 2**63 - 1])
def test_a_byte_count_is_kept(size: int) -> None:
    assert Entry("O0001", False, size).size == size


@pytest.mark.parametrize("size", NONSENSE_SIZES)
def test_octoprint_and_moonraker_listings_drop_a_nonsense_size(size: object) -> None:
    listed = octoprint._entry({"name": "part.gcode", "type": "machinecode", "size": size})
    assert listed.name == "part.gcode" and listed.size is None
    assert moonraker._entry("part.gcode", False, {"size": size}).size is None


def test_an_ftp_listing_with_an_absurd_size_gives_no_size() -> None:
    absurd = "9" * 30
    mlsd = parse_mlsx(f"type=file;size={absurd};modify=20250101000000; O0001")
    unix = parse_list_line(f"-rw-r--r-- 1 ftp ftp {absurd} Jan 02  2020 O0001")
    assert mlsd is not None and mlsd.size is None
    assert unix is not None and unix.name == "O0001" and unix.size is None
