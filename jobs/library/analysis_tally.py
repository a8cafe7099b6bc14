"""Running summaries of a program's analysis: time per program body, value ranges, calls.

Each body (the main program, each `O` subprogram in the same file) keeps its own time and
the calls it makes; `resolve_calls` adds the called bodies' time at the end, since a
subprogram usually comes after the program that calls it.
"""

from __future__ import annotations

import math

from jobs.library.analysis_result import ValueRange


class Tally:
    """The time of one program body (the main program or one subprogram) and its calls."""

    __slots__ = ("rapid_s", "feed_s", "dwell_s", "tool_change_s", "calls")

    def __init__(self) -> None:
        self.rapid_s = self.feed_s = self.dwell_s = self.tool_change_s = 0.0
        self.calls: dict[int, int] = {}  # program number → times called

    def parts(self) -> list[float]:
        return [self.rapid_s, self.feed_s, self.dwell_s, self.tool_change_s]


class RunningRange:
    """A running minimum and maximum."""

    __slots__ = ("low", "high")

    def __init__(self) -> None:
        self.low, self.high = math.inf, -math.inf

    def add(self, value: float) -> None:
        if value < self.low:
            self.low = value
        if value > self.high:
            self.high = value

    def result(self) -> ValueRange | None:
        return ValueRange(self.low, self.high) if self.low <= self.high else None


def resolve_calls(main: Tally, bodies: dict[int, Tally], *,
                  max_depth: int) -> tuple[list[float], int, set[int]]:
    """The time of `main` with the time of every subprogram it calls, nested.

    Args:
        main: The main program's tally.
        bodies: The subprograms found in the file, by number.
        max_depth: Calls nested deeper than this count 0 s, as do calls that loop back.

    Returns:
        The parts of `Tally.parts()` in total, how many calls were resolved (repeats
        counted), and the numbers of the programs called that could not be resolved.
    """
    memo: dict[int, list[float]] = {}
    resolved = [0]
    missing: set[int] = set()

    open_bodies: set[int] = set()  # the calls being resolved: one of them again is a loop

    def total(tally: Tally, depth: int) -> list[float]:
        parts = tally.parts()
        for number, times in tally.calls.items():
            body = bodies.get(number)
            if body is None or depth >= max_depth or number in open_bodies:
                missing.add(number)
                continue
            resolved[0] += times
            if number not in memo:
                open_bodies.add(number)
                memo[number] = total(body, depth + 1)
                open_bodies.discard(number)
            parts = [mine + times * theirs
                     for mine, theirs in zip(parts, memo[number], strict=True)]
        return parts

    return total(main, 0), resolved[0], missing
