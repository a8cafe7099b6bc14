"""A cron's fire times in a time zone, across the clocks' changes, as cron(8) runs them.

croniter only walks the wall clock here (naive times, the same in every version dncq
allows); which instant each wall time is, is reckoned below with the zone's offsets, since
croniter's own handling of a zone changed from version to version (before 6.2 an hourly
schedule lost the repeated hour and 02:30 ran at 03:30 on the night the clocks go forward).

A schedule limited to some hours (`30 2 * * *`, `0 1-3 * * *`) runs at fixed times, as cron
runs them: a time the clocks skip when they go forward runs as they change (02:30 at 03:00),
and a time they repeat when they go back runs once, the first time; so a nightly backup
runs once each of those nights. One that runs in every hour (`0 * * * *`, `*/15 * * * *`,
`@hourly`) runs by the clock: in the repeated hour again, and not in the hour that never
comes, so an hourly one runs once in each real hour.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from zoneinfo import ZoneInfo

from croniter import croniter

SCAN_STEP = timedelta(hours=6)  # no zone changes its offset twice within this
LOOK_BACK = timedelta(hours=3)  # more than any change of a zone's offset (2 h at most)
SECOND = timedelta(seconds=1)
HOURS_A_DAY = 24


@functools.lru_cache(maxsize=256)
def at_fixed_times(cron: str) -> bool:
    """Whether the schedule is limited to some hours of the day (not `*`, `0-23`, `@hourly`)."""
    hours = croniter(cron).expanded[1]
    return hours != ["*"] and len(set(hours)) < HOURS_A_DAY


def fires_after(cron: str, zone: ZoneInfo, start: datetime) -> Iterator[datetime]:
    """The schedule's fire times (UTC) after `start`, in order, each once."""
    fixed = at_fixed_times(cron)
    last = start  # everything given is later
    since = start  # where the stretch of one UTC offset being walked starts
    wall_from = _wall(start, zone) - SECOND  # a time at `start` is named, and `last` drops it
    while True:
        offset = _offset(since, zone)
        walk = croniter(cron, wall_from)
        while True:
            wall = walk.get_next(datetime)
            fire = (wall - offset).replace(tzinfo=UTC)
            change = _first_change(zone, since, fire, offset)
            if change is not None:
                break
            if fire > last and not (fixed and _second_pass(fire, zone)):
                yield fire
                last = fire
            since = fire
        new_offset = _offset(change, zone)
        # `wall` is the first time named after the old clock's last; one the clocks jump over
        skipped = wall < (change + new_offset).replace(tzinfo=None)
        if fixed and new_offset > offset and skipped:
            yield change  # a fixed time the clocks skip runs as they change
            last = change
        since = change
        wall_from = (change + new_offset).replace(tzinfo=None) - SECOND


def next_fire(cron: str, zone: ZoneInfo, start: datetime) -> datetime:
    """The schedule's first fire time (UTC) after `start`."""
    return next(fires_after(cron, zone, start))


def last_fire(cron: str, zone: ZoneInfo, now: datetime) -> datetime:
    """The schedule's latest fire time (UTC) at or before `now`."""
    # From a wall time the cron names a few hours back, forward: which instant a wall time is
    # depends on the offsets around it, so the times are not walked backwards.
    earlier = _wall(now, zone) - LOOK_BACK
    while True:
        earlier = croniter(cron, earlier).get_prev(datetime)
        latest = None
        for fire in fires_after(cron, zone, earlier.replace(tzinfo=zone).astimezone(UTC)
                                - LOOK_BACK):
            if fire > now:
                break
            latest = fire
        if latest is not None:
            return latest
        # None in reach (that time the clocks skipped, of a schedule that runs by the clock,
        # and no other since): from the time before it.


def on_the_clock(instant: datetime, zone: ZoneInfo) -> str:
    """`2026-12-07 02:00`, `instant` as the zone's clock shows it; in the hour the clocks go
    through twice, which of the two it is (`2026-10-25 02:00 CEST`, then `02:00 CET`)."""
    local = instant.astimezone(zone)
    shown = f"{local:%Y-%m-%d %H:%M}"
    if local.replace(fold=1 - local.fold).utcoffset() != local.utcoffset():
        shown += f" {local:%Z}"
    return shown


def _wall(instant: datetime, zone: ZoneInfo) -> datetime:
    """The zone's wall clock at `instant`, naive."""
    return instant.astimezone(zone).replace(tzinfo=None, fold=0)


def _offset(instant: datetime, zone: ZoneInfo) -> timedelta:
    offset = instant.astimezone(zone).utcoffset()
    assert offset is not None
    return offset


def _second_pass(fire: datetime, zone: ZoneInfo) -> bool:
    """Whether `fire` is the second time the wall clock shows its time (clocks went back)."""
    return fire.astimezone(zone).fold == 1  # set only for the later of two equal times


def _first_change(zone: ZoneInfo, since: datetime, until: datetime,
                  offset: timedelta) -> datetime | None:
    """The first instant in (since, until] at which the zone's offset is no longer `offset`
    (to the second: zones change on whole seconds), or None."""
    low = since
    while low < until:
        high = min(low + SCAN_STEP, until)
        if _offset(high, zone) != offset:
            while high - low > SECOND:
                middle = low + (high - low) / 2
                if _offset(middle, zone) == offset:
                    low = middle
                else:
                    high = middle
            whole = high.replace(microsecond=0)
            return whole if whole > low else high
        low = high
    return None
