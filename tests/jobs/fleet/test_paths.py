"""MachinePaths: dirAtCNC/subDir to a folder inside a machine's roots, and the name rules."""

from __future__ import annotations

import pytest

from jobs.errors import ContractError, ErrorCode
from jobs.fleet.catalogue import lookup
from jobs.fleet.paths import MachinePaths, Place, fanuc_name_from_content


def paths(model: str, root: str | None = None, *, confine: bool = False) -> MachinePaths:
    return MachinePaths(lookup(model), root, confine=confine)


def shown(model: str, dir_at_cnc: str | None, sub_dir: str | None = None,
          root: str | None = None) -> str:
    p = paths(model, root)
    return p.display(p.resolve(dir_at_cnc, sub_dir))


def code_of(call) -> ErrorCode:
    with pytest.raises(ContractError) as info:
        call()
    return info.value.code


# -- folders ---------------------------------------------------------------


@pytest.mark.parametrize(("model", "root"), [
    ("Fanuc 0i-F", "//CNC_MEM/"), ("Siemens 840D", "mpf.dir"),
    ("Heidenhain TNC640", "TNC:\\nc_prog"), ("Mitsubishi M800", "PRG\\USER\\"),
    ("Brother S", "/"), ("Mock", "/"), ("Fanuc 18i", "//CNC_MEM/"), ("Other", ""),
])
def test_no_folder_resolves_to_the_default_root(model, root):
    assert shown(model, None) == root


def test_empty_dir_at_cnc_resolves_to_the_default_root():
    assert shown("Siemens 840D", "") == "mpf.dir"


def test_sub_dir_alone_is_joined_to_the_default_root():
    assert shown("Siemens 840D", None, "dir1/sub") == "mpf.dir/dir1/sub"


def test_sub_dir_is_ignored_when_dir_at_cnc_is_given():
    assert shown("Fanuc 0i-F", "//CNC_MEM/USER", "OTHER") == "//CNC_MEM/USER"


def test_relative_dir_at_cnc_is_below_the_default_root():
    assert shown("Siemens 840D", "dir1") == "mpf.dir/dir1"


@pytest.mark.parametrize(("model", "dir_at_cnc"), [
    ("Fanuc 0i-F", "//CNC_MEM/USER"),
    ("Heidenhain TNC640", "TNC:\\nc_prog\\demo"),
    ("Mitsubishi M800", "IC1"),
    ("Mock", "/1/1"),
])
def test_rooted_dir_at_cnc_is_taken_as_written(model, dir_at_cnc):
    assert shown(model, dir_at_cnc) == dir_at_cnc


@pytest.mark.parametrize(("model", "written", "corrected"), [
    ("Heidenhain TNC640", "TNC:/nc_prog/demo", "TNC:\\nc_prog\\demo"),
    ("Fanuc 0i-F", "//cnc_mem/USER", "//CNC_MEM/USER"),
    ("Fanuc 0i-F", "//CNC_MEM", "//CNC_MEM/"),
    ("Mitsubishi M800", "ic1/sub", "IC1\\sub"),
    ("Mitsubishi M800", "prg/user", "PRG\\USER\\"),
])
def test_rooted_dir_at_cnc_is_shown_in_the_models_notation(model, written, corrected):
    assert shown(model, written) == corrected


def test_longest_root_wins_so_tnc_nc_prog_is_not_read_as_tnc_drive_plus_folder():
    p = paths("Heidenhain TNC640")
    assert p.resolve("TNC:\\nc_prog\\demo", None).root.display == "TNC:\\nc_prog"


def test_the_drive_root_of_tnc640_is_reachable_beside_its_default():
    p = paths("Heidenhain TNC640")
    assert p.resolve("TNC:\\", None) == Place(p.roots[-1])
    assert p.display(p.resolve("TNC:\\", None)) == "TNC:\\"


def test_storage_path_folds_drive_and_separators():
    p = paths("Heidenhain TNC640")
    assert p.resolve("TNC:\\nc_prog\\demo", None).storage == "TNC/nc_prog/demo"


def test_fanuc_0i_f_reaches_the_memory_card():
    assert shown("Fanuc 0i-F", "//MEMCARD/") == "//MEMCARD/"


def test_fanuc_0i_d_refuses_the_memory_card():
    assert code_of(lambda: paths("Fanuc 0i-D").resolve("//MEMCARD/", None)) \
        is ErrorCode.PATH_OUTSIDE_ROOT


@pytest.mark.parametrize(("model", "foreign"), [
    ("Fanuc 0i-F", "/etc"), ("Siemens 840D", "/nckfs"), ("Heidenhain TNC640", "C:\\nc_prog"),
])
def test_rooted_dir_at_cnc_outside_the_models_roots_is_refused(model, foreign):
    assert code_of(lambda: paths(model).resolve(foreign, None)) is ErrorCode.PATH_OUTSIDE_ROOT


@pytest.mark.parametrize(("dir_at_cnc", "sub_dir"), [("../x", None), (None, "a/../../x"),
                                                     ("//CNC_MEM/..", None)])
def test_dot_dot_in_a_folder_is_refused(dir_at_cnc, sub_dir):
    assert code_of(lambda: paths("Fanuc 0i-F").resolve(dir_at_cnc, sub_dir)) \
        is ErrorCode.PATH_OUTSIDE_ROOT


@pytest.mark.parametrize("model", ["Fanuc 18i", "Brother TC", "Other"])
@pytest.mark.parametrize(("dir_at_cnc", "sub_dir"), [("dir1", None), (None, "dir1")])
def test_model_without_target_folder_refuses_dir_at_cnc_and_sub_dir(model, dir_at_cnc, sub_dir):
    assert code_of(lambda: paths(model).resolve(dir_at_cnc, sub_dir)) is ErrorCode.UNSUPPORTED


def test_configured_root_is_the_default():
    assert shown("Mitsubishi M800", None, root="IC1") == "IC1"


def test_configured_root_leaves_the_models_roots_reachable_on_its_own_storage():
    assert shown("Fanuc 0i-F", "//CNC_MEM/USER", root="//MEMCARD/") == "//CNC_MEM/USER"


def test_confined_configured_root_is_the_only_reachable_root():
    p = paths("FTP server", "/cnc", confine=True)
    assert [r.display for r in p.roots] == ["/cnc"]
    assert p.display(p.resolve("/cnc/a", None)) == "/cnc/a"


@pytest.mark.parametrize(("model", "configured", "model_spelling"), [
    ("Fanuc 0i-F", "//memcard/", "//MEMCARD/"),
    ("Mitsubishi M800", "ic1", "IC1"),
    ("Heidenhain TNC640", "TNC:/nc_prog", "TNC:\\nc_prog"),
])
def test_configured_root_spelt_differently_is_the_models_root(model, configured,
                                                              model_spelling):
    p = paths(model, configured)
    assert p.resolve(None, None) == p.resolve(model_spelling, None)
    assert p.display(p.resolve(None, None)) == model_spelling


def test_configured_root_below_a_model_root_keeps_the_models_notation():
    p = paths("Fanuc 0i-F", "//cnc_mem/USER")
    assert p.display(p.resolve(None, None)) == "//CNC_MEM/USER"
    assert p.resolve(None, None).storage == "CNC_MEM/USER"


def test_relative_display_is_slash_for_the_folder_itself():
    assert paths("Mock").relative_display(()) == "/"


def test_relative_display_joins_subfolders():
    assert paths("Mock").relative_display(("1", "1")) == "1/1"


# -- file names --------------------------------------------------------------


@pytest.mark.parametrize("spelling", ["10", "010", "0010", "O0010", "o10"])
def test_fanuc_accepts_every_spelling_of_a_program_number(spelling):
    assert paths("Fanuc 0i-F").stored_name(spelling) == "O0010"


def test_fanuc_keeps_a_non_standard_name():
    assert paths("Fanuc 0i-F").stored_name("SAMPLE") == "SAMPLE"


def test_fanuc_listing_drops_o_and_leading_zeros():
    assert paths("Fanuc 0i-F").listed_name("O0010") == "10"


def test_fanuc_listing_keeps_a_non_standard_name():
    assert paths("Fanuc 0i-F").listed_name("SAMPLE") == "SAMPLE"


def test_fanuc_outside_the_listed_models_lists_the_o_number_unchanged():
    assert paths("Fanuc 18i").listed_name("O0010") == "O0010"


def test_plain_model_lists_names_unchanged():
    assert paths("Mock").listed_name("O0010") == "O0010"


@pytest.mark.parametrize("model", ["Siemens 840D", "Heidenhain TNC640"])
def test_name_without_extension_is_refused_where_the_model_needs_one(model):
    assert code_of(lambda: paths(model).stored_name("PART1")) is ErrorCode.BAD_PARAMETER


def test_name_with_extension_is_taken_where_the_model_needs_one():
    assert paths("Siemens 840D").stored_name("PART1.MPF") == "PART1.MPF"


@pytest.mark.parametrize("name", ["a/b", "a\\b", "..", ".", "C:x", "a\x00b", "", " a"])
def test_file_name_that_is_not_a_plain_name_is_a_bad_parameter(name):
    assert code_of(lambda: paths("Mock").stored_name(name)) is ErrorCode.BAD_PARAMETER


@pytest.mark.parametrize("name", ["\ud800", "P\udc80.nc"])
def test_file_name_with_a_lone_surrogate_is_a_bad_parameter(name):
    assert code_of(lambda: paths("Mock").stored_name(name)) is ErrorCode.BAD_PARAMETER


@pytest.mark.parametrize(("dir_at_cnc", "sub_dir"), [("\ud800", None), (None, "a/\udfff")])
def test_folder_with_a_lone_surrogate_is_a_bad_parameter(dir_at_cnc, sub_dir):
    assert code_of(lambda: paths("Mock").resolve(dir_at_cnc, sub_dir)) is ErrorCode.BAD_PARAMETER


LOOKALIKE_NAMES = ["\uff0e\uff0e\uff0fx", "..\u2215x", "..\uff3cx", "\u2025", "\uff0e\uff0e",
                   "a\uff0fb", "a\u2044b", "a\u29f8b", "a\u2216b", "C\uff1ax", "\uff0edncq-x"]


@pytest.mark.parametrize("name", LOOKALIKE_NAMES)
def test_file_name_that_reads_as_a_path_is_a_bad_parameter(name):
    assert code_of(lambda: paths("Mock").stored_name(name)) is ErrorCode.BAD_PARAMETER


@pytest.mark.parametrize("name", ["\uff21\uff22.nc", "\ufb01le.nc", "\u2460.nc", "caf\u00e9.nc"])
def test_file_name_whose_compatibility_form_is_plain_is_kept_as_written(name):
    assert paths("Mock").stored_name(name) == name


@pytest.mark.parametrize("folder", ["\uff0e\uff0e", "\u2025", "\uff0e\uff0e\uff0fx",
                                    "a/\uff0e\uff0e/b", "..\u2215x", "..\uff3cx"])
@pytest.mark.parametrize("param", ["dir_at_cnc", "sub_dir"])
def test_folder_that_reads_as_dot_dot_is_outside_the_root(param, folder):
    args = {"dir_at_cnc": None, "sub_dir": None, param: folder}

    assert code_of(lambda: paths("Mock").resolve(**args)) is ErrorCode.PATH_OUTSIDE_ROOT


@pytest.mark.parametrize("folder", ["\uff0fetc", "a\u2215b", "a\uff3cb", "\uff23\uff1a"])
def test_folder_with_a_slash_or_drive_look_alike_is_a_bad_parameter(folder):
    assert code_of(lambda: paths("Mock").resolve(folder, None)) is ErrorCode.BAD_PARAMETER


# -- Fanuc program name from content ------------------------------------------


def test_fanuc_name_is_the_text_between_the_first_and_second_newline():
    assert fanuc_name_from_content(b"%\nO0020\nG0 X0\nM30\n%\n") == "O0020"


def test_fanuc_name_is_normalised_to_o_and_four_digits():
    assert fanuc_name_from_content(b"%\nO20 (PART)\nM30\n") == "O0020"


def test_fanuc_named_program_takes_the_name_in_angle_brackets():
    assert fanuc_name_from_content(b"%\n<SAMPLE>\nM30\n%\n") == "SAMPLE"


def test_fanuc_content_without_a_program_name_is_a_bad_parameter():
    assert code_of(lambda: fanuc_name_from_content(b"%\nG0 X0\nM30\n")) \
        is ErrorCode.BAD_PARAMETER
