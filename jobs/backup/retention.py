"""Which backups a retention policy keeps, with the semantics of `restic forget`.

Each rule is counted on its own over all backups, newest first, and a backup is kept
if any rule keeps it (borg differs: there, a backup kept by an earlier rule does not
count towards later ones). Days, ISO weeks and months are those of the given zone.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, fields
from datetime import UTC, datetime, tzinfo

BucketKey = Callable[[datetime], Hashable]

# Rule name -> what makes two backups fall in the same bucket (None: every backup is its own).
_BUCKETS: dict[str, BucketKey | None] = {
    "last": None,
    "daily": lambda t: t.date(),
    "weekly": lambda t: t.isocalendar()[:2],  # (ISO year, ISO week): 30 Dec 2024 is in 2025-W01
    "monthly": lambda t: (t.year, t.month),
}


@dataclass(frozen=True)
class RetentionPolicy:
    """How many backups each rule keeps; 0 turns a rule off, all 0 keeps everything.

    Attributes:
        keep_last: The newest N backups.
        keep_daily: The newest backup of each of the N most recent days that have backups.
        keep_weekly: The same per ISO week (Monday to Sunday).
        keep_monthly: The same per calendar month.
    """

    keep_last: int = 0
    keep_daily: int = 0
    keep_weekly: int = 0
    keep_monthly: int = 0

    def __post_init__(self) -> None:
        for field in fields(self):
            value = getattr(self, field.name)
            # bool is an int subclass; True as a count is almost certainly a mistake
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ValueError(f"{field.name} must be a whole number >= 0, not {value!r}")

    @property
    def keeps_everything(self) -> bool:
        """True when no rule is on, so nothing is ever pruned."""
        return not any(self.counts().values())

    def counts(self) -> dict[str, int]:
        """The count of each rule, by its short name (`last`, `daily`, `weekly`, `monthly`)."""
        return {name: getattr(self, f"keep_{name}") for name in _BUCKETS}

    @classmethod
    def parse(cls, text: str) -> RetentionPolicy:
        """Read a policy such as ``"last=3,daily=7,weekly=4,monthly=6"``.

        Rules may come in any order and any may be left out (it is then 0); spaces
        around names, values and commas are ignored.

        Raises:
            ValueError: The text is empty, or a part is not ``name=count`` with a known
                name, a whole count >= 0, and no name given twice.
        """
        known = ", ".join(_BUCKETS)
        if not text.strip():
            raise ValueError(f"empty retention policy; expected e.g. 'last=3,daily=7' ({known})")
        counts: dict[str, int] = {}
        for part in text.split(","):
            name, sep, value = (s.strip() for s in part.partition("="))
            if not sep or not name:
                raise ValueError(f"retention rule {part.strip()!r} is not of the form name=count")
            if name not in _BUCKETS:
                raise ValueError(f"unknown retention rule {name!r}; known rules: {known}")
            if name in counts:
                raise ValueError(f"retention rule {name!r} is given twice")
            if not value.isdecimal():
                raise ValueError(f"retention rule {name!r} needs a whole number >= 0, "
                                 f"not {value!r}")
            counts[name] = int(value)
        return cls(**{f"keep_{name}": count for name, count in counts.items()})


def to_keep(backups: Sequence[tuple[str, datetime]], policy: RetentionPolicy,
            tz: tzinfo = UTC) -> set[str]:
    """The ids of the backups the policy keeps.

    Args:
        backups: (id, when taken) pairs in any order; times must be time zone aware.
        policy: The rules; all 0 keeps every backup.
        tz: The zone whose calendar decides days, weeks and months.

    Raises:
        ValueError: A time has no time zone, so its day is unknown.
    """
    for backup_id, taken_at in backups:
        if taken_at.tzinfo is None or taken_at.utcoffset() is None:
            raise ValueError(f"backup {backup_id!r} has a time without a time zone: {taken_at}")
    if policy.keeps_everything:
        return {backup_id for backup_id, _ in backups}
    # Newest first; ties broken by id so the choice does not depend on input order.
    newest_first = sorted(backups, key=lambda b: (b[1], b[0]), reverse=True)
    kept: set[str] = set()
    for name, count in policy.counts().items():
        kept |= _keep_by_rule(newest_first, count, _BUCKETS[name], tz)
    return kept


def to_prune(backups: Sequence[tuple[str, datetime]], policy: RetentionPolicy,
             tz: tzinfo = UTC) -> set[str]:
    """The ids of the backups the policy does not keep; see `to_keep`."""
    return {backup_id for backup_id, _ in backups} - to_keep(backups, policy, tz)


def _keep_by_rule(newest_first: Sequence[tuple[str, datetime]], count: int,
                  bucket_of: BucketKey | None, tz: tzinfo) -> set[str]:
    """The newest backup of each of the `count` newest buckets (or the `count` newest)."""
    kept: set[str] = set()
    seen: set[Hashable] = set()
    for backup_id, taken_at in newest_first:
        if len(seen) >= count:
            break
        bucket: Hashable
        if bucket_of is not None:
            bucket = bucket_of(taken_at.astimezone(tz))
            if bucket in seen:
                continue  # an older backup of a bucket that already has its newest kept
        else:
            bucket = taken_at, backup_id
        seen.add(bucket)
        kept.add(backup_id)
    return kept
