"""File names and folders from a command's body: prefix, suffix, extension modes, padding,
ignored characters, and the refusal of anything that is not one safe name."""

from __future__ import annotations

import pytest

from jobs.fleet.request_settings import NamingRules
from jobs.requests.naming import file_name, path_of, relative_folder


def test_prefix_suffix_and_extension_make_the_seeds_file_name():
    naming = NamingRules(prefix="P", suffix="_A", extension="NC")

    assert file_name("0010", naming) == "P0010_A.NC"


def test_a_number_is_padded_on_its_left_to_the_minimum_length():
    assert file_name("10", NamingRules(pad_to=4)) == "0010"


def test_padding_uses_the_padding_character():
    assert file_name("7", NamingRules(pad_to=3, pad_char="_")) == "__7"


def test_a_number_as_long_as_the_minimum_is_not_padded():
    assert file_name("12345", NamingRules(pad_to=4)) == "12345"


def test_a_name_that_is_not_a_number_is_not_padded():
    assert file_name("AB", NamingRules(pad_to=4)) == "AB"


def test_padding_comes_before_the_prefix():
    assert file_name("10", NamingRules(pad_to=4, prefix="O")) == "O0010"


def test_the_number_letter_is_dropped_before_a_number():
    naming = NamingRules(pad_to=4, number_letter="O")

    assert file_name("O10", naming) == file_name("10", naming) == "0010"


def test_the_number_letter_stays_in_a_name_that_is_not_a_number():
    assert file_name("OFFSET", NamingRules(number_letter="O")) == "OFFSET"


def test_ignored_characters_are_dropped_from_the_body():
    assert file_name(' "00 10" ', NamingRules(ignore_chars='" ')) == "0010"


def test_replace_mode_changes_the_bodys_extension():
    assert file_name("PART.TXT", NamingRules(extension="NC", extension_mode="replace")) == (
        "PART.NC")


def test_replace_mode_adds_the_extension_to_a_body_without_one():
    assert file_name("PART", NamingRules(extension="NC", extension_mode="replace")) == "PART.NC"


def test_add_mode_adds_the_extension_even_after_the_bodys():
    assert file_name("PART.TXT", NamingRules(extension="NC", extension_mode="add")) == (
        "PART.TXT.NC")


def test_remove_mode_drops_the_bodys_extension():
    assert file_name("PART.TXT", NamingRules(extension="NC", extension_mode="remove")) == "PART"


def test_keep_mode_keeps_the_bodys_extension():
    assert file_name("PART.TXT", NamingRules(extension="NC", extension_mode="keep")) == (
        "PART.TXT")


def test_keep_mode_adds_the_extension_when_the_body_has_none():
    assert file_name("PART", NamingRules(extension="NC", extension_mode="keep")) == "PART.NC"


def test_the_suffix_goes_before_the_bodys_kept_extension():
    assert file_name("PART.H", NamingRules(suffix="_2")) == "PART_2.H"


def test_a_padded_number_keeps_its_extension():
    assert file_name("10.NC", NamingRules(pad_to=4)) == "0010.NC"


@pytest.mark.parametrize("body", ["../x", "..", "a/b", "a\\b", "x\x07y", "", "   ", "...",
                                  "a:b"])
def test_a_body_that_is_not_one_safe_name_is_refused(body):
    with pytest.raises(ValueError):
        file_name(body, NamingRules())


def test_a_leading_slash_of_a_folder_is_dropped():
    assert relative_folder("/VIPROS") == "VIPROS"


def test_a_folder_with_backslashes_is_written_with_slashes():
    assert relative_folder("VIPROS\\OLD\\") == "VIPROS/OLD"


def test_an_empty_folder_or_a_slash_is_the_top():
    assert relative_folder("") == relative_folder("/") == ""


@pytest.mark.parametrize("body", ["../..", "VIPROS/../..", "C:\\NC", "//server/share",
                                  "\\\\server\\share", "A//B", "A/\x01"])
def test_a_folder_that_leaves_the_sources_is_refused(body):
    with pytest.raises(ValueError):
        relative_folder(body)


def test_a_path_of_the_top_is_the_name_alone():
    assert path_of("", "0010") == "0010"
    assert path_of("VIPROS", "0010") == "VIPROS/0010"
