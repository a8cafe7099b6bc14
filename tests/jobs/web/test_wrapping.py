"""Where a long name may wrap on a page (jobs.web.wrapping)."""

from __future__ import annotations

from jobs.web.wrapping import LONG_WORD_CHARS, breakable


def test_a_path_may_wrap_after_its_separators_and_before_its_extension() -> None:
    shown = breakable("CAM/FIXTURE_PLATE_SECOND_OP/O1234_ROUGHING.nc")

    assert shown == ("CAM/<wbr>FIXTURE_<wbr>PLATE_<wbr>SECOND_<wbr>OP/<wbr>O1234_<wbr>"
                     "ROUGHING<wbr>.nc")


def test_a_windows_path_and_a_dashed_name_may_wrap_at_their_separators() -> None:
    assert breakable(r"C:\CNC\PART-A.nc") == r"C:\<wbr>CNC\<wbr>PART-<wbr>A<wbr>.nc"


def test_a_run_of_separators_is_kept_together_and_nothing_breaks_at_either_end() -> None:
    assert breakable("../x__y") == "../<wbr>x__<wbr>y"
    assert breakable("NAME.") == "NAME."


def test_a_name_is_escaped_as_html() -> None:
    assert breakable("<b>&_x") == "&lt;b&gt;&amp;_<wbr>x"


def test_only_a_word_longer_than_any_cell_is_marked_to_be_cut_inside() -> None:
    long_word, short_word = "X" * (LONG_WORD_CHARS + 1), "Y" * LONG_WORD_CHARS

    assert breakable(f"{long_word}_{short_word}") == \
        f'<span class="long-word">{long_word}</span>_<wbr>{short_word}'


def test_nothing_shows_as_nothing() -> None:
    assert breakable(None) == ""
