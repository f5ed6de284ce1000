"""Service configuration from environment variables prefixed ``BRADYSCOPE_``.

Every field below can be set as ``BRADYSCOPE_<FIELD NAME IN CAPITALS>``, e.g.
``BRADYSCOPE_DATA_DIR=/srv/bradyscope`` or
``BRADYSCOPE_DATABASE_URL=postgresql+psycopg://bradyscope@db/bradyscope``.
A ``.env`` file is NOT read implicitly (explicit is safer in a hospital).

Tests build ``Settings(data_dir=tmp_path)`` directly instead of touching the
environment.
"""

from __future__ import annotations

import ipaddress
from functools import lru_cache
from pathlib import Path
from typing import Any
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """All service settings. See ``docs/operations.md`` for an explanation of each."""

    model_config = SettingsConfigDict(env_prefix="BRADYSCOPE_", extra="ignore")

    data_dir: Path = Field(
        default=Path("./data"), description="Database (SQLite) and stored files live here."
    )
    database_url: str | None = Field(
        default=None,
        description="SQLAlchemy URL; default: SQLite file bradyscope.sqlite3 in data_dir. "
        "PostgreSQL: postgresql+psycopg://user@host:5432/dbname",
    )
    max_upload_bytes: int = Field(default=2 * 1024**3, gt=0, description="Per uploaded file.")
    upload_chunk_bytes: int = Field(default=1024 * 1024, gt=0)
    job_lease_s: float = Field(
        default=60.0, gt=0, description="A job whose worker is silent this long is re-claimed."
    )
    job_heartbeat_s: float | None = Field(
        default=None, gt=0, description="Heartbeat period; default job_lease_s / 4."
    )
    job_max_attempts: int = Field(default=3, ge=1, description="Attempts before a job fails.")
    job_retry_delay_s: float = Field(default=5.0, ge=0, description="Back-off before a retry.")
    worker_poll_s: float = Field(default=1.0, gt=0, description="Idle worker polling period.")
    worker_nice: int = Field(
        default=10,
        ge=0,
        le=19,
        description="CPU priority the job workers of `serve` and `worker` give up (Linux nice"
        " steps), so that pages and a recording on the same machine come first; 0 keeps it.",
    )
    secure_cookies: bool = Field(
        default=False, description="Set the Secure flag on cookies (enable behind HTTPS)."
    )
    session_ttl_s: float = Field(
        default=8 * 3600.0, gt=0, description="Absolute life of a browser login (s)."
    )
    session_idle_s: float = Field(
        default=30 * 60.0, gt=0, description="A browser login unused this long ends (s)."
    )
    login_max_failures: int = Field(
        default=5,
        ge=1,
        description="Failed logins from one address for one account before delays begin "
        "(twice as many for the account from all addresses together).",
    )
    login_delay_s: float = Field(
        default=30.0, gt=0, description="First delay after the free failures; doubles each time."
    )
    login_max_delay_s: float = Field(
        default=15 * 60.0, gt=0, description="Longest delay between two login attempts."
    )
    login_lock_after_failures: int = Field(
        default=100,
        ge=10,
        description="Consecutive failures that lock an account until 'admin unlock' "
        "(NIST SP 800-63B: at most 100).",
    )
    login_window_s: float = Field(
        default=24 * 3600.0,
        gt=0,
        description="A failure streak (below the lock) is forgotten after this long without attempts.",
    )
    trusted_proxies: str = Field(
        default="",
        description="Comma-separated addresses or networks of reverse proxies whose "
        "X-Forwarded-For/-Proto headers are believed; empty: none (the socket's address counts).",
    )
    password_min_length: int = Field(
        default=15, ge=8, le=64, description="NIST SP 800-63B-4: 15 for a single factor."
    )
    api_key_days: int = Field(
        default=365, ge=1, description="Default life of a new API key (days)."
    )
    retention_days: int | None = Field(
        default=None,
        ge=1,
        description="Erase a patient this many days after their last recording "
        "('admin apply-retention'); unset: keep until erased by hand.",
    )
    local_login: bool = Field(
        default=True,
        description="Allow e-mail + password logins (false: single sign-on only).",
    )
    oidc_issuer: str | None = Field(
        default=None,
        description="OpenID Connect issuer URL of the hospital's identity provider; unset: no SSO.",
    )
    oidc_client_id: str | None = Field(default=None, description="bradyscope's client id there.")
    oidc_client_secret: str | None = Field(default=None, description="Its client secret.")
    oidc_scopes: str = Field(default="openid email profile")
    oidc_email_claim: str = Field(
        default="email", description="The ID-token claim holding the account's e-mail address."
    )
    oidc_require_verified_email: bool = Field(
        default=True,
        description="Accept an SSO login only with email_verified true in its ID token: its "
        "address finds (and binds) the account. false: for a provider that manages the "
        "addresses itself and does not send the claim.",
    )
    oidc_create_users: bool = Field(
        default=False,
        description="Create a clinician account at a person's first SSO login "
        "(default: only accounts an administrator created may log in).",
    )
    oidc_display_name: str = Field(
        default="the hospital's single sign-on", description="The login button's words."
    )
    audit_key_file: Path | None = Field(
        default=None,
        description="Secret key of the audit hash chain; default <data_dir>/audit.key.",
    )
    sqlite_busy_timeout_ms: int = Field(default=30_000, ge=0)
    migration_lock_timeout_s: float = Field(default=300.0, gt=0)
    log_level: str = Field(default="INFO")
    report_cache_mb: int = Field(
        default=256,
        ge=1,
        description="The most the trials' PDF reports made ahead of time may take on disk "
        "(<data_dir>/cache/reports; about 0.1 MB a report), and apart from them the patients'"
        " trend plots (<data_dir>/cache/trends).",
    )
    timezone: str = Field(
        default="UTC",
        description="The clinic's time zone (IANA name, e.g. Europe/Prague): session dates are"
        " entered and shown in it; the database stores UTC.",
    )

    @field_validator("timezone")
    @classmethod
    def _known_zone(cls, value: str) -> str:
        try:
            ZoneInfo(value)
        except (ZoneInfoNotFoundError, ValueError):
            raise ValueError(
                f"BRADYSCOPE_TIMEZONE={value!r} is not a time zone name; use an IANA name"
                " such as Europe/Prague or UTC"
            ) from None
        return value

    @field_validator("data_dir")
    @classmethod
    def _absolute(cls, value: Path) -> Path:
        return value.expanduser().resolve()

    @field_validator("trusted_proxies")
    @classmethod
    def _proxy_addresses(cls, value: str) -> str:
        items = [item.strip() for item in value.split(",") if item.strip()]
        for item in items:
            try:
                ipaddress.ip_network(item, strict=False)
            except ValueError:
                raise ValueError(
                    f"BRADYSCOPE_TRUSTED_PROXIES holds {item!r}, which is not an IP address or "
                    "network; list the proxies' addresses, e.g. 10.0.0.5,10.0.1.0/24"
                ) from None
        return ",".join(items)

    @property
    def trusted_proxy_list(self) -> list[str]:
        """The trusted proxies' addresses and networks (empty: trust no forwarded header)."""
        return [item for item in self.trusted_proxies.split(",") if item]

    @property
    def audit_key_path(self) -> Path:
        """Where the audit chain's secret key is kept."""
        return self.audit_key_file or self.data_dir / "audit.key"

    @property
    def effective_database_url(self) -> str:
        """``database_url``, or the default SQLite file in ``data_dir``."""
        if self.database_url:
            return normalise_database_url(self.database_url)
        return f"sqlite:///{self.data_dir / 'bradyscope.sqlite3'}"

    @property
    def is_sqlite(self) -> bool:
        return self.effective_database_url.startswith("sqlite")

    @property
    def display_database(self) -> str:
        """The database URL with any password hidden (for messages and logs)."""
        from sqlalchemy.engine import make_url

        try:
            return make_url(self.effective_database_url).render_as_string(hide_password=True)
        except Exception:  # malformed URL: SQLAlchemy will report it when connecting
            return "the configured database"

    @property
    def heartbeat_s(self) -> float:
        """Heartbeat period of a running job (seconds)."""
        return self.job_heartbeat_s if self.job_heartbeat_s is not None else self.job_lease_s / 4


def normalise_database_url(url: str) -> str:
    """Use the installed psycopg 3 driver for plain ``postgres(ql)://`` URLs.

    SQLAlchemy would otherwise look for psycopg2, which bradyscope does not install.
    """
    url = url.strip()
    for plain in ("postgres://", "postgresql://"):
        if url.startswith(plain):
            return "postgresql+psycopg://" + url[len(plain) :]
    return url


def settings_with(**overrides: Any) -> Settings:
    """Settings from the environment, with the non-None ``overrides`` on top (CLI options)."""
    return Settings(**{k: v for k, v in overrides.items() if v is not None})


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings read from the environment (cached; tests build their own)."""
    return Settings()
