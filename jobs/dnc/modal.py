"""The modal state of a mill or lathe program, followed block by block, and where it is unsure.

A `ModalScanner` reads blocks in order and keeps only the state in force (constant memory),
plus what would make a restart at the next block unsafe: an open canned cycle, a subprogram
body, cutter compensation, macro statements, coordinate shifts it cannot rebuild, a
subprogram call whose effect it cannot see. Lathes are read in Fanuc G-code system A (the
default): G90/G92/G94 are turning cycles, U/W incremental axes, G98/G99 the feed modes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from enum import StrEnum

from jobs.dnc.blocks import Block, BlockKind


class MachineKind(StrEnum):
    """How a program's codes are read."""

    MILL = "mill"  # machining centre: T… M6 tool changes, G43 H length offsets, G90/G91
    LATHE = "lathe"  # turning centre, system A: T0303 turret calls, G96/G97, G50 S, G98/G99


@dataclass(slots=True)
class ModalState:
    """The modal state in force at a block; `None` where the program has not set it yet.

    Codes are kept as the header writes them (`"G54.1 P3"`, `"S1200"`, `"F.25"`).
    """

    units: str | None = None  # G20 inch, G21 mm
    plane: str | None = None  # G17, G18, G19
    work_offset: str | None = None  # G54…G59, G54.1 Pn
    distance: str | None = None  # mill: G90 absolute, G91 incremental
    tool: int | None = None  # the tool number in the spindle or turret position
    tool_word: str | None = None  # the T word that selected it, as written: T7, T0303
    length_offset: str | None = None  # mill: "G43 H7", "G44 H7" or "G49"
    spindle_mode: str | None = None  # lathe: G96 constant surface speed, G97 rpm
    speed_clamp: str | None = None  # lathe: "G50 S2000", the rpm limit under G96
    spindle_speed: str | None = None  # "S1200" (rpm, or m/min / ft/min under G96)
    spindle: str | None = None  # M3, M4, M5
    coolant: tuple[str, ...] | None = None  # ("M8",), ("M7", "M8"); () after M9
    feed_mode: str | None = None  # mill G94/G95, lathe G98/G99 (per minute / per rev)
    feed: str | None = None  # "F250.", "F.2"
    motion: str | None = None  # G0, G1, G2, G3, threading; lathe G90/G92/G94 cycles
    cutter_comp: str | None = None  # G40, G41, G42
    canned_cycle: str | None = None  # the modal drilling cycle in force (G81…), until G80


_FIELD_NAMES = {
    "units": "units", "plane": "plane", "work_offset": "work offset",
    "distance": "absolute/incremental", "tool": "tool", "length_offset": "length offset",
    "spindle_mode": "spindle mode", "speed_clamp": "spindle speed clamp",
    "spindle_speed": "spindle speed", "spindle": "spindle direction", "coolant": "coolant",
    "feed_mode": "feed mode", "feed": "feed", "motion": "motion mode",
    "cutter_comp": "cutter compensation", "canned_cycle": "canned cycle",
}
_MILL_FIELDS = frozenset(_FIELD_NAMES) - {"spindle_mode", "speed_clamp"}
_LATHE_FIELDS = frozenset(_FIELD_NAMES) - {"distance", "length_offset"}

_MILL_MOTION = frozenset({"0", "1", "2", "3", "33"})
_LATHE_MOTION = frozenset({"0", "1", "2", "3", "32"})
_LATHE_TURNING_CYCLES = frozenset({"90", "92", "94"})  # system A, group 01: modal
_MILL_CYCLES = frozenset({"73", "74", "76", "81", "82", "83", "84", "85", "86", "87", "88", "89"})
_LATHE_DRILL_CYCLES = frozenset({"81", "82", "83", "84", "85", "86", "87", "88", "89"})
_LATHE_CONTOUR_CYCLES = frozenset({"71", "72", "73"})  # a P…Q contour follows
_LATHE_TWO_BLOCK_CYCLES = frozenset({"74", "75", "76"})  # a parameter block, then X/Z
_ARCS = frozenset({"G2", "G3"})
_AXES = ("X", "Y", "Z", "U", "V", "W")
# Modes whose effect a restart cannot rebuild, and why, until the code that ends them.
_UNSURE_WHY = {
    "G92": "it sets coordinates from where the tool stood then, which a restart cannot rebuild",
    "G50": "G50 X/Z sets coordinates from where the tool stood then, which a restart "
           "cannot rebuild",
    "G52": "a local coordinate shift is not rebuilt by a restart",
    "G68": "coordinate rotation is not rebuilt by a restart",
    "G51": "scaling is not rebuilt by a restart",
    "G51.1": "programmable mirror image is not rebuilt by a restart",
}


def kind_evidence(block: Block) -> MachineKind | None:
    """The machine kind a block's codes can only belong to, if any."""
    g, v = block.g, block.values
    if "6" in block.m or "H" in v or not {"43", "44", "49", "17", "19", "54.1"}.isdisjoint(g):
        return MachineKind.MILL
    tool = v.get("T", "")
    if ("96" in g or ("50" in g and "S" in v) or "U" in v or "W" in v
            or (len(tool) == 4 and tool.isdigit())
            or ({"70", "71", "72"} & set(g) and "P" in v and "Q" in v)):
        return MachineKind.LATHE
    return None


@dataclass(slots=True)
class _OpenCycle:
    """A lathe multi-block cycle whose blocks are still being read."""

    code: str  # G71…G76
    line: int  # its first block
    last_n: str | None = None  # contour cycles: the Q block that ends the contour


class ModalScanner:
    """Follows one program's modal state for one machine kind, a block at a time."""

    def __init__(self, kind: MachineKind) -> None:
        """Start at the top of a program, nothing set."""
        self.kind = kind
        self.state = ModalState()
        self._fields = _MILL_FIELDS if kind is MachineKind.MILL else _LATHE_FIELDS
        self._motion_codes = _MILL_MOTION if kind is MachineKind.MILL else _LATHE_MOTION
        self._pending_tool: str | None = None  # mill: the T word waiting for its M6
        self._comp_line = 0
        self._cycle_line = 0
        self._lathe_cycle: _OpenCycle | None = None
        self._unsure: dict[str, int] = {}  # code → line it took effect
        self._macro: tuple[int, str] | None = None
        self._unreadable: tuple[int, str] | None = None
        self._call: tuple[int, str] | None = None  # the last subprogram call
        self._unknown: set[str] = set()  # fields the last call may have changed
        self._seen_program = False
        self._subprogram: tuple[int, str] | None = None  # (line of O…, O…) until M99
        self._ended_at: tuple[int, str] | None = None  # (line, M30/M2/M99) of the main end

    def tool_change(self, block: Block) -> tuple[int, str] | None:
        """The tool number and T word a block changes to, if it changes the tool."""
        if block.kind is not BlockKind.PLAIN:
            return None
        digits = block.values.get("T")
        if self.kind is MachineKind.MILL:
            if "6" not in block.m:
                return None
            digits = digits or self._pending_tool
            return None if digits is None else (int(digits), "T" + digits)
        if digits is None or not digits.isdigit():
            return None
        number = int(digits[:-2]) if len(digits) > 2 else int(digits)
        return (number, "T" + digits) if number else None

    def refusal(self, line_no: int, block: Block) -> str | None:
        """Why the program cannot be restarted at this block, or None if it can.

        Reads the state before the block is applied: call it, then `apply` the block.
        """
        state = self.state
        if self._macro or block.kind is BlockKind.MACRO or {"65", "66"} & set(block.g):
            at, text = self._macro or (line_no, block.text)
            return (f"line {at} uses macro statements ({text}): variables, macro calls and "
                    "branching make the modal state at the restart point unknowable")
        if self._unreadable or block.kind is not BlockKind.PLAIN:
            at, text = self._unreadable or (line_no, block.text)
            return f"line {at} is not a block this scan can read ({text})"
        if self._subprogram or ("O" in block.values and self._seen_program):
            at, name = self._subprogram or (line_no, "O" + block.values["O"])
            return (f"line {line_no} is inside subprogram {name} (from line {at} to its M99): "
                    "the modal state it runs in is set by the program that calls it")
        if self._ended_at:
            at, code = self._ended_at
            return f"line {line_no} is after the end of the program ({code} at line {at})"
        motion_here = [c for c in block.g if c in self._motion_codes
                       or (self.kind is MachineKind.LATHE and c in _LATHE_TURNING_CYCLES)]
        if state.canned_cycle and not motion_here and "80" not in block.g and not (
                self._cycle_codes() & set(block.g)):
            return (f"line {line_no} is inside the {state.canned_cycle} canned cycle started at "
                    f"line {self._cycle_line}: restart from line {self._cycle_line}, or after "
                    "the cycle ends")
        if self._lathe_cycle:
            cycle = self._lathe_cycle
            contour = f" (its contour ends at N{cycle.last_n})" if cycle.last_n else ""
            return (f"line {line_no} is inside the G{cycle.code} cycle started at line "
                    f"{cycle.line}{contour}: restart from line {cycle.line}")
        if state.cutter_comp in ("G41", "G42") and not {"40", "41", "42"} & set(block.g):
            return (f"cutter radius compensation {state.cutter_comp} (from line "
                    f"{self._comp_line}) is active at line {line_no}: restart from a block "
                    "that cancels or starts it")
        for code, at in self._unsure.items():
            return f"{code} at line {at} is in force at line {line_no}: {_UNSURE_WHY[code]}"
        if self._unknown:
            at, text = self._call or (0, "")
            names = ", ".join(_FIELD_NAMES[f] for f in _FIELD_NAMES if f in self._unknown)
            return (f"{text} at line {at} calls a subprogram this scan cannot follow, and the "
                    f"program does not set its {names} again before line {line_no}")
        motion = next((f"G{c}" for c in reversed(motion_here)), state.motion)
        if motion in _ARCS:
            return (f"line {line_no} moves on an arc ({motion}), which starts where the block "
                    "before it ended: restart from a block in G0 or G1")
        return None

    def apply(self, line_no: int, block: Block) -> None:
        """Apply one block to the state."""
        if block.kind is BlockKind.MACRO and not self._macro:
            self._macro = (line_no, block.text)
        if block.kind is not BlockKind.PLAIN:
            if not self._unreadable and block.kind is not BlockKind.MACRO:
                self._unreadable = (line_no, block.text)
            return
        g, m, v = block.g, block.m, block.values
        if {"65", "66"} & set(g) and not self._macro:
            self._macro = (line_no, block.text)
        if "O" in v:
            if self._seen_program or self._ended_at:
                self._subprogram = (line_no, "O" + v["O"])
            self._seen_program = True
        if self._lathe_cycle_step(line_no, block):
            return
        change = self.tool_change(block)
        if self.kind is MachineKind.MILL and "T" in v:
            self._pending_tool = v["T"]
        if change:
            self._set("tool", change[0])
            self._set("tool_word", change[1])
            if self.kind is MachineKind.MILL:
                # Fanuc builders' M6 macros cancel G43 and stop the spindle; the program
                # gives the new tool its own G43 H and M3.
                self._set("length_offset", "G49")
                self._set("spindle", "M5")
        for code in g:
            self._apply_g(line_no, code, block)
        offset = self.state.length_offset or ""
        if "H" in v and offset.startswith(("G43", "G44")) and not {"43", "44"} & set(g):
            self._set("length_offset", f"{offset[:3]} H{v['H']}")  # a new H, same G43/G44
        if "S" in v:
            if self.kind is MachineKind.LATHE and "50" in g:
                self._set("speed_clamp", f"G50 S{v['S']}")
            else:
                self._set("spindle_speed", f"S{v['S']}")
        if "F" in v:
            self._set("feed", f"F{v['F']}")
        for code in m:
            self._apply_m(line_no, code, block)

    def _apply_g(self, line_no: int, code: str, block: Block) -> None:
        """Apply one G code of a block."""
        mill = self.kind is MachineKind.MILL
        v = block.values
        if code in self._motion_codes or (not mill and code in _LATHE_TURNING_CYCLES):
            self._set("motion", f"G{code}")
            self._set("canned_cycle", None)  # a group 01 code ends a drilling cycle
            if not mill and code in _LATHE_TURNING_CYCLES:
                self._set("canned_cycle", f"G{code}")
                self._cycle_line = line_no
        elif code in self._cycle_codes():
            self._set("canned_cycle", f"G{code}")
            self._cycle_line = line_no
        elif code == "80":
            self._set("canned_cycle", None)
        elif code in ("20", "21"):
            self._set("units", f"G{code}")
        elif code in ("17", "18", "19"):
            self._set("plane", f"G{code}")
        elif code in ("54", "55", "56", "57", "58", "59"):
            self._set("work_offset", f"G{code}")
        elif code == "54.1":
            self._set("work_offset", f"G54.1 P{v.get('P', '1')}")
        elif code in ("40", "41", "42"):
            self._set("cutter_comp", f"G{code}")
            self._comp_line = line_no
        elif mill and code in ("90", "91"):
            self._set("distance", f"G{code}")
        elif mill and code in ("43", "44"):
            number = v.get("H") or (self.state.length_offset or "").partition(" H")[2]
            self._set("length_offset", f"G{code} H{number}" if number else f"G{code}")
        elif mill and code == "49":
            self._set("length_offset", "G49")
        elif (mill and code in ("94", "95")) or (not mill and code in ("98", "99")):
            self._set("feed_mode", f"G{code}")
        elif not mill and code in ("96", "97"):
            self._set("spindle_mode", f"G{code}")
        else:
            self._apply_coordinates_g(line_no, code, block)

    def _apply_coordinates_g(self, line_no: int, code: str, block: Block) -> None:
        """Codes that shift, rotate, scale or mirror coordinates."""
        if self.kind is MachineKind.LATHE:
            if code == "50" and any(a in block.values for a in ("X", "Z", "U", "W")):
                self._unsure.setdefault("G50", line_no)
            return
        ends = {"69": "G68", "50": "G51", "50.1": "G51.1"}
        if code in ("92", "68", "51", "51.1"):
            self._unsure.setdefault(f"G{code}", line_no)
        elif code in ends:
            self._unsure.pop(ends[code], None)
        elif code == "52":
            if any(float(block.values.get(a, "0")) for a in _AXES):
                self._unsure["G52"] = line_no
            else:
                self._unsure.pop("G52", None)

    def _apply_m(self, line_no: int, code: str, block: Block) -> None:
        """Apply one M code of a block."""
        if code in ("3", "4", "5"):
            self._set("spindle", f"M{code}")
        elif code in ("7", "8"):
            # After an unseen call, the other coolant is taken as off: the program chose.
            known = () if "coolant" in self._unknown else (self.state.coolant or ())
            self._set("coolant", tuple(sorted({*known, f"M{code}"})))
        elif code == "9":
            self._set("coolant", ())
        elif code in ("98", "198"):
            self._call = (line_no, block.text)
            self._unknown = set(self._fields)
        elif code in ("30", "2"):
            if not self._subprogram:
                self._ended_at = (line_no, f"M{code}")
        elif code == "99":
            if self._subprogram:
                self._subprogram = None
            else:
                self._ended_at = (line_no, "M99")

    def _lathe_cycle_step(self, line_no: int, block: Block) -> bool:
        """Open, advance or close a lathe multi-block cycle (G71…G76).

        Returns:
            Whether the block is part of a G71–G73 contour: data the cycle reads, not a
            block run in its turn (the control goes on after the contour's last block).
        """
        if self.kind is not MachineKind.LATHE:
            return False
        cycle = self._lathe_cycle
        v = block.values
        if cycle and cycle.last_n is not None:
            number = v.get("N", "")
            if number.isdigit() and int(number) == int(float(cycle.last_n)):
                self._lathe_cycle = None  # the contour's last block
            return True
        codes = [c for c in block.g if c in _LATHE_CONTOUR_CYCLES | _LATHE_TWO_BLOCK_CYCLES]
        if not codes:
            return False
        code = codes[-1]
        line = cycle.line if cycle and cycle.code == code else line_no
        if code in _LATHE_CONTOUR_CYCLES:
            if "P" in v and "Q" in v:
                self._lathe_cycle = _OpenCycle(code, line, v["Q"])
            else:
                self._lathe_cycle = _OpenCycle(code, line)
        elif any(a in v for a in ("X", "Z", "U", "W")):
            self._lathe_cycle = None  # the second block: the cycle runs here and ends
        else:
            self._lathe_cycle = _OpenCycle(code, line)
        return False

    def _cycle_codes(self) -> frozenset[str]:
        return _MILL_CYCLES if self.kind is MachineKind.MILL else _LATHE_DRILL_CYCLES

    def _set(self, name: str, value: object) -> None:
        setattr(self.state, name, value)
        self._unknown.discard(name)

    def snapshot(self) -> ModalState:
        """A copy of the state in force now."""
        return dataclasses.replace(self.state)
