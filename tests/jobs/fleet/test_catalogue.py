"""The controller catalogue: forgiving lookups, and the seed's tables 55-57 as rows."""

from __future__ import annotations

import pytest

from jobs.fleet import catalogue
from jobs.fleet.catalogue import Naming, UnknownModel, lookup

# Table 55: (a model name of the row, may a request name a folder, default root).
TABLE_55 = [
    ("Brother TC", False, "/"),
    ("Brother S", True, "/"),
    ("Delta", True, "B:\\"),
    ("Fagor", True, "MEMORY"),
    *((f"Fanuc {m}", True, "//CNC_MEM/")
      for m in ("0i-D", "0i-F", "30i", "31i", "32i", "35i", "Power Motion i-A")),
    ("Fanuc 18i", False, "//CNC_MEM/"),  # the foreground folder, "such as //CNC_MEM/"
    ("Gsk 980", True, "/user/NCPROG"),
    ("Gsk 988", True, "/user/NCPROG"),
    ("Haas", True, ""),
    ("Haas MT-CONNECT", True, ""),
    ("Heidenhain TNC640", True, "TNC:\\nc_prog"),
    ("Heidenhain TNC640 DNC", True, "TNC:\\nc_prog"),
    ("Heidenhain iTNC530", True, "TNC:\\"),
    ("Lynuc", True, "/home/Lynuc/Users/NCFiles"),
    ("Mitsubishi", True, "PRG\\USER\\"),
    ("Mitsubishi M800", True, "PRG\\USER\\"),
    ("Mock", True, "/"),
    ("Okuma", True, "MD1"),
    ("Rexroth OPC UA", True, "Filesystem/prog"),
    ("Siemens", True, "/nckfs"),
    ("Siemens OPC UA", True, "Sinumerik/FileSystem/PartProgram"),
    ("Siemens 810D", True, "mpf.dir"),
    ("Siemens 840D", True, "mpf.dir"),
    ("Other", False, ""),
    ("FTP server", True, "/"),
    ("Shared folder", True, ""),
    ("Shared folder (Win XP)", True, ""),
    ("Wireless transfer box", True, "/"),
    ("Gateway file server", True, "/"),
]

# Table 56: (model, does a listing return subfolders). Models the table does not
# name fall under its "other models" row (X).
TABLE_56 = [
    ("Brother TC", True),
    ("Brother S", True),
    ("Fagor", False),
    *((f"Fanuc {m}", True) for m in ("0i-D", "0i-F", "30i", "31i", "32i", "35i",
                                     "Power Motion i-A")),
    ("Fanuc 18i", False),
    ("Heidenhain TNC640", True),
    ("Heidenhain iTNC530", True),
    ("Lynuc", True),
    ("Mitsubishi", False),
    ("Mitsubishi M700", False),
    ("Mitsubishi M800", False),
    ("Mock", True),
    ("Okuma", True),
    ("Rexroth OPC UA", True),
    ("Siemens", True),
    ("Siemens OPC UA", True),
    ("Siemens 840D", True),
    ("Other", False),
    ("FTP server", True),
    ("Shared folder", True),
    ("Shared folder (Win XP)", True),
    ("Wireless transfer box", True),
    ("Gateway file server", True),
]

# Table 57: (model, can folders be created/removed anywhere). Mitsubishi M700/M800
# only on the card, checked separately.
TABLE_57 = [
    ("Brother S", True),
    ("Brother TC", False),
    ("Delta", True),
    *((f"Fanuc {m}", True) for m in ("0i-D", "0i-F", "30i", "31i", "32i", "35i",
                                     "Power Motion i-A")),
    ("Fanuc 18i", False),
    ("Gsk 980", False),
    ("Haas", True),
    ("Heidenhain TNC640", True),
    ("Heidenhain iTNC530", True),
    ("Mock", True),
    ("Okuma", True),
    ("Rexroth OPC UA", True),
    ("Siemens", True),
    ("Siemens 840D", True),
    ("Other", False),
    ("FTP server", True),
    ("Shared folder", True),
    ("Shared folder (Win XP)", True),
    ("Wireless transfer box", True),
    ("Gateway file server", True),
]


def test_lookup_finds_a_model_by_its_name():
    assert lookup("Fanuc 0i-F").name == "Fanuc 0i-F"


@pytest.mark.parametrize("spelling", ["fanuc-0i-f", "FANUC 0i-F", "fanuc 0if", " Fanuc  0i - F "])
def test_lookup_ignores_case_spaces_and_dashes(spelling):
    assert lookup(spelling) is lookup("Fanuc 0i-F")


def test_lookup_takes_a_variant_of_a_listed_model_as_that_model():
    assert lookup("FANUC 0i-F Plus") is lookup("Fanuc 0i-F")


@pytest.mark.parametrize(("variant", "model"), [
    ("Fanuc 0i-MF", "Fanuc 0i-F"), ("Fanuc 0i-TF Plus", "Fanuc 0i-F"),
    ("Fanuc 0i-MD", "Fanuc 0i-D"), ("Fanuc 0i-TD", "Fanuc 0i-D"),
])
def test_lookup_takes_the_mill_and_lathe_variants_of_the_0i_as_that_model(variant, model):
    assert lookup(variant) is lookup(model)


def test_lookup_prefers_the_longest_matching_model_over_the_brand():
    assert lookup("Siemens 840D sl").name == "Siemens 840D"


def test_lookup_sends_a_fanuc_outside_the_listed_models_to_the_other_fanuc_row():
    row = lookup("Fanuc 18i")
    assert row.name == "Fanuc (other models)"
    assert row.naming is Naming.FANUC


def test_lookup_keeps_standard_listing_names_for_the_listed_fanuc_models_only():
    assert lookup("Fanuc 0i-F").naming is Naming.FANUC_STANDARD
    assert lookup("Fanuc 18i").naming is not Naming.FANUC_STANDARD


def test_lookup_raises_for_an_unknown_brand():
    with pytest.raises(UnknownModel, match="Acme 3000"):
        lookup("Acme 3000")


def test_every_name_and_alias_of_a_row_finds_that_row():
    for row in catalogue.ROWS:
        for spelling in (row.name, *row.aliases):
            assert lookup(spelling) is row, spelling


@pytest.mark.parametrize(("model", "target_folder", "default_root"), TABLE_55)
def test_table_55_row_has_the_seeds_target_folder_rule_and_default_root(
    model, target_folder, default_root
):
    row = lookup(model)
    assert (row.target_folder, row.default_root) == (target_folder, default_root)


@pytest.mark.parametrize(("model", "list_subdirs"), TABLE_56)
def test_table_56_row_lists_subfolders_as_the_seed_says(model, list_subdirs):
    assert lookup(model).list_subdirs is list_subdirs


@pytest.mark.parametrize(("model", "make_dirs"), TABLE_57)
def test_table_57_row_makes_folders_as_the_seed_says(model, make_dirs):
    row = lookup(model)
    assert row.make_dirs is make_dirs
    assert row.make_dirs_roots is None


@pytest.mark.parametrize("model", ["Mitsubishi M70", "Mitsubishi M700", "Mitsubishi M80",
                                   "Mitsubishi M800"])
def test_table_57_mitsubishi_m700_and_m800_make_folders_only_on_the_card(model):
    row = lookup(model)
    assert row.make_dirs_roots == ("IC1",)
    assert "IC1" in row.roots


@pytest.mark.parametrize("model", ["Fanuc 0i-F", "Fanuc 30i", "Fanuc 31i", "Fanuc 32i",
                                   "Fanuc 35i", "Fanuc Power Motion i-A"])
def test_table_55_note_listed_fanuc_models_may_use_the_memory_card(model):
    assert "//MEMCARD/" in lookup(model).roots


def test_table_55_note_fanuc_0i_d_has_no_memory_card_root():
    assert "//MEMCARD/" not in lookup("Fanuc 0i-D").roots


@pytest.mark.parametrize(("model", "allowed"), [
    ("Fanuc 0i-F", True), ("Fanuc 18i", True), ("Mitsubishi M800", True),
    ("Mitsubishi", True), ("Siemens 840D", False), ("Heidenhain TNC640", False),
    ("Brother S", False), ("Mock", False),
])
def test_lock_range_only_for_fanuc_and_mitsubishi(model, allowed):
    assert lookup(model).lock_range is allowed


@pytest.mark.parametrize(("model", "allowed"), [
    ("Brother S", True), ("Brother TC", True), ("Fanuc 0i-F", True), ("Fanuc 0i-D", True),
    ("Mock", True), ("Fanuc 18i", False), ("Siemens 840D", False),
    ("Heidenhain TNC640", False), ("Mitsubishi M800", False),
])
def test_select_program_only_for_brother_listed_fanuc_and_mock(model, allowed):
    assert lookup(model).select_program is allowed


@pytest.mark.parametrize(("model", "needed"), [
    ("Siemens 840D", True), ("Siemens", True), ("Gsk 980", True),
    ("Heidenhain TNC640", True), ("Fanuc 0i-F", False), ("Mock", False),
])
def test_extension_required_where_the_seed_says(model, needed):
    assert lookup(model).needs_extension is needed
