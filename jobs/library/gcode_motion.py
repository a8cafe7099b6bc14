"""The geometry and timing of single moves: lines, rapids, arcs, accelerated or not.

Pure functions in millimetres, mm/min and seconds. A move with acceleration starts and
ends at rest (a trapezoid, or a triangle when it is too short to reach its speed): there is
no look-ahead, so a chain of short moves is estimated slower than a control with blending
would run it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

TAU = 2.0 * math.pi
_SAME_POINT_MM = 1e-6  # an arc that ends this close to its start is a full circle


def move_time_s(distance_mm: float, feed_mm_min: float, accel_mm_s2: float | None) -> float:
    """How long a move of `distance_mm` at `feed_mm_min` takes.

    Args:
        distance_mm: The path length.
        feed_mm_min: The programmed speed along the path.
        accel_mm_s2: The acceleration and deceleration, or `None` to ignore them.

    Returns:
        Seconds; 0 for no distance or no speed.
    """
    if distance_mm <= 0.0 or feed_mm_min <= 0.0:
        return 0.0
    speed_mm_s = feed_mm_min / 60.0
    if accel_mm_s2 is None or accel_mm_s2 <= 0.0:
        return distance_mm / speed_mm_s
    ramps_mm = speed_mm_s * speed_mm_s / accel_mm_s2  # up to speed and down again
    if distance_mm >= ramps_mm:
        return distance_mm / speed_mm_s + speed_mm_s / accel_mm_s2
    return 2.0 * math.sqrt(distance_mm / accel_mm_s2)  # a triangle: never reaches speed


def rapid_time_s(deltas_mm: Sequence[float], rates_mm_min: Sequence[float],
                 accel_mm_s2: float | None) -> float:
    """How long a rapid move takes when each axis runs at its own rate (Fanuc's default).

    Args:
        deltas_mm: The distance each axis travels.
        rates_mm_min: Each axis's rapid rate, in the same order.
        accel_mm_s2: The acceleration of every axis, or `None` to ignore it.

    Returns:
        Seconds: the time of the slowest axis.
    """
    return max((move_time_s(abs(delta), rate, accel_mm_s2)
                for delta, rate in zip(deltas_mm, rates_mm_min, strict=True)), default=0.0)


def distance_mm(deltas_mm: Iterable[float]) -> float:
    """The straight-line length of a move."""
    return math.sqrt(sum(delta * delta for delta in deltas_mm))


def arc_sweep_rad(start: tuple[float, float], end: tuple[float, float],
                  center: tuple[float, float], clockwise: bool) -> float:
    """The angle an arc turns through from `start` to `end` around `center`.

    Args:
        start: The start point in the arc's plane.
        end: The end point in the arc's plane.
        center: The centre in the arc's plane.
        clockwise: `G2` (True) or `G3` (False), seen from the plane's positive normal.

    Returns:
        Radians in (0, 2π]; an arc ending where it started is a full circle.
    """
    if math.dist(start, end) < _SAME_POINT_MM:
        return TAU
    start_rad = math.atan2(start[1] - center[1], start[0] - center[0])
    end_rad = math.atan2(end[1] - center[1], end[0] - center[0])
    sweep = (start_rad - end_rad) if clockwise else (end_rad - start_rad)
    sweep %= TAU
    return sweep if sweep > 0.0 else TAU


def center_from_radius(start: tuple[float, float], end: tuple[float, float], radius: float,
                       clockwise: bool) -> tuple[float, float] | None:
    """The centre of an `R` arc: a positive `R` takes the short way, a negative one the long.

    Args:
        start: The start point in the arc's plane.
        end: The end point in the arc's plane.
        radius: The programmed `R`, signed.
        clockwise: `G2` (True) or `G3` (False).

    Returns:
        The centre, or `None` when start and end coincide (an `R` arc cannot be a circle).
    """
    chord = math.dist(start, end)
    if chord < _SAME_POINT_MM or radius == 0.0:
        return None
    half = chord / 2.0
    size = max(abs(radius), half)  # a radius too small for the chord: a half circle
    offset = math.sqrt(size * size - half * half)
    mid_x, mid_y = (start[0] + end[0]) / 2.0, (start[1] + end[1]) / 2.0
    # unit normal to the chord, to the left of start→end
    normal_x, normal_y = -(end[1] - start[1]) / chord, (end[0] - start[0]) / chord
    # the short arc turning clockwise has its centre to the right of the chord
    left = (not clockwise) == (radius > 0.0)
    sign = 1.0 if left else -1.0
    return mid_x + sign * offset * normal_x, mid_y + sign * offset * normal_y


def arc_extremes(start: tuple[float, float], center: tuple[float, float], radius: float,
                 sweep_rad: float, clockwise: bool) -> list[tuple[float, float]]:
    """The points where an arc crosses its circle's axis extremes (0°, 90°, 180°, 270°).

    Args:
        start: The start point in the arc's plane.
        center: The centre.
        radius: The radius.
        sweep_rad: The angle turned through, from `arc_sweep_rad`.
        clockwise: The direction.

    Returns:
        The extreme points the arc passes through, for the toolpath extents.
    """
    start_rad = math.atan2(start[1] - center[1], start[0] - center[0])
    points = []
    for quarter in range(4):
        angle = quarter * math.pi / 2.0
        turned = ((start_rad - angle) if clockwise else (angle - start_rad)) % TAU
        if turned <= sweep_rad:
            points.append((center[0] + radius * math.cos(angle),
                           center[1] + radius * math.sin(angle)))
    return points
