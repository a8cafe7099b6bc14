"""The per-machine options of the program analysis: rapid rates, acceleration, dialect."""

from __future__ import annotations

import hashlib
from enum import StrEnum

from pydantic import BaseModel, ConfigDict, NonNegativeFloat, PositiveFloat


class Dialect(StrEnum):
    """How a program's codes are read."""

    AUTO = "auto"  # printer when printer codes show up (M104, M82, G1 … E…), else CNC
    CNC = "cnc"  # ISO G-code of a mill or lathe: G0 at the rapid rate, E ignored
    PRINTER = "printer"  # Marlin/Klipper: G0 at the feed like G1, E is the extruder


class MachineKind(StrEnum):
    """Which ISO reading applies to a CNC program."""

    MILL = "mill"  # G94/G95 feed modes, G98/G99 drilling return levels, U/V/W extra axes
    LATHE = "lathe"  # Fanuc system A: G98/G99 feed modes, X in diameter, U/W incremental


class AnalysisSettings(BaseModel):
    """What the analysis assumes of the machine a program runs on.

    Attributes:
        rapid_mm_min: The rapid rate of every axis.
        rapid_axis_mm_min: Rapid rates of single axes that differ (`{"Z": 15000}`).
        rapid_interpolated: Rapids move in a straight line at `rapid_mm_min` instead of
            each axis at its own rate (Fanuc parameter 1401 bit 1, LRP).
        accel_mm_s2: The acceleration of every move (a trapezoid from rest to rest), or
            `None` to ignore acceleration.
        default_feed_mm_min: The feed of feed moves before any `F` is given.
        dialect: CNC or printer G-code, or told apart by the codes (`auto`).
        machine: Mill or lathe reading of CNC programs.
        max_spindle_rpm: The spindle's top speed, the limit of `G96` constant surface
            speed when the program sets none (`G50 S`, `G92 S`).
        peck_clearance_mm: The `d` of pecking cycles (Fanuc parameters 5114/5115).
        tool_change_s: The time of one `M6` tool change.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    rapid_mm_min: PositiveFloat = 10_000.0
    rapid_axis_mm_min: dict[str, PositiveFloat] = {}
    rapid_interpolated: bool = False
    accel_mm_s2: PositiveFloat | None = None
    default_feed_mm_min: PositiveFloat = 1_000.0
    dialect: Dialect = Dialect.AUTO
    machine: MachineKind = MachineKind.MILL
    max_spindle_rpm: PositiveFloat = 6_000.0
    peck_clearance_mm: NonNegativeFloat = 1.0
    tool_change_s: NonNegativeFloat = 0.0

    def rapid_rate_mm_min(self, axis: str) -> float:
        """The rapid rate of one axis (`"X"`, `"Y"`, `"Z"`)."""
        return self.rapid_axis_mm_min.get(axis, self.rapid_mm_min)

    def digest(self) -> str:
        """A short digest of these settings, stored with each analysis made with them."""
        return hashlib.sha256(self.model_dump_json().encode()).hexdigest()[:16]
