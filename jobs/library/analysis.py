"""The analysis of a stored program: cycle time, tools, extents, ranges, filament.

`analyse(lines)` reads the program's lines once, in order, and keeps only the state in
force and bounded summaries (tools, ranges, one tally per subprogram), so a 2 GB program
is read in constant memory. ISO G-code (Fanuc, Haas, Siemens ISO mode) and printer G-code
(Marlin/Klipper) are read; what it estimates, how, and its limits are in docs/analysis.md.

Parser libraries: gcodeparser (MIT, maintained) parses a whole string at once with one
regular expression, drops blocks without a G/M/T word (modal `X10 Y20` lines, the bulk of
CNC programs) and knows no parenthesised comments or O numbers; pygcode is GPLv3 (this
project is MIT), has had no release since 2017 and reads LinuxCNC's dialect. Neither
streams nor knows Fanuc's canned cycles or subprograms, so the words are read here
(`gcode_words`), the modes followed in `gcode_interpreter`, the geometry computed in
`gcode_motion` and drilling in `gcode_cycles`.
"""

from __future__ import annotations

from collections.abc import Iterable

from jobs.library.analysis_result import (
    ANALYSER_VERSION,
    Analysis,
    Extents,
    ToolUse,
    ValueRange,
    format_duration,
    format_filament,
)
from jobs.library.analysis_settings import AnalysisSettings, Dialect, MachineKind
from jobs.library.analysis_tally import resolve_calls
from jobs.library.gcode_interpreter import MAX_CALL_DEPTH, Interpreter

__all__ = ["ANALYSER_VERSION", "Analysis", "AnalysisSettings", "Dialect", "Extents",
           "MachineKind", "ToolUse", "ValueRange", "analyse", "format_duration",
           "format_filament"]


def analyse(lines: Iterable[str], *, settings: AnalysisSettings | None = None) -> Analysis:
    """Analyse one program, reading its lines once.

    Args:
        lines: The program's text lines, in order (a file opened in text mode will do).
        settings: What to assume of the machine; the defaults when `None`.

    Returns:
        The analysis.
    """
    interpreter = Interpreter(settings or AnalysisSettings())
    for line in lines:
        interpreter.read(line)
    return _result(interpreter)


def _result(state: Interpreter) -> Analysis:
    """The analysis of everything the interpreter read."""
    parts, calls, missing = resolve_calls(state.main, state.subs, max_depth=MAX_CALL_DEPTH)
    rapid_s, feed_s, dwell_s, tool_change_s = parts
    state.unresolved.update(dict.fromkeys(f"O{number}" for number in missing))
    if state.unresolved:
        state.note("unresolved subprogram calls count 0 s")
    extents = None
    if state.low[0] <= state.high[0]:
        extents = Extents(state.low[0], state.high[0], state.low[1], state.high[1],
                          state.low[2], state.high[2])
    return Analysis(
        analyser_version=ANALYSER_VERSION, settings_digest=state.settings.digest(),
        dialect="printer" if state.printer else "cnc", lines=state.lines,
        cycle_time_s=rapid_s + feed_s + dwell_s + tool_change_s, rapid_time_s=rapid_s,
        feed_time_s=feed_s, dwell_time_s=dwell_s, tool_change_time_s=tool_change_s,
        tools=tuple(ToolUse(number, first, last)
                    for number, (first, last) in state.tools.items()),
        extents=extents, feed_mm_min=state.feed_min.result(),
        feed_mm_rev=state.feed_rev.result(),
        spindle_rpm=state.spindle.result() if not state.printer else None,
        program_number=state.program_number, program_name=state.program_name,
        first_comment=state.first_comment, inch=state.inch,
        filament_mm=sum(state.e_most.values()) if state.printer else None,
        subprogram_calls=calls, unresolved_subprograms=tuple(sorted(state.unresolved)),
        notes=tuple(state.notes),
    )
