"""What the analysis of one program found, as stored (JSON) and as the listing shows it.

`Analysis` is frozen and round-trips through `to_json()`/`from_json()`; `ANALYSER_VERSION`
changes whenever the same program would be analysed differently, so that stored analyses
with an older version are recomputed. The formatters give the seed listing's strings:
`estimatedPrintTime` as `"HH:mm:ss"` and `filament` as `"0.79m"`.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from typing import Any

ANALYSER_VERSION = 2  # 2: a CR alone or LF CR ends a line too


@dataclass(frozen=True, slots=True)
class ToolUse:
    """One tool the program calls.

    Attributes:
        number: The `T` number as a number (`T0101` is 101).
        first_line: The first line (1-based) with this `T` word.
        last_line: The last line with this `T` word.
    """

    number: int
    first_line: int
    last_line: int


@dataclass(frozen=True, slots=True)
class Extents:
    """The box the programmed toolpath stays in, in millimetres, program coordinates."""

    min_x_mm: float
    max_x_mm: float
    min_y_mm: float
    max_y_mm: float
    min_z_mm: float
    max_z_mm: float


@dataclass(frozen=True, slots=True)
class ValueRange:
    """The least and the greatest of the values a program uses."""

    min: float
    max: float


@dataclass(frozen=True, slots=True)
class Analysis:
    """The analysis of one program.

    Attributes:
        analyser_version: `ANALYSER_VERSION` when it was made.
        settings_digest: A digest of the `AnalysisSettings` it was made with.
        dialect: `"cnc"` or `"printer"` (Marlin/Klipper G-code).
        lines: How many lines were read.
        cycle_time_s: The estimated run time: every part below, plus resolved subprograms.
        rapid_time_s: The part spent in rapid moves (CNC `G0`; a printer has none).
        feed_time_s: The part spent in feed moves (`G1`-`G3`, drilling feeds).
        dwell_time_s: The part spent in dwells (`G4`, `P` of drilling cycles).
        tool_change_time_s: The part spent in tool changes (`M6`), from the settings.
        tools: The tools called, in the order of their first line.
        extents: The toolpath's box, or `None` when nothing moved.
        feed_mm_min: The range of feeds per minute used by feed moves.
        feed_mm_rev: The range of feeds per revolution (`G95`, lathe `G99`).
        spindle_rpm: The range of spindle speeds in rpm (`S` under `G97`; CNC only).
        program_number: The first `O` number as written (`"O1234"`).
        program_name: A Siemens (`%_N_NAME_MPF`) or Heidenhain (`BEGIN PGM NAME`) name.
        first_comment: The program's first non-empty comment.
        inch: Whether the program switched to inch input (`G20`) anywhere.
        filament_mm: For printer G-code: the filament pushed, in millimetres (the most the
            extruder was ever ahead, so that a final retraction does not count).
        subprogram_calls: How many `M98` calls were resolved (repeats counted).
        unresolved_subprograms: The programs called that the file does not hold
            (`"O2000"`); each such call counts 0 s.
        notes: What the estimate left out or guessed, one short sentence each.
    """

    analyser_version: int
    settings_digest: str
    dialect: str
    lines: int
    cycle_time_s: float
    rapid_time_s: float
    feed_time_s: float
    dwell_time_s: float
    tool_change_time_s: float
    tools: tuple[ToolUse, ...]
    extents: Extents | None
    feed_mm_min: ValueRange | None
    feed_mm_rev: ValueRange | None
    spindle_rpm: ValueRange | None
    program_number: str | None
    program_name: str | None
    first_comment: str | None
    inch: bool
    filament_mm: float | None
    subprogram_calls: int
    unresolved_subprograms: tuple[str, ...]
    notes: tuple[str, ...]

    def to_json(self) -> str:
        """The analysis as a JSON object, for storing."""
        return json.dumps(asdict(self), separators=(",", ":"), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> Analysis:
        """An analysis back from `to_json()`'s text.

        Raises:
            ValueError: The text is not a stored analysis.
        """
        try:
            data: dict[str, Any] = json.loads(text)
            data["tools"] = tuple(ToolUse(**tool) for tool in data["tools"])
            data["extents"] = Extents(**data["extents"]) if data["extents"] else None
            for name in ("feed_mm_min", "feed_mm_rev", "spindle_rpm"):
                data[name] = ValueRange(**data[name]) if data[name] else None
            data["unresolved_subprograms"] = tuple(data["unresolved_subprograms"])
            data["notes"] = tuple(data["notes"])
            return cls(**data)
        except (TypeError, KeyError, json.JSONDecodeError) as exc:
            raise ValueError(f"not a stored analysis: {exc}") from exc

    @property
    def estimated_print_time(self) -> str:
        """The cycle time as the seed's `estimatedPrintTime`: `"HH:mm:ss"`."""
        return format_duration(self.cycle_time_s)

    @property
    def filament(self) -> str | None:
        """The filament as the seed's `filament` (`"0.79m"`), or `None` for CNC programs."""
        return None if self.filament_mm is None else format_filament(self.filament_mm)


def format_duration(seconds: float) -> str:
    """`"HH:mm:ss"`, rounded to the second; hours go past 24 (`"27:03:10"`)."""
    total_s = max(0, round(seconds))
    hours, rest_s = divmod(total_s, 3600)
    minutes, secs = divmod(rest_s, 60)
    return f"{hours:02d}:{minutes:02d}:{secs:02d}"


def format_filament(length_mm: float) -> str:
    """Metres with two decimals and `m`, as the seed writes it: 790 mm is `"0.79m"`."""
    return f"{length_mm / 1000.0:.2f}m"
