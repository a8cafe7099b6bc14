"""The analysis of CNC programs against times worked out by hand from each test's geometry.

Each reference is plain arithmetic on the program in the test (path length over feed, or
distance over rapid rate), written out in the docstring; the tolerance is 0.01 s unless a
test says otherwise, since the model and the hand figure are the same arithmetic.
"""

from __future__ import annotations

import itertools
import math
import tracemalloc
from collections.abc import Iterator

import pytest

from jobs.library.analysis import (
    ANALYSER_VERSION,
    Analysis,
    AnalysisSettings,
    ToolUse,
    analyse,
    format_duration,
    format_filament,
)

TOLERANCE_S = 0.01


def run(text: str, **settings: object) -> Analysis:
    return analyse(text.strip().splitlines(), settings=AnalysisSettings(**settings))


SQUARE = """
O1234 (SQUARE 100 MM)
G21 G90 G17 G94
T1 M6
G0 X0 Y0 Z0
G1 X100 F500
Y100
X0
Y0
M30
"""


def test_square_of_100_mm_at_f500_takes_48_s() -> None:
    """400 mm at 500 mm/min = 0.8 min = 48 s; the G0 goes nowhere from the origin."""
    analysis = run(SQUARE)
    assert analysis.cycle_time_s == pytest.approx(48.0, abs=TOLERANCE_S)
    assert analysis.feed_time_s == pytest.approx(48.0, abs=TOLERANCE_S)
    assert analysis.feed_mm_min is not None and analysis.feed_mm_min.max == 500.0


def test_full_circle_of_r10_by_ijk_at_f300() -> None:
    """An arc ending where it starts is a circle: 2π·10 mm / 300 mm/min = 12.566 s."""
    analysis = run("G17 G90 G0 X10 Y0 Z0\nG2 X10 Y0 I-10 J0 F300\nM30")
    assert analysis.feed_time_s == pytest.approx(2 * math.pi * 10 / 300 * 60, abs=TOLERANCE_S)
    assert analysis.extents is not None
    assert (analysis.extents.min_x_mm, analysis.extents.max_y_mm) == pytest.approx((-10, 10))


def test_two_half_circles_by_r_make_a_circle() -> None:
    """Two G3 R10 half circles: 2 · π·10 mm at 300 mm/min = 12.566 s."""
    analysis = run("G17 G90 G0 X10 Y0\nG3 X-10 Y0 R10 F300\nG3 X10 Y0 R10\nM30")
    assert analysis.feed_time_s == pytest.approx(2 * math.pi * 10 / 300 * 60, abs=TOLERANCE_S)


def test_negative_r_takes_the_long_way_round() -> None:
    """G3 from (0,0) to (10,10) with R-10 turns 270°: 1.5π·10 mm at 600 mm/min = 4.712 s."""
    analysis = run("G17 G90 G0 X0 Y0\nG3 X10 Y10 R-10 F600\nM30")
    assert analysis.feed_time_s == pytest.approx(1.5 * math.pi * 10 / 600 * 60, abs=TOLERANCE_S)


def test_helix_adds_its_lead_to_the_arc() -> None:
    """A circle of R10 dropping 5 mm: √((2π·10)² + 5²) mm at 300 mm/min."""
    analysis = run("G17 G90 G0 X10 Y0 Z0\nG2 X10 Y0 Z-5 I-10 F300\nM30")
    expected_s = math.hypot(2 * math.pi * 10, 5) / 300 * 60
    assert analysis.feed_time_s == pytest.approx(expected_s, abs=TOLERANCE_S)


DRILLING = """
G17 G21 G90 G94
G0 X0 Y0 Z25
G98 G81 X0 Y0 R2 Z-10 F100
X20
X40
G80
M30
"""


def test_drilling_pattern_returns_to_the_initial_level_under_g98() -> None:
    """Three holes from Z25, R2, Z-10 at F100: each feeds 12 mm (7.2 s) and rapids 23 mm
    down and 35 mm up; with the 25 mm first rise and two 20 mm steps, all at 10,000 mm/min:
    21.6 s of feed and (25 + 3·58 + 40)/10000·60 = 1.434 s of rapid."""
    analysis = run(DRILLING)
    assert analysis.feed_time_s == pytest.approx(21.6, abs=TOLERANCE_S)
    assert analysis.rapid_time_s == pytest.approx((25 + 3 * 58 + 40) / 10_000 * 60,
                                                  abs=TOLERANCE_S)
    assert analysis.extents is not None and analysis.extents.min_z_mm == -10.0


def test_g99_returns_to_the_r_plane_between_holes() -> None:
    """Under G99 each hole rises only to R2: the first falls 23 mm, the others 0; each rises
    12 mm: (25 + 23 + 3·12 + 40)/10000·60 = 0.744 s of rapid."""
    analysis = run(DRILLING.replace("G98", "G99"))
    assert analysis.rapid_time_s == pytest.approx((25 + 23 + 36 + 40) / 10_000 * 60,
                                                  abs=TOLERANCE_S)


def test_g83_pecks_back_to_r_each_time() -> None:
    """R2 to Z-10 by Q4 is three pecks; with d = 1 mm: 12 + 2·1 mm fed at F100 (8.4 s) and
    4 up, 3 down, 8 up, 7 down, then 12 up to the initial level: 34 mm of rapid."""
    analysis = run("G90 G0 X0 Y0 Z2\nG98 G83 R2 Z-10 Q4 F100\nG80\nM30",
                   peck_clearance_mm=1.0)
    assert analysis.feed_time_s == pytest.approx(8.4, abs=TOLERANCE_S)
    assert analysis.rapid_time_s == pytest.approx((2 + 34) / 10_000 * 60, abs=TOLERANCE_S)


def test_g82_dwells_p_milliseconds_at_each_hole() -> None:
    """G82 P500 at two holes: 2 · 0.5 s of dwell."""
    analysis = run("G90 G0 X0 Y0 Z5\nG82 R1 Z-3 P500 F60\nX10\nG80\nM30")
    assert analysis.dwell_time_s == pytest.approx(1.0)


def test_dwell_p_is_milliseconds_unless_written_with_a_point_and_x_is_seconds() -> None:
    """G4 P1500 = 1.5 s, G4 X2. = 2 s, G4 P2.5 = 2.5 s (Haas, Fanuc decimal input)."""
    analysis = run("G4 P1500\nG4 X2.\nG4 P2.5\nM30")
    assert analysis.dwell_time_s == pytest.approx(6.0)


def test_feed_per_revolution_needs_the_spindle_speed() -> None:
    """G95 F0.1 at S1000 is 100 mm/min: 100 mm take 60 s."""
    analysis = run("G21 G90 G95 S1000 M3\nG0 X0 Y0\nG1 X100 F0.1\nM30")
    assert analysis.feed_time_s == pytest.approx(60.0, abs=TOLERANCE_S)
    assert analysis.feed_mm_rev is not None and analysis.feed_mm_rev.min == 0.1
    assert analysis.spindle_rpm is not None and analysis.spindle_rpm.max == 1000.0


def test_lathe_x_is_a_diameter_and_g99_is_per_revolution() -> None:
    """Lathe system A: facing from X50 to X0 moves 25 mm; at G99 F0.2 and G97 S500 that is
    100 mm/min, so 15 s; then 100 mm along Z at the same feed, 60 s."""
    analysis = run("G18 G21 G99 G97 S500 M3\nG0 X50 Z0\nG1 X0 F0.2\nG0 X50\nG1 Z-100\nM30",
                   machine="lathe")
    assert analysis.feed_time_s == pytest.approx(75.0, abs=TOLERANCE_S)


def test_inch_program_is_measured_in_millimetres() -> None:
    """G20: a 4 in square at F20 in/min is 16 in / 20 in/min = 48 s; extents in mm."""
    analysis = run("G20 G90 G0 X0 Y0\nG1 X4 F20\nY4\nX0\nY0\nM30")
    assert analysis.cycle_time_s == pytest.approx(48.0, abs=TOLERANCE_S)
    assert analysis.inch
    assert analysis.extents is not None and analysis.extents.max_x_mm == pytest.approx(101.6)


def test_incremental_square_ends_where_it_started() -> None:
    """G91: the same 100 mm square by steps takes 48 s and spans 100 mm from X10 Y10."""
    analysis = run("G90 G0 X10 Y10\nG91 G1 X100 F500\nY100\nX-100\nY-100\nM30")
    assert analysis.feed_time_s == pytest.approx(48.0, abs=TOLERANCE_S)
    assert analysis.extents is not None
    assert (analysis.extents.min_x_mm, analysis.extents.max_x_mm) == (10.0, 110.0)


def test_rapid_takes_its_longest_axis_or_a_straight_line() -> None:
    """G0 X100 Y50 at 10,000 mm/min: 0.6 s when each axis runs alone (X is longest), and
    √(100² + 50²)/10000·60 = 0.671 s interpolated; a Z at 5,000 mm/min: 50 mm take 0.6 s."""
    assert run("G0 X100 Y50").rapid_time_s == pytest.approx(0.6)
    interpolated = run("G0 X100 Y50", rapid_interpolated=True)
    assert interpolated.rapid_time_s == pytest.approx(math.hypot(100, 50) / 10_000 * 60)
    assert run("G0 X10 Z50", rapid_axis_mm_min={"Z": 5000}).rapid_time_s == pytest.approx(0.6)


def test_acceleration_adds_a_ramp_or_makes_a_triangle() -> None:
    """100 mm at 6000 mm/min (100 mm/s) with 1000 mm/s²: 1 s + 100/1000 s = 1.1 s; a 1 mm
    move never reaches speed: 2·√(1/1000) s."""
    assert run("G1 X100 F6000", accel_mm_s2=1000).feed_time_s == pytest.approx(1.1)
    assert run("G1 X1 F6000", accel_mm_s2=1000).feed_time_s == pytest.approx(2 * math.sqrt(1e-3))


SUBPROGRAMS = """
%
O1000 (MAIN)
G21 G90 G94
G0 X0 Y0 Z0
M98 P2000 L2
M98 P32000
M98 P9999
M30
O2000 (SQUARE 100 BY STEPS)
G91 G1 X100 F500
Y100
X-100
Y-100
G90
M99
%
"""


def test_subprograms_in_the_file_are_resolved_and_repeated() -> None:
    """O2000 is a 48 s square, called twice by L2 and three times by P32000 (Fanuc's count
    in the leading digits): 5 · 48 s; O9999 is not in the file and counts 0 s."""
    analysis = run(SUBPROGRAMS)
    assert analysis.cycle_time_s == pytest.approx(240.0, abs=TOLERANCE_S)
    assert analysis.subprogram_calls == 5
    assert analysis.unresolved_subprograms == ("O9999",)
    assert analysis.program_number == "O1000"


def test_subprogram_calling_itself_is_unresolved_not_endless() -> None:
    """A subprogram calling itself counts once, its call to itself 0 s."""
    analysis = run("O1\nM98 P2\nM30\nO2\nG1 X10 F600\nM98 P2\nM99")
    assert analysis.cycle_time_s == pytest.approx(1.0)
    assert analysis.unresolved_subprograms == ("O2",)


def test_program_number_and_first_comment() -> None:
    """The first O number as written, and the first non-empty comment."""
    analysis = run("%\n()\nO0010 (BRACKET OP1)\n; second\nM30")
    assert (analysis.program_number, analysis.first_comment) == ("O0010", "BRACKET OP1")


def test_siemens_and_heidenhain_names() -> None:
    """`%_N_PART1_MPF` and `0 BEGIN PGM PLATE MM` name their programs."""
    assert run("%_N_PART1_MPF\n;$PATH=/_N_MPF_DIR\nG0 X1\nM30").program_name == "PART1"
    assert run("0 BEGIN PGM PLATE MM\n1 L X+10 FMAX\n2 END PGM PLATE MM").program_name == "PLATE"


def test_tools_with_their_first_and_last_lines() -> None:
    """T1 on lines 1 and 5, T2 on line 3, in the order first called."""
    analysis = run("T1 M6\nG0 X1\nT2 M6\nG0 X2\nT1 M6\nM30")
    assert analysis.tools == (ToolUse(1, 1, 5), ToolUse(2, 3, 3))


def test_tool_changes_take_the_configured_time() -> None:
    """Two M6 at 4 s each."""
    assert run("T1 M6\nT2 M6\nM30", tool_change_s=4).tool_change_time_s == pytest.approx(8.0)


def test_unknown_words_and_macro_lines_are_not_fatal() -> None:
    """Macro statements are skipped with a note; unknown addresses are ignored."""
    analysis = run("#100=5\nIF[#100GT3]GOTO10\nG1 X60 F600 Q7 @3\nG65 P9810 A1\nM30")
    assert analysis.feed_time_s == pytest.approx(6.0)
    assert "O9810" in analysis.unresolved_subprograms
    assert any("macro" in note for note in analysis.notes)


def test_nothing_after_the_end_of_the_program_counts() -> None:
    """Blocks after M30 that belong to no subprogram are not run."""
    assert run("G1 X60 F600\nM30\nG1 X0").feed_time_s == pytest.approx(6.0)


def test_analysis_round_trips_through_json_and_formats_the_seed_strings() -> None:
    """`to_json`/`from_json` give back an equal analysis; 1900 s is "00:31:40" and 790 mm of
    filament "0.79m", the seed's example values."""
    analysis = run(SUBPROGRAMS)
    assert Analysis.from_json(analysis.to_json()) == analysis
    assert analysis.analyser_version == ANALYSER_VERSION
    assert format_duration(1900) == "00:31:40"
    assert format_duration(27 * 3600 + 190) == "27:03:10"
    assert format_filament(790) == "0.79m"
    assert analysis.estimated_print_time == "00:04:00" and analysis.filament is None


def test_settings_digest_tells_settings_apart() -> None:
    """An analysis records which settings made it."""
    assert run(SQUARE).settings_digest != run(SQUARE, rapid_mm_min=20_000).settings_digest


_BODY = tuple(f"G1 X{index % 100}.5 Y{(index * 7) % 50}.25 Z-1. F{500 + index % 3}\n"
              for index in range(300))


def _long_program(lines: int) -> Iterator[str]:
    """A program of `lines` lines, made as it is read (the same 300 feed moves over and over,
    so that the generator itself allocates nothing per line)."""
    yield "O5000 (GENERATED)\n"
    yield from itertools.islice(itertools.cycle(_BODY), lines - 2)
    yield "M30\n"


@pytest.mark.slow  # tracemalloc traces every allocation: about 20 s
def test_a_long_program_is_read_without_holding_it() -> None:
    """200,000 lines (about 7 MB of text) with a peak of traced allocations under 100 kB
    (it is about 10 kB): the lines are consumed one at a time and never kept, so the
    2 GB programs of a drip-feed are analysed in the same memory."""
    tracemalloc.start()
    try:
        analysis = analyse(_long_program(200_000))
        _, peak_bytes = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert analysis.lines == 200_000
    assert analysis.feed_mm_min is not None and analysis.feed_mm_min.max == 502.0
    assert peak_bytes < 100_000
