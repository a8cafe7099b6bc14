"""A moment as people read it: on this computer's clock, naming its zone (the CLI's tables
and the dashboard's pages say the same). Loads nothing but the standard library: the CLI
imports it at its start."""

from __future__ import annotations

from datetime import UTC, datetime

ZONE_NAME_AT_MOST = 5  # characters: CET, CEST, AEDT, +0530; a table column stays narrow
DATE = "%Y-%m-%d"


def local_text(moment: datetime, *, seconds: bool = False) -> str:
    """`2026-12-06 03:40 CET`: `moment` on the local clock, to the minute or the second, with
    its zone: in the hour the clocks go back, 02:30 CEST and 02:30 CET are an hour apart. A
    naive moment is taken as UTC, as the database keeps it."""
    date, clock = local_parts(moment, seconds=seconds)
    return f"{date} {clock}"


def local_parts(moment: datetime, *, seconds: bool = False) -> tuple[str, str]:
    """`("2026-12-06", "03:40 CET")`: the date and the clock of `local_text`, apart, for a
    page that keeps each whole on its line."""
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    moment = moment.astimezone()
    clock = "%H:%M:%S" if seconds else "%H:%M"
    return moment.strftime(DATE), f"{moment.strftime(clock)} {_zone(moment)}"


def _zone(moment: datetime) -> str:
    """The zone of a local time, short: its abbreviation (`CET`, `CEST`), or where the
    system names it at length (Windows: `W. Europe Standard Time`) its offset (`+0100`)."""
    name = moment.tzname() or ""
    if 0 < len(name) <= ZONE_NAME_AT_MOST and " " not in name:
        return name
    return moment.strftime("%z")
