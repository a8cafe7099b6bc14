"""Restart from a block: the point, the header and the modal state, and every refusal."""

from __future__ import annotations

import itertools
import resource
from collections.abc import Iterator
from pathlib import Path

import pytest

from jobs.dnc.blocks import BlockKind, read_block
from jobs.dnc.modal import MachineKind, ModalState
from jobs.dnc.restart import (
    InvalidRestartPoint,
    PointKind,
    RestartPlan,
    RestartPoint,
    RestartPointNotFound,
    RestartRefused,
    plan_restart,
)

PROGRAMS = Path(__file__).parent / "programs"
MILL_SAFE = "G40 G49 G80"
LATHE_SAFE = "G40 G80"


def _program(name: str) -> Iterator[str]:
    """The program's lines, read lazily as a caller reads the file."""
    with (PROGRAMS / name).open(encoding="ascii") as lines:
        yield from lines


def _plan(name: str, **point: str | int) -> RestartPlan:
    return plan_restart(_program(name), RestartPoint.parse(**point))  # type: ignore[arg-type]


def _refusal(name: str, **point: str | int) -> str:
    with pytest.raises(RestartRefused) as refused:
        _plan(name, **point)
    return refused.value.reason


def _tail(line: int, block: int | None, motion: str | None) -> list[str]:
    at = f"LINE {line}" + (f" N{block}" if block is not None else "")
    moves = f"IN {motion} " if motion else ""
    return [f"(RESTART AT {at})",
            f"(NO MOVE ADDED - THE NEXT BLOCK MOVES {moves}FROM WHERE THE TOOL STANDS)"]


# The point as the CLI gives it.

def test_parse_reads_a_block_number_with_or_without_its_n():
    assert RestartPoint.parse(from_block="N1234") == RestartPoint(PointKind.BLOCK, 1234)
    assert RestartPoint.parse(from_block=" n1234 ") == RestartPoint(PointKind.BLOCK, 1234)
    assert RestartPoint.parse(from_block="1234") == RestartPoint(PointKind.BLOCK, 1234)


def test_parse_reads_a_line_number_from_text_or_an_int():
    assert RestartPoint.parse(from_line="48213") == RestartPoint(PointKind.LINE, 48213)
    assert RestartPoint.parse(from_line=7) == RestartPoint(PointKind.LINE, 7)


def test_parse_reads_a_tool_alone_or_looking_back_from_a_line():
    assert RestartPoint.parse(from_tool="T7") == RestartPoint(PointKind.TOOL, 7)
    assert RestartPoint.parse(from_tool="t07", from_line="500") == RestartPoint(
        PointKind.TOOL, 7, before_line=500)


@pytest.mark.parametrize(("options", "message"), [
    ({}, "give one of --from"),
    ({"from_block": "N12", "from_line": "40"}, "--from names the point alone"),
    ({"from_block": "N12", "from_tool": "T1"}, "--from names the point alone"),
    ({"from_block": "G01"}, "'G01' is not a block (write it like N1234)"),
    ({"from_block": "N12.5"}, "'N12.5' is not a block"),
    ({"from_line": "0"}, "'0' is not a line number (lines count from 1)"),
    ({"from_line": "-3"}, "'-3' is not a line number"),
    ({"from_line": "abc"}, "'abc' is not a line number"),
    ({"from_tool": "H7"}, "'H7' is not a tool (write it like T7)"),
    ({"from_tool": "T0"}, "T0 selects no tool"),
])
def test_parse_refuses_what_is_not_a_point_with_a_message_saying_why(options, message):
    with pytest.raises(InvalidRestartPoint) as invalid:
        RestartPoint.parse(**options)
    assert message in invalid.value.reason


def test_describe_names_the_point_in_words():
    assert RestartPoint(PointKind.BLOCK, 12).describe() == "block N12"
    assert RestartPoint(PointKind.LINE, 9).describe() == "line 9"
    assert RestartPoint(PointKind.TOOL, 7).describe() == "the first change to T7"
    assert RestartPoint(PointKind.TOOL, 7, 50).describe() == (
        "the last change to T7 at or before line 50")


# Fanuc milling: several tools, G54/G55, G43 H, coolant, G81.

def test_mill_restart_from_a_block_rebuilds_work_offset_tool_spindle_coolant_and_feed():
    plan = _plan("mill_bracket.nc", from_block="N350")

    assert plan.start_line == 38
    assert plan.block_number == 350
    assert plan.machine_kind is MachineKind.MILL
    assert plan.header == [MILL_SAFE, "G21", "G17", "G55", "G90", "T7 M6", "G43 H7",
                           "S6000 M3", "M7", "G94 F300.", "G1", *_tail(38, 350, "G1")]
    assert plan.modal == ModalState(
        units="G21", plane="G17", work_offset="G55", distance="G90", tool=7,
        tool_word="T7", length_offset="G43 H7", spindle_speed="S6000", spindle="M3",
        coolant=("M7",), feed_mode="G94", feed="F300.", motion="G1", cutter_comp="G40")


def test_mill_restart_from_the_line_of_a_canned_cycle_block_is_allowed():
    plan = _plan("mill_bracket.nc", from_line=22)

    assert plan.start_line == 22
    assert plan.header == [MILL_SAFE, "G21", "G17", "G54", "G90", "T2 M6", "G43 H2",
                           "S2200 M3", "M8", "G94 F600.", "G0", *_tail(22, 190, "G0")]
    assert plan.modal.canned_cycle is None


def test_mill_restart_from_a_tool_starts_at_its_m6_and_leaves_the_change_to_it():
    plan = _plan("mill_bracket.nc", from_tool="T7")  # T7 preselected at N160, M6 at N300

    assert plan.start_line == 33
    assert plan.header == [MILL_SAFE, "G21", "G17", "G55", "G91", "S2200 M5", "M9",
                           "G94 F180.", "G0", *_tail(33, 300, "G0")]  # G49: the safe start's
    assert plan.modal.tool == 2  # the state in force before the change
    assert plan.modal.spindle == "M5"


def test_mill_restart_from_a_tool_without_a_line_takes_its_first_change():
    plan = _plan("mill_bracket.nc", from_tool="T1")

    assert plan.start_line == 5
    assert plan.header == [MILL_SAFE, "G21", "G17", "G90", "M5", "M9", "G94",
                           *_tail(5, 20, None)]


def test_mill_restart_from_a_tool_cancels_the_length_offset_once():
    default = _plan("mill_bracket.nc", from_tool="T7")
    configured = plan_restart(_program("mill_bracket.nc"), RestartPoint.parse(from_tool="T7"),
                              safe_start=["G40 G80", "G91 G28 Z0."])

    assert sum(block.split().count("G49") for block in default.header) == 1  # G40 G49 G80
    assert configured.header[:7] == ["G40 G80", "G91 G28 Z0.", "G21", "G17", "G55", "G91",
                                     "G49"]  # a safe start without G49: the header's own


def test_mill_restart_from_a_tool_before_a_line_takes_its_last_change_up_to_that_line():
    plan = _plan("mill_bracket.nc", from_tool="T1", from_line=50)

    assert plan.start_line == 44
    assert plan.header == [MILL_SAFE, "G21", "G17", "G55", "G91", "S6000 M5", "M9",
                           "G94 F900.", "G0", *_tail(44, 410, "G0")]


def test_mill_restart_from_a_tool_before_a_line_ignores_changes_after_it():
    assert _plan("mill_bracket.nc", from_tool="T1", from_line=43).start_line == 5


def test_mill_restart_inside_a_canned_cycle_is_refused_naming_its_first_block():
    reason = _refusal("mill_bracket.nc", from_block="N200")

    assert reason == ("cannot restart from block N200 (line 23): line 23 is inside the G81 "
                      "canned cycle started at line 22: restart from line 22, or after the "
                      "cycle ends")


def test_mill_restart_after_the_cycle_is_cancelled_is_allowed():
    plan = _plan("mill_bracket.nc", from_block="N230")

    assert plan.modal.canned_cycle is None
    assert plan.modal.work_offset == "G54"  # N230 itself changes to G55


def test_a_block_that_does_not_exist_is_not_found():
    with pytest.raises(RestartPointNotFound) as missing:
        _plan("mill_bracket.nc", from_block="N9999")
    assert missing.value.reason == "the program has no block N9999 (read 54 lines)"


def test_a_line_past_the_end_and_a_tool_never_used_are_not_found():
    with pytest.raises(RestartPointNotFound, match="no line 900 "):
        _plan("mill_bracket.nc", from_line=900)
    with pytest.raises(RestartPointNotFound, match="no change to tool T9 "):
        _plan("mill_bracket.nc", from_tool="T9")


# Fanuc turning: G50 S clamp, G96/G97, G99 feed per revolution, G71/G70.

def test_lathe_restart_from_a_block_rebuilds_turret_clamp_spindle_mode_and_feed_per_rev():
    plan = _plan("lathe_shaft.nc", from_block="N260")

    assert plan.machine_kind is MachineKind.LATHE
    assert plan.start_line == 28
    assert plan.header == [LATHE_SAFE, "G21", "G18", "T0505", "G50 S3000", "G97 S800 M3",
                           "M8", "G99 F.28", "G0", *_tail(28, 260, "G0")]
    assert plan.modal == ModalState(
        units="G21", plane="G18", tool=5, tool_word="T0505", spindle_mode="G97",
        speed_clamp="G50 S3000", spindle_speed="S800", spindle="M3", coolant=("M8",),
        feed_mode="G99", feed="F.28", motion="G0", cutter_comp="G40")


def test_lathe_restart_at_the_first_block_of_g71_is_allowed():
    plan = _plan("lathe_shaft.nc", from_block="N70")

    assert plan.header == [LATHE_SAFE, "G21", "G18", "T0101", "G50 S2500", "G96 S200 M3",
                           "M8", "G99", "G0", *_tail(9, 70, "G0")]


def test_lathe_restart_after_g71_reads_the_contour_as_cycle_data_not_as_run_blocks():
    plan = _plan("lathe_shaft.nc", from_block="N200")

    assert plan.header == [LATHE_SAFE, "G21", "G18", "T0303", "G50 S3000", "G96 S250 M3",
                           "M9", "G99 F.28", "G0", *_tail(22, 200, "G0")]


def test_lathe_restart_from_a_tool_starts_at_its_t_word_and_keeps_the_spindle_running():
    plan = _plan("lathe_shaft.nc", from_tool="T5")

    assert plan.start_line == 25
    assert plan.header == [LATHE_SAFE, "G21", "G18", "G50 S3000", "G96 S250 M3", "M9",
                           "G99 F.28", "G0", *_tail(25, 230, "G0")]


def test_lathe_restart_from_a_tool_written_with_its_offset_finds_the_t_word():
    assert _plan("lathe_shaft.nc", from_tool="T0303").start_line == 19


def test_lathe_restart_inside_a_g71_contour_is_refused_naming_the_cycle():
    reason = _refusal("lathe_shaft.nc", from_block="N120")

    assert reason == ("cannot restart from block N120 (line 14): line 14 is inside the G71 "
                      "cycle started at line 9 (its contour ends at N150): restart from line 9")


def test_lathe_restart_at_the_second_block_of_g71_is_refused():
    reason = _refusal("lathe_shaft.nc", from_block="N80")

    assert reason.endswith("line 10 is inside the G71 cycle started at line 9: restart from "
                           "line 9")


def test_lathe_restart_inside_a_g90_turning_cycle_is_refused():
    program = ["O1", "G21 G99 T0101", "G97 S1000 M3", "G0 X52. Z2.", "G90 X48. Z-30. F.25",
               "X46.", "X44.", "G0 X100."]

    with pytest.raises(RestartRefused, match="line 6 is inside the G90 canned cycle started "
                                             "at line 5"):
        plan_restart(program, RestartPoint(PointKind.LINE, 6), machine_kind="lathe")


# Subprogram calls.

def test_restart_after_a_subprogram_call_is_refused_until_the_program_sets_everything_again():
    reason = _refusal("mill_pockets_subprogram.nc", from_block="N60")

    assert reason == (
        "cannot restart from block N60 (line 8): N50 M98 P3101 at line 7 calls a subprogram "
        "this scan cannot follow, and the program does not set its units, plane, work "
        "offset, absolute/incremental, tool, length offset, spindle speed, spindle "
        "direction, coolant, feed mode, feed, motion mode, cutter compensation, canned "
        "cycle again before line 8")


def test_restart_after_a_call_names_only_what_is_still_unset():
    reason = _refusal("mill_pockets_subprogram.nc", from_block="N140")

    assert reason.endswith("N70 M98 P3101 at line 9 calls a subprogram this scan cannot "
                           "follow, and the program does not set its feed again before line 16")


def test_restart_once_the_program_has_set_everything_again_is_allowed():
    plan = _plan("mill_pockets_subprogram.nc", from_block="N160")

    assert plan.header == [MILL_SAFE, "G21", "G17", "G54", "G90", "T4 M6", "G43 H4",
                           "S5000 M3", "M8", "G94 F150.", "G1", *_tail(18, 160, "G1")]


def test_restart_at_the_call_itself_is_allowed():
    plan = _plan("mill_pockets_subprogram.nc", from_block="N50")

    assert plan.header == [MILL_SAFE, "G21", "G17", "G54", "G90", "T3 M6", "G43 H3",
                           "S3500 M3", "M8", "G94", "G0", *_tail(7, 50, "G0")]


def test_restart_inside_a_subprogram_body_is_refused():
    reason = _refusal("mill_pockets_subprogram.nc", from_block="N3")

    assert reason == ("cannot restart from block N3 (line 26): line 26 is inside subprogram "
                      "O3101 (from line 23 to its M99): the modal state it runs in is set by "
                      "the program that calls it")


# Macros and other controls.

def test_restart_after_macro_statements_is_refused():
    reason = _refusal("mill_bolt_circle_macro.nc", from_block="N150")

    assert reason == ("cannot restart from block N150 (line 17): line 7 uses macro statements "
                      "(N50 #1=0): variables, macro calls and branching make the modal state "
                      "at the restart point unknowable")


def test_restart_before_the_first_macro_statement_is_allowed():
    plan = _plan("mill_bolt_circle_macro.nc", from_block="N40")

    assert plan.header == [MILL_SAFE, "G21", "G17", "G54", "G90", "T5 M6", "G49", "S2000 M3",
                           "M9", "G94", "G0", *_tail(6, 40, "G0")]


@pytest.mark.parametrize("line", ["IF[#1GT10]GOTO100", "GOTO 20", "WHILE[#1LT6]DO1", "END1",
                                  "G0 X#24", "#500=[#1+1]"])
def test_branching_and_variables_are_read_as_macro_statements(line):
    assert read_block(line).kind is BlockKind.MACRO


def test_a_g65_macro_call_is_refused_as_a_macro():
    program = ["G21 G17 G90", "T1 M6", "G65 P9010 A1. B2.", "G0 X0. Y0."]

    with pytest.raises(RestartRefused, match=r"line 3 uses macro statements \(G65 P9010"):
        plan_restart(program, RestartPoint(PointKind.LINE, 4))


def test_heidenhain_plain_text_is_refused_as_out_of_scope():
    with pytest.raises(RestartRefused) as refused:
        _plan("heidenhain_plate.h", from_line=6)

    assert refused.value.reason == (
        "line 1 is Heidenhain plain text (0 BEGIN PGM 5001 MM): restarting is for ISO "
        "(Fanuc-style) G-code programs only; restart it on the control")
    assert refused.value.line == 1


# What else a restart cannot rebuild.

def test_restart_with_cutter_compensation_active_is_refused():
    program = ["G21 G17 G90 G54", "T1 M6", "S3000 M3", "G0 X-10. Y0.", "G41 D1 G1 X0. F300.",
               "Y50.", "G40 G0 X-10."]

    with pytest.raises(RestartRefused, match="cutter radius compensation G41 .from line 5. is "
                                             "active at line 6"):
        plan_restart(program, RestartPoint(PointKind.LINE, 6))
    assert plan_restart(program, RestartPoint(PointKind.LINE, 7)).start_line == 7


def test_restart_on_an_arc_is_refused():
    program = ["G21 G17 G90 G54", "T1 M6", "S3000 M3", "G1 X0. Y0. F300.", "G2 X10. Y10. R10.",
               "X20. Y0. R10.", "G1 X30."]

    with pytest.raises(RestartRefused, match=r"line 6 moves on an arc \(G2\)"):
        plan_restart(program, RestartPoint(PointKind.LINE, 6))
    assert plan_restart(program, RestartPoint(PointKind.LINE, 7)).modal.motion == "G2"


def test_restart_after_a_g92_coordinate_setting_is_refused():
    program = ["G21 G17 G90", "T1 M6", "G92 X0. Y0. Z100.", "G0 X10."]

    with pytest.raises(RestartRefused, match="G92 at line 3 is in force at line 4"):
        plan_restart(program, RestartPoint(PointKind.LINE, 4))


def test_restart_after_the_program_end_is_refused():
    program = ["G21 G17 G90", "T1 M6", "M30", "G0 X0."]

    with pytest.raises(RestartRefused, match=r"after the end of the program \(M30 at line 3\)"):
        plan_restart(program, RestartPoint(PointKind.LINE, 4))


def test_a_program_that_does_not_say_mill_or_lathe_before_the_point_needs_the_kind():
    program = ["G21 G90", "G0 X10. Z5.", "G1 X20. F100."]

    with pytest.raises(RestartRefused, match="give the machine kind"):
        plan_restart(program, RestartPoint(PointKind.LINE, 3))
    assert plan_restart(program, RestartPoint(PointKind.LINE, 3),
                        machine_kind="mill").machine_kind is MachineKind.MILL


def test_crlf_lines_inch_units_g54_1_feed_per_rev_and_reverse_spindle_are_rebuilt():
    program = ["%\r\n", "O0042\r\n", "G20 G17 G90 G95\r\n", "T3 M6\r\n",
               "G54.1 P12 G0 X1. Y1. S900 M4\r\n", "G43 H3 Z1. M8 M7\r\n",
               "G1 Z-.1 F.004\r\n", "X2.\r\n"]

    plan = plan_restart(program, RestartPoint(PointKind.LINE, 8))

    assert plan.header == [MILL_SAFE, "G20", "G17", "G54.1 P12", "G90", "T3 M6", "G43 H3",
                           "S900 M4", "M7", "M8", "G95 F.004", "G1", *_tail(8, None, "G1")]


def test_a_configured_safe_start_opens_the_header():
    plan = plan_restart(_program("mill_bracket.nc"), RestartPoint(PointKind.BLOCK, 350),
                        safe_start=["G40 G49 G80 G69", "G91 G28 Z0."])

    assert plan.header[:3] == ["G40 G49 G80 G69", "G91 G28 Z0.", "G21"]


# Sending, and the memory a large program takes.

def test_stream_sends_the_header_then_the_program_from_the_start_line():
    plan = _plan("mill_bracket.nc", from_block="N480")
    lines = list(plan.stream(_program("mill_bracket.nc")))

    assert lines[:len(plan.header)] == plan.header
    assert [line.strip() for line in lines[len(plan.header):]] == [
        "N480 G91 G28 Z0.", "N490 G28 X0. Y0.", "N500 M30", "%"]


class _OnceOnly:
    """An iterable that can be iterated once, counting the lines taken from it."""

    def __init__(self, lines: Iterator[str]) -> None:
        self._lines = lines
        self.iterations = 0
        self.taken = 0

    def __iter__(self) -> Iterator[str]:
        self.iterations += 1
        assert self.iterations == 1, "iterated twice"
        for line in self._lines:
            self.taken += 1
            yield line


def _large_program(lines: int) -> Iterator[str]:
    """A generated mill program of `lines` lines: a tool change then straight cuts."""
    yield from ["%", "O9000 (GENERATED)", "G17 G21 G40 G49 G80 G90 G94", "T12 M6",
                "G54 G0 X0. Y0. S8000 M3", "G43 H12 Z5. M8", "G1 Z-1. F1500."]
    for n in itertools.count(8):
        if n > lines:
            return
        yield f"N{n} X{n % 997}.{n % 10} Y{n % 389}.5"


def test_a_two_million_line_program_is_scanned_once_in_constant_memory():
    program = _OnceOnly(_large_program(2_000_000))
    peak_before_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss

    plan = plan_restart(program, RestartPoint(PointKind.BLOCK, 1_999_990))

    assert plan.start_line == 1_999_990
    assert plan.header == [MILL_SAFE, "G21", "G17", "G54", "G90", "T12 M6", "G43 H12",
                           "S8000 M3", "M8", "G94 F1500.", "G1",
                           *_tail(1_999_990, 1_999_990, "G1")]
    assert program.iterations == 1
    assert program.taken == 1_999_990  # stops at the point: the rest is never read
    # Holding the lines would take some 170 MB (2,000,000 str objects); the scan keeps none.
    grown_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak_before_kib
    assert grown_kib < 30 * 1024
