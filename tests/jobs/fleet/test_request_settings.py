"""A machine's request settings: validated at load, presets per controller family."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from jobs.fleet.request_settings import (
    Action,
    RequestSettings,
    Source,
    decode_marker,
    family_of,
    resolve,
)


def test_a_hex_escape_is_its_character():
    assert decode_marker("#1B#26") == "\x1b&"


def test_a_marker_without_escapes_is_itself():
    assert decode_marker("%H") == "%H"


def test_two_hashes_are_one_hash():
    assert decode_marker("##1B") == "#1B"


@pytest.mark.parametrize("marker", ["#", "#1", "#G0", "A#"])
def test_a_hash_that_starts_no_escape_is_refused(marker):
    with pytest.raises(ValueError, match="is not '##' or '#' and two hex digits"):
        decode_marker(marker)


def test_a_control_character_written_as_it_is_is_refused_with_its_escape():
    with pytest.raises(ValueError, match="#1B"):
        decode_marker("\x1b&")


def test_the_defaults_read_the_seeds_example():
    settings = RequestSettings()

    assert settings.request_program == "O8888"
    assert settings.action_of("DIR") is Action.SET_PATH
    assert settings.action_of("prg") is Action.SEND
    assert settings.switch_window_s == 180.0
    assert settings.max_request_bytes == 65536
    assert settings.parsed_sources == [Source("library", "")]


def test_an_unknown_field_is_refused():
    with pytest.raises(ValidationError, match="extra"):
        RequestSettings.model_validate({"enabeld": True})


def test_a_pattern_that_does_not_compile_is_refused_at_load():
    with pytest.raises(ValidationError, match="does not compile"):
        RequestSettings(patterns=[r"\((\w+=(.*)\)"])


def test_a_pattern_with_one_group_is_refused_at_load():
    with pytest.raises(ValidationError, match="needs two, the command and its body"):
        RequestSettings(patterns=[r"\((\w+)\)"])


def test_a_pattern_with_named_groups_command_and_body_is_taken():
    settings = RequestSettings(patterns=[r"\[(?P<command>\w+) (?P<body>\w*)\]"])

    assert settings.patterns == [r"\[(?P<command>\w+) (?P<body>\w*)\]"]


def test_command_names_differing_only_in_case_are_refused():
    with pytest.raises(ValidationError, match="are one name"):
        RequestSettings(commands={"PRG": "send", "prg": "list"})


def test_a_command_mapped_to_no_action_is_refused():
    with pytest.raises(ValidationError, match="commands.PRG"):
        RequestSettings(commands={"PRG": "fetch"})


def test_a_header_with_neither_name_length_nor_separator_is_refused():
    with pytest.raises(ValidationError, match="name_chars or a header.separator"):
        RequestSettings(where="header", header={"start": "#1B&", "separator": ""})


def test_a_header_marker_with_a_bad_escape_is_refused_at_load():
    with pytest.raises(ValidationError, match="two hex digits"):
        RequestSettings(header={"start": "#ZZ"})


def test_a_listing_template_with_an_unknown_field_is_refused():
    with pytest.raises(ValidationError, match=r"\{owner\} is not one of"):
        RequestSettings(listing={"line": "{name} {owner}"})


def test_a_listing_template_with_attribute_access_is_refused():
    with pytest.raises(ValidationError, match="is not one of"):
        RequestSettings(listing={"line": "{name.__class__}"})


def test_a_report_template_that_does_not_parse_is_refused():
    with pytest.raises(ValidationError, match="does not parse"):
        RequestSettings(error_program={"not_found": "NOT FOUND {path"})


def test_a_library_source_is_its_folder():
    assert Source.parse("library:VIPROS") == Source("library", "VIPROS")


def test_a_machine_source_keeps_the_folder_in_the_machines_notation():
    assert Source.parse("machine:1010:TNC:\\nc_prog") == Source(
        "machine", "TNC:\\nc_prog", "1010")


@pytest.mark.parametrize("text", ["VIPROS", "library:../x", "machine:1010", "machine::/x",
                                  "machine:1010:/a/../b", "ftp:1010:/x"])
def test_a_source_of_another_form_is_refused(text):
    with pytest.raises(ValueError):
        Source.parse(text)


def test_sources_are_validated_at_load():
    with pytest.raises(ValidationError, match="is not library:FOLDER"):
        RequestSettings(sources=["library:VIPROS", "C:\\NC"])


def test_a_receive_folder_that_leaves_the_library_is_refused():
    with pytest.raises(ValidationError, match="has a '..' step"):
        RequestSettings(receive_folder="RECEIVED/../..")


@pytest.mark.parametrize(("model", "preset"), [
    ("Fanuc 0i-F", "fanuc"), ("Fanuc 16i", "fanuc"), ("Haas", "haas"),
    ("Heidenhain TNC640", "heidenhain_iso"), ("Heidenhain iTNC530", "heidenhain_iso"),
    ("Siemens 840D", "siemens_iso"), ("Sinumerik", "siemens_iso"),
    ("siemens_iso", "siemens_iso"), ("Mitsubishi M700", None), ("No such model", None),
])
def test_a_controller_gets_its_familys_preset(model, preset):
    assert family_of(model) == preset


def test_the_fanuc_preset_pads_numbers_to_four_digits_under_o8888():
    settings = resolve("Fanuc 0i-F", None)

    assert (settings.preset, settings.dialect, settings.request_program) == (
        "fanuc", "fanuc", "O8888")
    assert (settings.naming.pad_to, settings.naming.prefix) == (4, "")
    assert (settings.listing.comment_open, settings.listing.comment_close) == ("(", ")")


def test_the_haas_preset_writes_five_digit_numbers():
    settings = resolve("Haas", None)

    assert (settings.request_program, settings.naming.pad_to) == ("O08888", 5)
    assert settings.listing.program_name == "O08889"


def test_the_heidenhain_preset_comments_with_a_semicolon_and_numbers_every_block():
    settings = resolve("Heidenhain TNC640", None)

    assert settings.dialect == "heidenhain_iso"
    assert settings.listing.comment_open == ";"
    assert settings.listing.block_numbers is True
    assert settings.naming.extension == "I"


def test_the_siemens_preset_names_main_programs():
    settings = resolve("Siemens 840D", None)

    assert settings.dialect == "siemens_iso"
    assert (settings.listing.comment_open, settings.listing.comment_close) == (";", "")
    assert settings.naming.extension == "MPF"
    assert settings.listing.program_name == "DNCLIST.MPF"


def test_a_model_without_preset_gets_the_fanuc_like_defaults():
    settings = resolve("Mitsubishi M700", {"enabled": True})

    assert settings.preset is None
    assert settings.model_dump(exclude={"enabled"}) == RequestSettings().model_dump(
        exclude={"enabled"})


def test_given_nested_fields_override_the_preset_one_by_one():
    settings = resolve("Haas", {"naming": {"pad_to": 4}})

    assert settings.naming.pad_to == 4
    assert settings.naming.number_letter == "O"  # the rest of the preset's naming kept


def test_given_commands_replace_the_presets_whole():
    settings = resolve("Fanuc 0i-F", {"commands": {"GET": "send"}})

    assert settings.commands == {"GET": Action.SEND}


def test_a_given_preset_wins_over_the_models_family():
    settings = resolve("Fanuc 0i-F", {"preset": "siemens_iso"})

    assert (settings.preset, settings.dialect) == ("siemens_iso", "siemens_iso")


def test_invalid_given_settings_are_refused_as_a_value_error():
    with pytest.raises(ValueError, match="switch_window_s"):
        resolve("Fanuc 0i-F", {"switch_window_s": 0})


def test_answers_go_to_the_drop_folder_unless_another_is_given():
    assert RequestSettings(drop_folder="/REQ").answers_to == "/REQ"
    assert RequestSettings(drop_folder="/REQ", answer_folder="/ANS").answers_to == "/ANS"
