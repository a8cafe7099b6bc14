"""The one Settings object: environment variables `DNCQ_*` and an optional TOML file."""

from __future__ import annotations

import os
import secrets
from enum import StrEnum
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

API_KEY_FILE = "api-key"


class AuthMode(StrEnum):
    """How the HTTP API checks its callers."""

    KEY = "key"  # every request carries the API key
    NONE = "none"  # closed shop-floor network: no check at all


class Settings(BaseSettings):
    """dncq's configuration, validated once at start."""

    model_config = SettingsConfigDict(env_prefix="DNCQ_", extra="ignore")

    data_dir: Path = Field(default=Path("data"), description="Database, payloads, mock machines")
    database_url: str | None = Field(default=None, description="Default: SQLite in data_dir")
    broker_url: str | None = Field(
        default=None, description="Celery broker; default: a file-backed queue in data_dir"
    )
    api_key: SecretStr | None = None
    auth: AuthMode = AuthMode.KEY
    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=0, le=65535)  # 0: any free port (the benches)
    url: str | None = Field(default=None, description="Where the CLI finds the API")

    max_json_body_bytes: int = 20 * 1024 * 1024  # sendFile is for <= 10 MB; base64 adds a third
    max_stream_body_bytes: int = 4 * 1024**3
    max_receive_file_bytes: int = 10 * 1024 * 1024  # receiveFile (JSON) answers up to this size
    max_send_file_bytes: int = 10 * 1024 * 1024  # sendFile (JSON) takes up to this size
    max_kept_file_bytes: int = 32 * 1024 * 1024  # a replace keeps the old file up to this size

    batch_wait_s: float = 300.0  # batchSendFile/batchDeleteFile answer after at most this long
    busy_wait_s: float = 30.0  # a single-machine request waits this long for a busy machine
    max_attempts: int = 5  # tries of a target that fails with a transient error
    retry_base_s: float = 2.0  # first retry delay; doubles each attempt, with jitter
    retry_max_s: float = 300.0
    lease_ttl_s: float = 30.0  # a dead runner's targets run again within this long
    reaper_interval_s: float = 2.0  # how often stuck and waiting targets are looked at
    redispatch_after_s: float = 60.0  # a queued target not started by then is queued again
    worker_concurrency: int = 16  # embedded mode: machines served at once
    claim_ahead: bool = True  # gevent workers: as many tasks wait for a slot, targets claimed
    job_retention_days: int = 30  # `dncq jobs prune` removes finished jobs older than this
    audit_retention_days: int = Field(default=400, ge=1)  # `dncq audit prune`: older goes
    # Deflate level of backup ZIPs: 0 stores, 1-3 are ISA-L's (jobs.backup.deflate; on G-code
    # level 3 runs 2.3x as fast as zlib-ng's level 3 into members within 1 % of its size),
    # 4-9 zlib-ng's, 1-2 % smaller at 3-5x the CPU (level 9: 4 % smaller than 6, 2.5x its CPU).
    backup_zip_level: int = Field(default=3, ge=0, le=9)
    notify_urls: list[str] = Field(  # webhooks / apprise URLs for every alert; may hold secrets
        default_factory=list, description='JSON list, e.g. ["https://hooks.example/dncq"]')
    schedule_tick_s: float = 30.0  # how often beat (or the embedded mode) looks at schedules
    # Workers check each idle, enabled machine this often (0: only when asked): the fleet
    # page and the `dncq_machines` metric; a check older than 3 periods counts as none.
    machine_check_interval_s: float = Field(default=300.0, ge=0)
    request_scan_interval_s: float = 10.0  # how often drop folders are looked into for requests
    # Logs of serve, api, worker and beat: lines of text, or one JSON object per line.
    log_format: Literal["text", "json"] = "text"
    listen: bool = True  # workers listen on serial and dnc links for what operators send
    # The inbox (programs machines sent): failed receptions kept per machine, and how long
    # a rejected program is kept after its rejection.
    inbox_failed_keep: int = Field(default=50, ge=1)
    inbox_rejected_keep_days: int = Field(default=30, ge=0)
    # Sign-in lock-out: this many failed sign-ins of a user within signin_window_s lock
    # the user out for signin_lockout_s.
    signin_max_failures: int = Field(default=5, ge=1)
    signin_window_s: float = Field(default=900.0, gt=0)
    signin_lockout_s: float = Field(default=900.0, ge=0)
    # The dashboard's sign-in: a session ends after this long unused, and this long after
    # it began whatever its use.
    web_session_idle_s: float = Field(default=8 * 3600, gt=0)
    web_session_max_s: float = Field(default=24 * 3600, gt=0)

    config_file: Path | None = Field(default=None, description="Optional TOML file")

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        sources: list[PydanticBaseSettingsSource] = [init_settings, env_settings]
        toml_path = os.environ.get("DNCQ_CONFIG_FILE")
        if toml_path and not Path(toml_path).is_file():  # not quietly the defaults instead
            raise ValueError(f"DNCQ_CONFIG_FILE: no file {toml_path}")
        if toml_path:
            toml = TomlConfigSettingsSource(settings_cls, toml_file=toml_path)
            _no_unknown_names(toml.toml_data, list(settings_cls.model_fields), toml_path)
            sources.append(toml)
        return tuple(sources)

    @field_validator("url")
    @classmethod
    def _http_url(cls, value: str | None) -> str | None:
        # Said as a setting's error, not as the HTTP client's traceback at the first call.
        if value is None:
            return None
        from urllib.parse import urlsplit

        parts = urlsplit(value)
        try:
            _ = parts.port  # a port that is no number, or out of range
        except ValueError as exc:
            raise ValueError(f"not a URL of the API: {exc}") from None
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError("the API's URL is http:// or https:// and a host")
        return value

    @property
    def resolved_database_url(self) -> str:
        """The database URL, defaulting to a SQLite file in the data folder."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'dncq.sqlite3').resolve()}"

    @property
    def check_max_age_s(self) -> float | None:
        """How old a machine's last check may be and still say online or offline."""
        return 3 * self.machine_check_interval_s if self.machine_check_interval_s else None

    @property
    def api_url(self) -> str:
        """Base URL of the HTTP API for the CLI."""
        return self.url or f"http://{self.host}:{self.port}"

    def effective_api_key(self, *, create: bool = False) -> str | None:
        """The configured key, else the one kept in the data folder (made when `create`)."""
        if self.auth is AuthMode.NONE:
            return None
        if self.api_key is not None:
            return self.api_key.get_secret_value()
        key_file = self.data_dir / API_KEY_FILE
        if key_file.exists():
            return key_file.read_text().strip()
        if not create:
            return None
        self.data_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
        key = secrets.token_urlsafe(24)
        fd = os.open(key_file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(key + "\n")
        return key


def _no_unknown_names(data: dict[str, object], known: list[str], path: str) -> None:
    """Refuse a name in the TOML file that is no setting (a typo, or `DNCQ_PORT` for `port`),
    which would otherwise leave that setting at its default without a word."""
    from jobs.errors import hint

    unknown = [name for name in data if name not in known]
    if unknown:
        named = ", ".join(f"{name}{hint(name.lower().removeprefix('dncq_'), known)}"
                          for name in unknown)
        raise ValueError(f"DNCQ_CONFIG_FILE: {path}: not a setting: {named} (a setting is "
                         "named as its DNCQ_ variable, in lower case without DNCQ_)")


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings, read once."""
    return Settings()
