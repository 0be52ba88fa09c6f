"""The ``notify`` section of daemon.yaml: which verdicts to announce, the morning-check
deadline per machine, the webhook and the e-mail (SMTP) settings."""

from __future__ import annotations

import os
import re
import ssl
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from contracts.yaml_files import ConfigError, HostName, StrictModel

_HHMM = re.compile(r"([01][0-9]|2[0-3]):([0-5][0-9])")
_ADDR = re.compile(r"[^@\s<>,;\"\r\n]{1,64}@[A-Za-z0-9.-]{1,253}")
DAYS = ("mon", "tue", "wed", "thu", "fri", "sat", "sun")
Event = Literal["WARN", "FAIL", "ERROR"]


def _hhmm(v: str | None) -> str | None:
    if v is not None and not _HHMM.fullmatch(v):
        raise ValueError(f"{v!r}: expected a local time HH:MM (24 h), e.g. '07:00'")
    return v


class WebhookFile(StrictModel):
    url: str
    token_file: str | None = None  # sent as "Authorization: Bearer …" (mode 600 file)
    timeout_s: float = Field(10.0, gt=0, le=120)
    attempts: int = Field(3, ge=1, le=10)

    @field_validator("url")
    @classmethod
    def _url(cls, v: str) -> str:
        if not re.fullmatch(r"https?://[^\s]+", v):
            raise ValueError(f"{v!r}: expected an http:// or https:// URL")
        return v


class EmailFile(StrictModel):
    host: HostName
    port: int = Field(25, ge=1, le=65535)
    starttls: bool = False
    ca: str | None = None  # CA bundle of the server's certificate (default: the system's)
    sender: str = Field(alias="from")
    to: list[str] = Field(min_length=1)
    username: str | None = None
    password_file: str | None = None  # mode 600, like the MQTT password
    timeout_s: float = Field(20.0, gt=0, le=300)

    @field_validator("sender", "to")
    @classmethod
    def _addresses(cls, v: str | list[str]) -> str | list[str]:
        for a in [v] if isinstance(v, str) else v:
            if not _ADDR.fullmatch(a):  # no header injection through an address
                raise ValueError(f"{a!r}: expected one e-mail address (name@host)")
        return v

    @model_validator(mode="after")
    def _creds(self) -> EmailFile:
        if (self.username is None) != (self.password_file is None):
            raise ValueError("give both 'username' and 'password_file', or neither")
        return self


class NotifyFile(StrictModel):
    on: list[Event] = ["WARN", "FAIL", "ERROR"]
    morning_check_by: str | None = None  # every machine of this daemon, local time
    morning_check_by_machine: dict[str, str | None] = {}  # per machine; null: no deadline
    morning_check_days: list[Literal[DAYS]] = list(DAYS[:5])  # type: ignore[valid-type]
    webhook: WebhookFile | None = None
    email: EmailFile | None = None
    _t = field_validator("morning_check_by")(_hhmm)

    @field_validator("morning_check_by_machine")
    @classmethod
    def _times(cls, v: dict[str, str | None]) -> dict[str, str | None]:
        for t in v.values():
            _hhmm(t)
        return v

    @model_validator(mode="after")
    def _somewhere(self) -> NotifyFile:
        if self.webhook is None and self.email is None:
            raise ValueError("give a 'webhook', an 'email', or both")
        return self


@dataclass(frozen=True)
class EmailConfig:
    host: str
    port: int
    starttls: ssl.SSLContext | None
    sender: str
    to: tuple[str, ...]
    username: str | None
    password: str | None
    timeout_s: float


@dataclass(frozen=True)
class NotifyConfig:
    on: frozenset[str]
    deadlines: dict[str, tuple[int, int]]  # machine → (hour, minute) local
    days: frozenset[int]  # time.struct_time.tm_wday values
    webhook_url: str | None = None
    webhook_token: str | None = None
    webhook_timeout_s: float = 10.0
    webhook_attempts: int = 3
    email: EmailConfig | None = None


def load_notify(f: NotifyFile, base: Path, where: str, machines: list[str],
                read_secret: Callable[[Path, str], str]) -> NotifyConfig:
    """Resolve files relative to daemon.yaml and read the secrets with ``read_secret`` (private
    file, ≥ 16 characters); per-machine deadlines must name configured machines."""
    def _resolve(p: str) -> Path:
        q = Path(os.path.expandvars(os.path.expanduser(p)))
        return q if q.is_absolute() else base / q

    for name in f.morning_check_by_machine:
        if name not in machines:
            raise ConfigError(f"{where}.morning_check_by_machine.{name}: not a configured "
                              f"machine ({', '.join(machines)})")
    deadlines = {}
    for m in machines:
        t = f.morning_check_by_machine.get(m, f.morning_check_by)
        if t is not None:
            hh, mm = t.split(":")
            deadlines[m] = (int(hh), int(mm))
    token = None
    if f.webhook is not None and f.webhook.token_file is not None:
        token = read_secret(_resolve(f.webhook.token_file), f"{where}.webhook.token_file")
    email = None
    if f.email is not None:
        e = f.email
        password = (read_secret(_resolve(e.password_file), f"{where}.email.password_file")
                    if e.password_file else None)
        ctx = None
        if e.starttls:
            try:
                ctx = ssl.create_default_context(cafile=str(_resolve(e.ca)) if e.ca else None)
            except (OSError, ssl.SSLError) as x:
                raise ConfigError(f"{where}.email.ca: {getattr(x, 'strerror', None) or x}"
                                  ) from None
        email = EmailConfig(e.host, e.port, ctx, e.sender, tuple(e.to), e.username, password,
                            e.timeout_s)
    return NotifyConfig(frozenset(f.on), deadlines,
                        frozenset(DAYS.index(d) for d in f.morning_check_days),
                        f.webhook.url if f.webhook else None, token,
                        f.webhook.timeout_s if f.webhook else 10.0,
                        f.webhook.attempts if f.webhook else 3, email)
