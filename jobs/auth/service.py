"""Users and named API keys: made, changed, removed, listed; sign-in with its lock-out; a
key's principal.

Errors: a name that is taken or not there is a ContractError (PATH_EXISTS, PATH_NOT_FOUND);
a name, password or machine list that cannot be taken (an admin's, for one) is a ValueError;
a refused sign-in is SignInRefused.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterable
from datetime import datetime, timedelta
from typing import Literal, TypeVar

from sqlalchemy import Select, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from jobs import db
from jobs.auth import passwords
from jobs.auth.guessers import guesser_of, held_count
from jobs.auth.models import SIGNIN_COUNT_NAME_CHARS, ApiKey, SignInCount, User
from jobs.auth.roles import Principal, Role, shown_id
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import registry
from jobs.models import Machine, utcnow
from jobs.settings import Settings

NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._@-]{0,63}")
KEY_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
LAST_USED_EVERY_S = 60.0  # a key's last use is written at most this often: not a write per request
# An admin makes keys and users, and changes its own list: a list would limit nothing.
ADMIN_LIST = ("an admin may change every machine: give it no machine list (all machines), or "
              "another role")
# Every refused sign-in says the same (a name is not given away): a lock-out told apart
# showed which names exist, since only those are ever locked.
WRONG = ("wrong name or password, or too many failed sign-ins with that name (a lock-out "
         "ends by itself after a while, or when an admin sets a new password)")


Row = TypeVar("Row", User, ApiKey, SignInCount)


class SignInRefused(Exception):
    """A sign-in refused: wrong name or password, locked out (until when), or disabled;
    `locked_now`: this failure is the one that locked the name out (the audit trail's)."""

    def __init__(self, kind: Literal["wrong", "locked", "disabled"], reason: str, *,
                 locked_until: datetime | None = None, locked_now: bool = False) -> None:
        super().__init__(reason)
        self.kind = kind
        self.reason = reason
        self.locked_until = locked_until
        self.locked_now = locked_now


class _Unset:
    """A keyword not given (None is a value: all machines)."""


UNSET = _Unset()


def _checked_machines(machines: Iterable[str] | None) -> list[str] | None:
    if machines is None:
        return None
    chosen = [m.strip() for m in machines]
    if not chosen:  # read as every machine by some, as none by the list: said, not guessed
        raise ValueError("a machine list names no machine (it would allow none): name its "
                         "machines, or give --machines all for every machine (in the API, "
                         '"machines": null)')
    if any(not m or len(m) > 64 for m in chosen):
        raise ValueError("a machine id is empty or longer than 64 characters")
    return list(dict.fromkeys(chosen))


def _machine_list(session: Session, role: Role,
                  machines: Iterable[str] | None) -> list[str] | None:
    """The machine list of a user or key of `role` (None: all machines), of registered ids."""
    chosen = _checked_machines(machines)
    if chosen is None:
        return None
    if Role(role) is Role.ADMIN:
        raise ValueError(ADMIN_LIST)
    known = set(session.scalars(select(Machine.id).where(Machine.id.in_(chosen))))
    unknown = [m for m in chosen if m not in known]  # a typo would allow nothing, silently
    if unknown:
        ids = "the id" if len(unknown) == 1 else "the ids"
        hinted = registry.hints(session=session, names=unknown)
        named = ", ".join(shown_id(m) + hinted.get(m, "") for m in unknown)
        raise ValueError(f"no machine has {ids} {named} (dncq machines list and the "
                         "dashboard's fleet show the ids)")
    return chosen


def _checked_password(password: str) -> str:
    if len(password) < passwords.MIN_PASSWORD_CHARS:
        raise ValueError(f"a password has at least {passwords.MIN_PASSWORD_CHARS} characters")
    return password


def _checked_name(name: str, pattern: re.Pattern[str], what: str) -> str:
    if not pattern.fullmatch(name):
        raise ValueError(f"a {what} name is 1 to 64 letters, digits, `.`, `_` or `-`"
                         f"{', `@`' if pattern is NAME else ''}, starting with a letter or digit")
    return name


# -- users ----------------------------------------------------------------------------------


def create_user(*, session: Session, name: str, password: str, role: Role,
                machines: Iterable[str] | None = None) -> User:
    """A new user with its password hashed (argon2id)."""
    _checked_name(name, NAME, "user")
    if session.scalar(select(User).where(User.name == name)) is not None:
        raise ContractError(ErrorCode.PATH_EXISTS, f"user {name} exists")
    user = User(name=name, role=Role(role), machines=_machine_list(session, role, machines),
                password_hash=passwords.hash_password(_checked_password(password)),
                disabled=False, failed_signins=0)
    session.add(user)
    _flush_new(session, f"user {name} exists")
    return user


def get_user(*, session: Session, name: str, for_update: bool = False) -> User:
    """The user of that name (PATH_NOT_FOUND when there is none); `for_update` holds its row
    to the end of the transaction, read as another change that held it left it."""
    query = select(User).where(User.name == name)
    user = _held(session, query) if for_update else session.scalar(query)
    if user is None:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"no user {name}")
    return user


def list_users(*, session: Session) -> list[User]:
    """Every user, by name."""
    return list(session.scalars(select(User).order_by(User.name)))


def update_user(*, session: Session, name: str, role: Role | None = None,
                machines: Iterable[str] | None | _Unset = UNSET, password: str | None = None,
                disabled: bool | None = None) -> User:
    """Change what is given of a user; a new password or enabling it again ends a lock-out.

    Held: a change checked against the user as another left it (no admin with a machine
    list), and PATH_NOT_FOUND for one removed meanwhile."""
    user = get_user(session=session, name=name, for_update=True)
    if not isinstance(machines, _Unset):
        user.machines = _machine_list(session, Role(role or user.role), machines)
    elif role is not None and Role(role) is Role.ADMIN and user.machines is not None:
        # The ids it kept need not all be there still: the list is cleared, not checked.
        raise ValueError(f"user {user.name} has a machine list, which an admin takes none of "
                         "(it would limit nothing): clear it in the same change, with "
                         '--machines all (in the API, "machines": null)')
    if role is not None:
        user.role = Role(role)
    if password is not None:
        user.password_hash = passwords.hash_password(_checked_password(password))
    if disabled is not None:
        user.disabled = disabled
    if password is not None or disabled is False:
        _reset_failures(user)
    session.flush()
    return user


def delete_user(*, session: Session, name: str) -> None:
    """Remove a user (what it did stays in the audit trail); of two removals at once the
    second is PATH_NOT_FOUND."""
    session.delete(get_user(session=session, name=name, for_update=True))
    session.flush()


def _held(session: Session, query: Select[Row]) -> Row | None:
    """The user or key `query` finds, its row held to the end of the transaction and read
    as another that held it left it (on SQLite, the database's write lock taken first)."""
    return session.scalar(db.held(session, query))


def principal_of(user: User) -> Principal:
    """The principal a signed-in user acts as."""
    machines = tuple(user.machines) if user.machines is not None else None
    return Principal(name=user.name, kind="user", role=Role(user.role), machines=machines)


def _reset_failures(counted: User | SignInCount) -> None:
    counted.failed_signins, counted.failed_since, counted.locked_until = 0, None, None


def authenticate(*, session: Session, settings: Settings, name: str, password: str) -> User:
    """The user whose name and password these are; SignInRefused otherwise.

    Failures are counted per user: `signin_max_failures` within `signin_window_s` lock it
    for `signin_lockout_s`, refusing even the right password; a success resets the count.
    The count is committed before a refusal is raised, so the caller's rollback keeps it.
    """
    user = session.scalar(select(User).where(User.name == name))
    # Verified whoever it is (an unknown name against a dummy hash): a refusal that came
    # sooner for some names than for others would tell them apart.
    right = passwords.verify_password(user.password_hash if user else None, password)
    if user is not None:
        # Then held, as other sign-ins of the user left it: failures at the same moment each
        # count, where guesses sent at once were all counted as one.
        user = _held(session, select(User).where(User.id == user.id))
    if user is None:
        raise SignInRefused("wrong", WRONG)
    _refuse_locked_or_wrong(session, settings, user, right=right)
    if user.disabled:
        raise SignInRefused("disabled", f"user {user.name} is disabled")
    _reset_failures(user)
    user.last_signin_at = utcnow()
    if passwords.needs_rehash(user.password_hash):
        user.password_hash = passwords.hash_password(password)
    session.flush()
    return user


def authenticate_with_key(*, session: Session, settings: Settings, name: str, given: str,
                          key: str | None, address: str | None) -> None:
    """Nothing when `given` is `key`, the password of `name`, which no user has (the admin
    key's `admin`); SignInRefused otherwise, its failures counted and locked out as a user's,
    but for each client address apart.

    Per address, as the HTTP API counts wrong keys (jobs.auth.wrong_keys): a lock-out of the
    name for everyone would let anyone keep the administrator out of the dashboard with five
    wrong guesses; counted per address, a guesser locks out only itself. The key is compared
    in constant time; the count is committed before a refusal is raised.
    """
    # A password's verify spent on nothing, as for a name nobody has: answered without one,
    # a sign-in as `admin` came tens of times sooner while no user of that name is stored.
    passwords.verify_password(None, given)
    right = key is not None and passwords.same_key(given, key)
    counted: SignInCount = held_count(session, SignInCount.name, _counted_name(name, address),
                                      window_s=settings.signin_window_s, failed_signins=0)
    _refuse_locked_or_wrong(session, settings, counted, right=right)
    _reset_failures(counted)
    session.flush()


def _counted_name(name: str, address: str | None) -> str:
    """The row a key sign-in's failures are counted in: the name's from that address (an IPv6
    address's /64)."""
    if address is None:
        return name
    address = guesser_of(address)
    counted = f"{name} from {address}"
    # An address longer than the column (no IP address is) shares a row by its digest.
    return counted if len(counted) <= SIGNIN_COUNT_NAME_CHARS else \
        f"{name} from #{hashlib.sha256(address.encode()).hexdigest()[:32]}"


def _refuse_locked_or_wrong(session: Session, settings: Settings, counted: User | SignInCount,
                            *, right: bool) -> None:
    """SignInRefused while `counted` is locked out, or for a wrong password (the failure
    counted and committed, so the caller's rollback keeps it); nothing for a right one."""
    now = utcnow()
    if counted.locked_until is not None and counted.locked_until > now:
        raise SignInRefused("locked", WRONG, locked_until=counted.locked_until)
    if not right:
        _count_failure(counted, settings, now)
        session.commit()
        if counted.locked_until is not None and counted.locked_until > now:
            raise SignInRefused("locked", WRONG, locked_until=counted.locked_until,
                                locked_now=True)
        raise SignInRefused("wrong", WRONG)


def _count_failure(counted: User | SignInCount, settings: Settings, now: datetime) -> None:
    """Count a failure of `counted`, not locked out now; at the last one allowed, lock it
    out, its failures and their start kept (what an administrator is shown)."""
    window = timedelta(seconds=settings.signin_window_s)
    if counted.locked_until is not None or counted.failed_since is None or \
            now - counted.failed_since > window:
        # A new window, also after a lock-out that ended: its failures were paid for.
        counted.failed_since, counted.failed_signins, counted.locked_until = now, 0, None
    counted.failed_signins += 1
    if counted.failed_signins >= settings.signin_max_failures:
        counted.locked_until = now + timedelta(seconds=settings.signin_lockout_s)


# -- named API keys ---------------------------------------------------------------------------


def create_key(*, session: Session, name: str, role: Role,
               machines: Iterable[str] | None = None,
               created_by: str | None = None) -> tuple[ApiKey, str]:
    """A new named key and the key itself, which is not kept and cannot be shown again."""
    _checked_name(name, KEY_NAME, "key")
    if session.scalar(select(ApiKey).where(ApiKey.name == name)) is not None:
        raise ContractError(ErrorCode.PATH_EXISTS, f"key {name} exists (a revoked key keeps "
                                                   "its name: choose another)")
    plain = passwords.new_key()
    key = ApiKey(name=name, role=Role(role), key_hash=passwords.key_digest(plain),
                 prefix=plain[:passwords.KEY_SHOWN_CHARS], created_by=created_by,
                 machines=_machine_list(session, role, machines))
    session.add(key)
    _flush_new(session, f"key {name} exists")
    return key, plain


def _flush_new(session: Session, exists: str) -> None:
    """Write the new row; one of the same name added by another at the same moment, which
    the check before did not see yet, is PATH_EXISTS as it would have been then."""
    try:
        session.flush()
    except IntegrityError:
        session.rollback()
        raise ContractError(ErrorCode.PATH_EXISTS, exists) from None


def get_key(*, session: Session, name: str, for_update: bool = False) -> ApiKey:
    """The key of that name (PATH_NOT_FOUND when there is none); `for_update` as for
    `get_user`."""
    query = select(ApiKey).where(ApiKey.name == name)
    key = _held(session, query) if for_update else session.scalar(query)
    if key is None:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"no key {name}")
    return key


def list_keys(*, session: Session, revoked: bool = True) -> list[ApiKey]:
    """Every key by name (without the revoked ones unless `revoked`)."""
    query = select(ApiKey).order_by(ApiKey.name)
    if not revoked:
        query = query.where(ApiKey.revoked_at.is_(None))
    return list(session.scalars(query))


def revoke_key(*, session: Session, name: str) -> ApiKey:
    """Refuse the key from now on (kept, revoked, so that the audit trail still names it);
    revoked again, also by another at the same moment, it keeps the first revoke's time."""
    key = get_key(session=session, name=name, for_update=True)
    if key.revoked_at is None:
        key.revoked_at = utcnow()
    session.flush()
    return key


def find_key(*, session: Session, plain: str) -> ApiKey | None:
    """The key `plain` is, revoked or not; its last use noted (at most once a minute)."""
    key = session.scalar(select(ApiKey).where(ApiKey.key_hash == passwords.key_digest(plain)))
    if key is not None and key.revoked_at is None:
        now = utcnow()
        if key.last_used_at is None or \
                (now - key.last_used_at).total_seconds() >= LAST_USED_EVERY_S:
            key.last_used_at = now
            session.flush()
    return key


def key_principal(key: ApiKey) -> Principal:
    """The principal a named key acts as: `key:NAME`."""
    machines = tuple(key.machines) if key.machines is not None else None
    return Principal(name=f"key:{key.name}", kind="key", role=Role(key.role), machines=machines)
