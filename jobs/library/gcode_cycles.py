"""The time of one hole of a canned drilling cycle (G73, G74, G76, G81-G89), Fanuc style.

At each hole the tool rapids to the R plane, works down to Z as its cycle says, and goes
back to the initial level (`G98`) or to R (`G99`). Pecking (`G83` full retract to R, `G73`
chip-breaking retract) uses the clearance `d` of the control's parameters (Fanuc 5114/5115)
from the analysis settings; spindle stops, orientations and reversals take no time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from jobs.library.gcode_motion import move_time_s

# cycle → (feeds back out to R, dwells at the bottom)
_CYCLES: dict[int, tuple[bool, bool]] = {
    73: (False, False), 74: (True, True), 76: (False, True), 81: (False, False),
    82: (False, True), 83: (False, False), 84: (True, True), 85: (True, False),
    86: (False, False), 87: (False, True), 88: (False, True), 89: (True, True),
}
CANNED_CYCLES = frozenset(_CYCLES)


@dataclass(frozen=True, slots=True)
class Hole:
    """One hole: where the cycle works along Z, and how.

    Attributes:
        cycle: The G code (81 for G81).
        start_z_mm: Where Z is when the tool arrives over the hole.
        r_mm: The R plane.
        bottom_z_mm: The hole's bottom (the cycle's Z).
        return_z_mm: Where Z ends: the initial level (G98) or R (G99).
        peck_mm: The peck depth `Q` of G73/G83, or 0 for one pass.
        clearance_mm: The peck clearance or retract `d`.
        dwell_s: The dwell `P` at the bottom, in seconds.
    """

    cycle: int
    start_z_mm: float
    r_mm: float
    bottom_z_mm: float
    return_z_mm: float
    peck_mm: float
    clearance_mm: float
    dwell_s: float


class HoleTime(NamedTuple):
    """A hole's time, split as the analysis reports it."""

    rapid_s: float
    feed_s: float
    dwell_s: float


def hole_time(hole: Hole, *, feed_mm_min: float, rapid_z_mm_min: float,
              accel_mm_s2: float | None) -> HoleTime:
    """How long one hole of a canned cycle takes, from its arrival over the hole.

    Args:
        hole: The hole.
        feed_mm_min: The cycle's feed.
        rapid_z_mm_min: The Z axis's rapid rate.
        accel_mm_s2: The acceleration, or `None` to ignore it.

    Returns:
        The rapid, feed and dwell seconds.
    """
    feeds_out, dwells = _CYCLES[hole.cycle]
    depth_mm = abs(hole.r_mm - hole.bottom_z_mm)
    rapids_mm = [abs(hole.start_z_mm - hole.r_mm)]
    feeds_mm = []
    if hole.cycle in (73, 83) and 0.0 < hole.peck_mm < depth_mm:
        pecks = math.ceil(depth_mm / hole.peck_mm)
        clearance_mm = min(hole.clearance_mm, hole.peck_mm)
        for peck in range(1, pecks):
            reached_mm = peck * hole.peck_mm
            feeds_mm.append(hole.peck_mm + (clearance_mm if peck > 1 else 0.0))
            if hole.cycle == 83:  # out to R, back down to just above the last depth
                rapids_mm += [reached_mm, reached_mm - clearance_mm]
            else:  # G73: back by d only, then feeds on from there
                rapids_mm.append(clearance_mm)
        feeds_mm.append(depth_mm - (pecks - 1) * hole.peck_mm + clearance_mm)
    else:
        feeds_mm.append(depth_mm)
    if feeds_out:
        feeds_mm.append(depth_mm)
        rapids_mm.append(abs(hole.r_mm - hole.return_z_mm))
    else:
        rapids_mm.append(abs(hole.bottom_z_mm - hole.return_z_mm))
    return HoleTime(
        rapid_s=sum(move_time_s(mm, rapid_z_mm_min, accel_mm_s2) for mm in rapids_mm),
        feed_s=sum(move_time_s(mm, feed_mm_min, accel_mm_s2) for mm in feeds_mm),
        dwell_s=hole.dwell_s if dwells else 0.0,
    )
