"""Machine secrets encrypted at rest, with a key kept apart from the database.

A sealed value is `dncq-sealed:v1:` and a Fernet token. The keys come from the
environment variable `DNCQ_SECRETS_KEY` when it is set (the distributed mode: every API
and worker process gets the same value), else from the file `secrets-key` in the data
folder, made (0600) on first use. Either holds one or more keys, separated by commas or
lines: the first seals, every one unseals, so a new key is put first and the old kept
until every machine is sealed again (`Keyring.rotated`).
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

from cryptography.fernet import Fernet, InvalidToken, MultiFernet

from jobs.folders import private_dir

KEY_ENV = "DNCQ_SECRETS_KEY"
KEY_FILE = "secrets-key"
PREFIX = "dncq-sealed:v1:"


class SecretsKeyError(ValueError):
    """The secrets key is missing, malformed, or not the one a secret was sealed with."""


def is_sealed(value: object) -> bool:
    """Whether `value` is a sealed secret."""
    return isinstance(value, str) and value.startswith(PREFIX)


class Keyring:
    """The keys that seal and unseal machine secrets."""

    def __init__(self, keys: list[str], *, source: str) -> None:
        if not keys:
            raise SecretsKeyError(f"no key in {source}")
        try:
            self._fernet = MultiFernet([Fernet(k.encode("ascii")) for k in keys])
        except (ValueError, UnicodeEncodeError):
            raise SecretsKeyError(
                f"{source} holds a key that is not a Fernet key (32 url-safe base64 bytes; "
                "make one with `dncq secrets-key`)") from None
        self.source = source

    def seal(self, plain: str) -> str:
        """`plain` sealed with the first key."""
        return PREFIX + self._fernet.encrypt(plain.encode("utf-8")).decode("ascii")

    def unseal(self, value: str) -> str:
        """The plain secret of a sealed value; a value stored before sealing, as it is."""
        if not is_sealed(value):
            return value
        try:
            return self._fernet.decrypt(value.removeprefix(PREFIX).encode("ascii")).decode()
        except (InvalidToken, UnicodeError):
            raise SecretsKeyError(
                f"a machine secret was sealed with a key {self.source} does not hold") from None

    def rotated(self, value: str) -> str:
        """`value` sealed with the first key, whichever key sealed it (or none)."""
        return self.seal(self.unseal(value))


def new_key() -> str:
    """A fresh key, as `DNCQ_SECRETS_KEY` or the key file takes it."""
    return Fernet.generate_key().decode("ascii")


def keyring(data_dir: Path, *, create: bool = True) -> Keyring:
    """The keys of this process: the environment's, else the data folder's key file.

    Args:
        data_dir: the data folder, where the key file is.
        create: make the key file when it is missing (to seal; unsealing never needs a new
            key, and a worker on another host must not make one of its own).
    """
    from_env = os.environ.get(KEY_ENV)
    if from_env is not None:
        return _parsed(from_env, f"${KEY_ENV}")
    key_file = data_dir / KEY_FILE
    try:
        st = key_file.stat()
    except FileNotFoundError:
        if not create:
            raise SecretsKeyError(f"no secrets key: set {KEY_ENV} (the same on every host) "
                                  f"or give this host the data folder's {KEY_FILE}") from None
        _create_key_file(data_dir, key_file)
        st = key_file.stat()
    # Read again only when the file changed (a key added or dropped): a worker unseals a
    # machine's password for every target it sends.
    stamp = (st.st_ino, st.st_mtime_ns, st.st_size)
    known = _READ.get(key_file)
    if known is None or known[0] != stamp:
        known = _READ[key_file] = (stamp, _parsed(key_file.read_text(), str(key_file)))
    return known[1]


_READ: dict[Path, tuple[tuple[int, int, int], Keyring]] = {}  # key file -> as last read


@lru_cache(maxsize=16)
def _parsed(text: str, source: str) -> Keyring:
    keys = [k.strip() for k in text.replace(",", "\n").splitlines() if k.strip()]
    return Keyring(keys, source=source)


def _create_key_file(data_dir: Path, key_file: Path) -> None:
    private_dir(data_dir)
    part = data_dir / f".{KEY_FILE}.{os.getpid()}"
    fd = os.open(part, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(new_key() + "\n")
    try:
        os.link(part, key_file)  # appears whole or not at all; never replaces another's key
    except FileExistsError:  # another process made it first: use theirs
        pass
    finally:
        part.unlink()
