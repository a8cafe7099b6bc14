"""The state of a program read line by line: modes, position, time tallies and summaries.

`Interpreter.read(line)` takes one line in; only the state in force and bounded summaries
are kept. Whether the program is a printer's is told by `jobs.library.gcode_dialect`;
`jobs.library.analysis` turns what it gathered into an `Analysis`.
"""

from __future__ import annotations

import math

from jobs.library.analysis_settings import AnalysisSettings, Dialect, MachineKind
from jobs.library.analysis_tally import RunningRange, Tally
from jobs.library.gcode_cycles import CANNED_CYCLES, Hole, hole_time
from jobs.library.gcode_dialect import names_a_slicer, printer_by_words
from jobs.library.gcode_motion import (
    arc_extremes,
    arc_sweep_rad,
    center_from_radius,
    distance_mm,
    move_time_s,
    rapid_time_s,
)
from jobs.library.gcode_words import Words, read_words

MM_PER_INCH = 25.4
MAX_NOTES = 20
MAX_COMMENT_CHARS = 200
MAX_CALL_DEPTH = 16  # Fanuc nests subprograms 4 to 10 deep; deeper is a loop
_AXES = ("X", "Y", "Z")
_PLANES = {17.0: (0, 1, 2), 18.0: (2, 0, 1), 19.0: (1, 2, 0)}  # first, second, normal axis
_CENTER_WORDS = ("I", "J", "K")
_NO_MOTION_G = frozenset({4.0, 10.0, 28.0, 30.0, 50.0, 52.0, 53.0, 65.0, 92.0})
_LATHE_CYCLES = frozenset({70.0, 71.0, 72.0, 73.0, 74.0, 75.0, 76.0, 90.0, 92.0, 94.0})


class Interpreter:
    """The state in force while the lines go by, and the summaries kept of them."""

    def __init__(self, settings: AnalysisSettings) -> None:
        self.settings = settings
        self.lathe = settings.machine is MachineKind.LATHE
        self.printer: bool | None = {Dialect.AUTO: None, Dialect.CNC: False,
                                     Dialect.PRINTER: True}[settings.dialect]
        self.rapid_rates = [settings.rapid_rate_mm_min(axis) for axis in _AXES]
        self.pos = [0.0, 0.0, 0.0]  # program coordinates, mm (a lathe's X is a diameter)
        self.scale = 1.0  # mm per program unit: 25.4 under G20
        self.absolute = True
        self.relative_e = False
        self.per_rev = False
        self.feed: float | None = None  # mm/min or mm/rev
        self.rpm = 0.0
        self.css_m_min: float | None = None  # G96 surface speed
        self.rpm_limit: float | None = None
        self.plane = _PLANES[18.0 if self.lathe else 17.0]
        self.motion = 0.0  # G0-G3, or a canned cycle's G code
        self.motion_before_cycle = 0.0  # what G80 goes back to
        self.cycle_r = self.cycle_z = self.initial_z = 0.0
        self.cycle_q = self.cycle_dwell_s = 0.0
        self.return_initial = True
        self.tool = 0
        self.e_now: dict[int, float] = {}  # extruder → E register
        self.e_total: dict[int, float] = {}
        self.e_most: dict[int, float] = {}
        self.lines = 0
        self.tools: dict[int, list[int]] = {}
        self.low = [math.inf] * 3
        self.high = [-math.inf] * 3
        self.feed_min, self.feed_rev, self.spindle = RunningRange(), RunningRange(), RunningRange()
        self.program_number: str | None = None
        self.program_name: str | None = None
        self.first_comment: str | None = None
        self.inch = False
        self.notes: dict[str, None] = {}
        self.unresolved: dict[str, None] = {}
        self.main = Tally()
        self.subs: dict[int, Tally] = {}
        self.tally: Tally | None = self.main  # where time goes now; None after the end
        self.main_ended = False

    def note(self, text: str) -> None:
        if len(self.notes) < MAX_NOTES:
            self.notes[text] = None

    def read(self, line: str) -> None:
        """Take one line into the state."""
        self.lines += 1
        words = read_words(line)
        if words.comments:
            if self.first_comment is None:
                self.first_comment = next(
                    (text[:MAX_COMMENT_CHARS] for text in words.comments if text), None)
            if self.printer is None and names_a_slicer(words.comments):
                self.printer = True
        if words.program_name and self.program_name is None:
            self.program_name = words.program_name
        if words.skipped:
            self.note(f"lines of {words.skipped} are not estimated")
            return
        if words.program_number is not None:
            self._program_start(words.program_number)
        if self.tally is None or not (words.g or words.m or words.values):
            return
        if self.printer is None:
            self.printer = printer_by_words(words)
        self._modes(words)
        self._words(words)
        self._motion(words)
        self._ends(words)

    def _program_start(self, number: str) -> None:
        """An O number: the program's own first, then each one starts a subprogram."""
        if self.program_number is None and not self.main_ended and not any(self.main.parts()):
            self.program_number = "O" + number
            return
        self.main_ended = True
        self.tally = self.subs.setdefault(int(number), Tally())

    def _modes(self, words: Words) -> None:
        """The modal G and M codes of the block, before its motion (Fanuc's order)."""
        for g in words.g:
            if g == 20.0:
                self.scale, self.inch = MM_PER_INCH, True
            elif g == 21.0:
                self.scale = 1.0
            elif g == 90.0 and not self.lathe:
                self.absolute = True
            elif g == 91.0 and not self.lathe:
                self.absolute = False
            elif g in _PLANES:
                self.plane = _PLANES[g]
            elif g in (94.0, 95.0) and not self.lathe:
                self.per_rev = g == 95.0
            elif g in (98.0, 99.0):
                if self.lathe:
                    self.per_rev = g == 99.0
                else:
                    self.return_initial = g == 98.0
            elif g == 96.0:
                self.css_m_min = 0.0
            elif g == 97.0:
                self.css_m_min = None
            elif g == 80.0:
                self.motion = self.motion_before_cycle
            elif g in (0.0, 1.0, 2.0, 3.0):
                self.motion = g
            elif g in CANNED_CYCLES and not self.lathe or g in (83.0, 84.0, 85.0):
                if self.motion not in CANNED_CYCLES:
                    self.initial_z = self.pos[2]
                    self.motion_before_cycle = self.motion
                self.motion = g
            elif self.lathe and g in _LATHE_CYCLES:
                self.note("lathe turning cycles (G70-G76, G90, G92, G94) are not estimated")
        if 82.0 in words.m and self.printer:
            self.relative_e = False
        elif 83.0 in words.m and self.printer:
            self.relative_e = True

    def _words(self, words: Words) -> None:
        """F, S and T words, dwells, position settings and tool changes."""
        values = words.values
        if "F" in values and values["F"] > 0.0:
            self.feed = values["F"] * (1.0 if self.printer else self.scale)
        if "S" in values and not self.printer:
            if any(g in (50.0, 92.0) for g in words.g):
                self.rpm_limit = values["S"]
            elif self.css_m_min is not None:
                self.css_m_min = values["S"] * (0.3048 if self.scale != 1.0 else 1.0)
            elif values["S"] > 0.0:
                self.rpm = values["S"]
                self.spindle.add(self.rpm)
        if "T" in values:
            self.tool = int(values["T"])
            seen = self.tools.setdefault(self.tool, [self.lines, self.lines])
            seen[1] = self.lines
        if 6.0 in words.m and not self.printer:
            self._add("tool_change_s", self.settings.tool_change_s)
        if 4.0 in words.g:
            self._add("dwell_s", self._dwell_s(words))
        if 92.0 in words.g and (self.printer or not self.lathe):
            self._set_position(words)
        elif 28.0 in words.g and self.printer:
            homed = [axis for axis in _AXES if axis in values] or list(_AXES)
            for axis in homed:
                self.pos[_AXES.index(axis)] = 0.0

    def _dwell_s(self, words: Words) -> float:
        """`G4`: X/U (and a printer's S) in seconds; P in milliseconds, or seconds when
        written with a decimal point on a CNC (Haas, Fanuc with decimal input)."""
        values = words.values
        if self.printer:
            return values.get("S", 0.0) + values.get("P", 0.0) / 1000.0
        if "X" in values or "U" in values:
            return values.get("X", values.get("U", 0.0))
        if "P" in values:
            return values["P"] if "P" in words.decimal else values["P"] / 1000.0
        return 0.0

    def _set_position(self, words: Words) -> None:
        values = words.values
        if not any(axis in values for axis in (*_AXES, "E")):
            if self.printer:
                self.pos = [0.0, 0.0, 0.0]
                self.e_now[self.tool] = 0.0
            return
        for index, axis in enumerate(_AXES):
            if axis in values:
                self.pos[index] = values[axis] * self.scale
        if "E" in values and self.printer:
            self.e_now[self.tool] = values["E"]

    def _motion(self, words: Words) -> None:
        """The block's move, in the motion mode now in force."""
        if any(g in _NO_MOTION_G for g in words.g) or (
                self.lathe and any(g in _LATHE_CYCLES for g in words.g)):
            return
        values = words.values
        target = list(self.pos)
        moved = False
        for index, axis in enumerate(_AXES):
            if axis in values:
                value = values[axis] * self.scale
                target[index] = value if self.absolute else self.pos[index] + value
                moved = True
        if self.lathe:
            for index, axis in ((0, "U"), (2, "W")):
                if axis in values:
                    target[index] = self.pos[index] + values[axis] * self.scale
                    moved = True
        extrude = self.printer and "E" in values and self.motion in (0.0, 1.0, 2.0, 3.0)
        if self.motion in CANNED_CYCLES:
            if moved or "R" in values:
                self._holes(words, target)
            return
        if not moved and not extrude:
            return
        e_mm = self._extrude(values["E"]) if extrude else 0.0
        if self.motion in (2.0, 3.0) and moved:
            self._arc(words, target, e_mm)
        elif self.motion == 0.0 and not self.printer:
            deltas = self._geometry_deltas(target)
            if self.settings.rapid_interpolated:
                seconds = move_time_s(distance_mm(deltas), self.settings.rapid_mm_min,
                                      self.settings.accel_mm_s2)
            else:
                seconds = rapid_time_s(deltas, self.rapid_rates, self.settings.accel_mm_s2)
            self._add("rapid_s", seconds)
        else:
            path_mm = max(distance_mm(self._geometry_deltas(target)), abs(e_mm))
            self._add("feed_s", move_time_s(path_mm, self._feed_mm_min(),
                                            self.settings.accel_mm_s2))
        if moved:
            self._reach(target)

    def _geometry_deltas(self, target: list[float]) -> list[float]:
        """Axis distances in mm; a lathe's X is a diameter, so its tool moves half."""
        deltas = [end - start for start, end in zip(self.pos, target, strict=True)]
        if self.lathe:
            deltas[0] /= 2.0
        return deltas

    def _reach(self, target: list[float]) -> None:
        for index in range(3):
            if target[index] < self.low[index]:
                self.low[index] = target[index]
            if target[index] > self.high[index]:
                self.high[index] = target[index]
        self.pos = target

    def _extrude(self, e_word: float) -> float:
        """Take one E word (M82/M83, G92 E) into the extruder's tally; the mm pushed."""
        now = self.e_now.get(self.tool, 0.0)
        delta = e_word if self.relative_e or not self.absolute else e_word - now
        self.e_now[self.tool] = now + delta
        total = self.e_total.get(self.tool, 0.0) + delta
        self.e_total[self.tool] = total
        self.e_most[self.tool] = max(self.e_most.get(self.tool, 0.0), total)
        return delta

    def _feed_mm_min(self) -> float:
        """The feed per minute of a feed move now, recorded in the feed ranges."""
        if self.feed is None:
            self.note("feed moves before any F run at the default feed")
            return self.settings.default_feed_mm_min
        if not self.per_rev:
            self.feed_min.add(self.feed)
            return self.feed
        self.feed_rev.add(self.feed)
        rpm = self._spindle_rpm()
        if rpm <= 0.0:
            self.note("feed per revolution without a spindle speed runs at the default feed")
            return self.settings.default_feed_mm_min
        return self.feed * rpm

    def _spindle_rpm(self) -> float:
        """The spindle speed now; under G96 from the surface speed at the current X."""
        if self.css_m_min is None:
            return self.rpm
        limit_rpm = self.rpm_limit or self.settings.max_spindle_rpm
        diameter_mm = abs(self.pos[0]) if self.lathe else 2.0 * abs(self.pos[0])
        if diameter_mm <= 0.0:
            return limit_rpm
        return min(limit_rpm, 1000.0 * self.css_m_min / (math.pi * diameter_mm))

    def _arc(self, words: Words, target: list[float], e_mm: float) -> None:
        """A G2/G3 arc (helical when the normal axis moves), by R or by I/J/K."""
        first, second, normal = self.plane
        half = 0.5 if self.lathe else 1.0  # the arc's geometry in radius values on a lathe
        factor = [half, 1.0, 1.0]
        start = (self.pos[first] * factor[first], self.pos[second] * factor[second])
        end = (target[first] * factor[first], target[second] * factor[second])
        clockwise = self.motion == 2.0
        values = words.values
        center: tuple[float, float] | None = None
        if "R" in values:
            center = center_from_radius(start, end, values["R"] * self.scale, clockwise)
        elif _CENTER_WORDS[first] in values or _CENTER_WORDS[second] in values:
            center = (start[0] + values.get(_CENTER_WORDS[first], 0.0) * self.scale,
                      start[1] + values.get(_CENTER_WORDS[second], 0.0) * self.scale)
        if center is None:
            self.note("arcs without a usable R or I/J/K are taken as straight lines")
            path_mm = distance_mm(self._geometry_deltas(target))
        else:
            radius_mm = math.dist(start, center)
            sweep_rad = arc_sweep_rad(start, end, center, clockwise)
            helix_mm = target[normal] - self.pos[normal]
            path_mm = math.hypot(radius_mm * sweep_rad, helix_mm)
            for point in arc_extremes(start, center, radius_mm, sweep_rad, clockwise):
                extreme = list(target)
                extreme[first] = point[0] / factor[first]
                extreme[second] = point[1] / factor[second]
                self._reach(extreme)
        seconds = move_time_s(max(path_mm, abs(e_mm)), self._feed_mm_min(),
                              self.settings.accel_mm_s2)
        self._add("feed_s", seconds)

    def _holes(self, words: Words, target: list[float]) -> None:
        """A block under a canned cycle: a hole at the target, repeated K (or L) times."""
        values = words.values
        if "R" in values:
            r_value = values["R"] * self.scale
            self.cycle_r = r_value if self.absolute else self.initial_z + r_value
        if "Z" in values:
            z_value = values["Z"] * self.scale
            self.cycle_z = z_value if self.absolute else self.cycle_r + z_value
        if "Q" in values:
            self.cycle_q = abs(values["Q"]) * self.scale
        if "P" in values:
            self.cycle_dwell_s = (values["P"] if "P" in words.decimal
                                  else values["P"] / 1000.0)
        repeats = int(values.get("K", values.get("L", 1.0)))
        step = [target[0] - self.pos[0], target[1] - self.pos[1]]
        for repeat in range(repeats):
            hole_xy = ([target[0], target[1]] if self.absolute or repeat == 0 else
                       [self.pos[0] + step[0], self.pos[1] + step[1]])
            over = [hole_xy[0], hole_xy[1], self.pos[2]]
            self._add("rapid_s", rapid_time_s(self._geometry_deltas(over), self.rapid_rates,
                                              self.settings.accel_mm_s2))
            self._reach(over)
            return_z = self.initial_z if self.return_initial else self.cycle_r
            hole = Hole(int(self.motion), self.pos[2], self.cycle_r, self.cycle_z, return_z,
                        self.cycle_q, self.settings.peck_clearance_mm, self.cycle_dwell_s)
            spent = hole_time(hole, feed_mm_min=self._feed_mm_min(),
                              rapid_z_mm_min=self.rapid_rates[2],
                              accel_mm_s2=self.settings.accel_mm_s2)
            self._add("rapid_s", spent.rapid_s)
            self._add("feed_s", spent.feed_s)
            self._add("dwell_s", spent.dwell_s)
            self._reach([hole_xy[0], hole_xy[1], min(self.cycle_z, self.cycle_r)])
            self._reach([hole_xy[0], hole_xy[1], return_z])

    def _ends(self, words: Words) -> None:
        """Subprogram calls and the ends of programs and subprograms."""
        values = words.values
        if (98.0 in words.m or 65.0 in words.g) and "P" in values and self.tally:
            number, repeats = int(values["P"]), int(values.get("L", values.get("K", 1.0)))
            if number > 9999 and "L" not in values and "K" not in values:
                repeats, number = divmod(number, 10000)  # Fanuc P□□□□○○○○: count, program
            if 65.0 in words.g:
                self.unresolved[f"O{number}"] = None
                self.note("G65 macro calls count 0 s")
            else:
                self.tally.calls[number] = self.tally.calls.get(number, 0) + max(repeats, 1)
        if 97.0 in words.m and "P" in values and not self.printer:
            self.unresolved[f"N{int(values['P'])}"] = None
            self.note("M97 local subroutine calls count 0 s")
        if any(m in (2.0, 30.0, 99.0) for m in words.m) and not self.printer:
            if self.tally is self.main:
                self.main_ended = True
            self.tally = None

    def _add(self, part: str, seconds: float) -> None:
        if self.tally is not None:
            setattr(self.tally, part, getattr(self.tally, part) + seconds)
