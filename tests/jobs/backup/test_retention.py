"""jobs.backup.retention: which backups a policy keeps, and how a policy is written."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from zoneinfo import ZoneInfo

import pytest

from jobs.backup.retention import RetentionPolicy, to_keep, to_prune


def at(text: str) -> datetime:
    """A UTC time from 'YYYY-MM-DD HH:MM'."""
    return datetime.strptime(text, "%Y-%m-%d %H:%M").replace(tzinfo=UTC)


def sixty_nights_and_manual_runs() -> list[tuple[str, datetime]]:
    """Nightly backups at 02:00 UTC from 2024-01-11 to 2024-03-10, plus four manual ones."""
    first = at("2024-01-11 02:00")
    nightly = [(f"nightly-{(first + timedelta(days=n)):%Y-%m-%d}", first + timedelta(days=n))
               for n in range(60)]
    manual = [
        ("manual-2023-12-20", at("2023-12-20 12:00")),  # a month before the nightly ones
        ("manual-2024-02-17", at("2024-02-17 11:00")),  # Saturday, older than Sunday's nightly
        ("manual-2024-02-25", at("2024-02-25 20:00")),  # Sunday, after the nightly of that day
        ("manual-2024-03-09", at("2024-03-09 18:30")),
        ("manual-2024-03-10", at("2024-03-10 15:00")),  # the newest of all
    ]
    return nightly + manual


def test_retention_keeps_the_right_set_over_60_simulated_days() -> None:
    backups = sixty_nights_and_manual_runs()
    assert backups[-6][0] == "nightly-2024-03-10"  # the 60 nights end on Sunday 10 March
    policy = RetentionPolicy.parse("last=2,daily=7,weekly=4,monthly=3")

    kept = to_keep(backups, policy)

    # Worked out by hand from the calendar (10 March 2024 is a Sunday, ISO week 10).
    expected_last = {"manual-2024-03-10", "nightly-2024-03-10"}
    expected_daily = {
        "manual-2024-03-10",  # Sun 10 Mar
        "manual-2024-03-09",  # Sat 9 Mar: the manual run at 18:30 is newer than the nightly
        "nightly-2024-03-08", "nightly-2024-03-07", "nightly-2024-03-06",
        "nightly-2024-03-05", "nightly-2024-03-04",
    }
    expected_weekly = {
        "manual-2024-03-10",  # week 10 (4-10 Mar)
        "nightly-2024-03-03",  # week 9 (26 Feb-3 Mar)
        "manual-2024-02-25",  # week 8 (19-25 Feb): Sunday's manual run at 20:00
        "nightly-2024-02-18",  # week 7 (12-18 Feb): Sunday's nightly beats Saturday's manual
    }
    expected_monthly = {"manual-2024-03-10", "nightly-2024-02-29", "nightly-2024-01-31"}
    expected = expected_last | expected_daily | expected_weekly | expected_monthly
    assert len(expected) == 13
    assert kept == expected
    assert to_prune(backups, policy) == {backup_id for backup_id, _ in backups} - expected
    assert {"nightly-2024-03-09", "nightly-2024-02-25", "manual-2024-02-17",
            "manual-2023-12-20"} <= to_prune(backups, policy)


def test_a_backup_at_2330_utc_counts_on_the_next_day_in_berlin() -> None:
    backups = [
        ("late", at("2024-03-09 23:30")),  # 00:30 on 10 March in Berlin (UTC+1)
        ("morning", at("2024-03-10 10:00")),
        ("noon-before", at("2024-03-09 12:00")),
    ]
    two_days = RetentionPolicy(keep_daily=2)

    assert to_keep(backups, two_days, tz=UTC) == {"morning", "late"}
    assert to_keep(backups, two_days, tz=ZoneInfo("Europe/Berlin")) == {"morning", "noon-before"}


def test_weekly_uses_iso_weeks_across_the_new_year() -> None:
    backups = [
        ("mon-2024-12-30", at("2024-12-30 02:00")),  # ISO 2025-W01, like 1 January
        ("wed-2025-01-01", at("2025-01-01 02:00")),
        ("sun-2024-12-29", at("2024-12-29 02:00")),  # ISO 2024-W52
    ]

    assert to_keep(backups, RetentionPolicy(keep_weekly=2)) == {"wed-2025-01-01",
                                                                 "sun-2024-12-29"}


def test_keep_last_keeps_the_newest_whatever_the_input_order() -> None:
    backups = [("b", at("2024-01-02 02:00")), ("c", at("2024-01-03 02:00")),
               ("a", at("2024-01-01 02:00"))]

    assert to_keep(backups, RetentionPolicy(keep_last=2)) == {"b", "c"}


def test_a_rule_keeps_what_there_is_when_there_are_fewer_backups_than_its_count() -> None:
    backups = [("a", at("2024-01-01 02:00")), ("b", at("2024-01-01 03:00"))]

    assert to_keep(backups, RetentionPolicy(keep_monthly=12)) == {"b"}


def test_all_zero_policy_keeps_everything() -> None:
    backups = sixty_nights_and_manual_runs()

    assert to_keep(backups, RetentionPolicy()) == {backup_id for backup_id, _ in backups}
    assert to_keep(backups, RetentionPolicy.parse("last=0,daily=0")) == {
        backup_id for backup_id, _ in backups}
    assert to_prune(backups, RetentionPolicy()) == set()


def test_no_backups_keep_nothing() -> None:
    assert to_keep([], RetentionPolicy(keep_last=3)) == set()


def test_a_time_without_a_time_zone_is_refused() -> None:
    with pytest.raises(ValueError, match="'naive' has a time without a time zone"):
        to_keep([("naive", datetime(2024, 1, 1, 2, 0))], RetentionPolicy(keep_last=1))


def test_parse_reads_every_rule_in_any_order_with_spaces() -> None:
    assert RetentionPolicy.parse(" monthly=6 , last=3,daily = 7,weekly=4") == RetentionPolicy(
        keep_last=3, keep_daily=7, keep_weekly=4, keep_monthly=6)


def test_parse_leaves_unnamed_rules_off() -> None:
    assert RetentionPolicy.parse("daily=7") == RetentionPolicy(keep_daily=7)


@pytest.mark.parametrize(("text", "message"), [
    ("", "empty retention policy"),
    ("   ", "empty retention policy"),
    ("hourly=3", "unknown retention rule 'hourly'; known rules: last, daily, weekly, monthly"),
    ("daily", "retention rule 'daily' is not of the form name=count"),
    ("=3", "retention rule '=3' is not of the form name=count"),
    ("daily=7,", "retention rule '' is not of the form name=count"),
    ("daily=seven", "retention rule 'daily' needs a whole number >= 0, not 'seven'"),
    ("daily=-1", "retention rule 'daily' needs a whole number >= 0, not '-1'"),
    ("daily=1.5", "retention rule 'daily' needs a whole number >= 0, not '1.5'"),
    ("daily=7,daily=3", "retention rule 'daily' is given twice"),
])
def test_parse_errors_raise_value_error_saying_what_is_wrong(text: str, message: str) -> None:
    with pytest.raises(ValueError) as raised:
        RetentionPolicy.parse(text)
    assert message in str(raised.value)


def test_a_negative_count_is_refused() -> None:
    with pytest.raises(ValueError, match="keep_weekly must be a whole number >= 0, not -2"):
        RetentionPolicy(keep_weekly=-2)
