"""Password hashes (argon2id, argon2-cffi's defaults) and API key digests (SHA-256)."""

from __future__ import annotations

import functools
import hashlib
import secrets
from urllib.parse import unquote_plus

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError

_hasher = PasswordHasher()
KEY_PREFIX = "dncq_"  # a named key says what it is; secret scanners can match it
KEY_PARAMETER = "apikey"  # the query parameter a key may come in, instead of X-Api-Key
KEY_SHOWN_CHARS = 12  # the listing shows this much of a key: enough to tell keys apart
MIN_PASSWORD_CHARS = 8


def is_key_parameter(name: str) -> bool:
    """Whether a query parameter's name, as sent, is or reads as the key's (`APIKEY`,
    `api%6Bey`): its value is a key, to keep out of logs and addresses."""
    return unquote_plus(name).strip().lower() == KEY_PARAMETER


@functools.cache
def _dummy_hash() -> str:
    """Verified against for a name nobody has: an unknown name costs as long as a wrong
    password. Made on first need, not at import (a hash costs 64 MiB and tens of ms)."""
    return _hasher.hash(secrets.token_urlsafe(16))


def hash_password(password: str) -> str:
    """The argon2id hash of `password`, as a PHC string (salt and parameters inside)."""
    return _hasher.hash(password)


def verify_password(password_hash: str | None, password: str) -> bool:
    """Whether `password` is the one hashed; a missing hash is verified against a dummy."""
    try:
        return _hasher.verify(password_hash or _dummy_hash(), password) and bool(password_hash)
    except (VerificationError, InvalidHashError):
        return False


def needs_rehash(password_hash: str) -> bool:
    """Whether the hash was made with weaker parameters than today's."""
    return _hasher.check_needs_rehash(password_hash)


def new_key() -> str:
    """A new API key: the prefix and 32 random bytes, URL-safe (no `@`: see KEY@MACHINE)."""
    return KEY_PREFIX + secrets.token_urlsafe(32)


def key_digest(key: str) -> str:
    """The hex SHA-256 a key is kept and looked up by (a random 32-byte key needs no salt)."""
    return hashlib.sha256(key.encode()).hexdigest()


def same_key(given: str, key: str) -> bool:
    """Whether `given` is `key`, compared in constant time (their digests: not even the
    key's length shows in how long a wrong one takes)."""
    return secrets.compare_digest(key_digest(given), key_digest(key))
