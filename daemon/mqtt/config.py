"""The ``mqtt`` section of daemon.yaml (live results out): broker, site, credentials, TLS."""

from __future__ import annotations

import os
import re
import ssl
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pydantic import Field, field_validator, model_validator

from contracts.yaml_files import ConfigError, HostName, StrictModel
from daemon.hosts import is_loopback

_TOPIC_LEVEL = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def topic_level(v: str) -> str:
    """One MQTT topic level from configuration: no '/', '+', '#', '$' or spaces (a name must
    neither add levels nor act as a wildcard in someone's subscription)."""
    if not _TOPIC_LEVEL.fullmatch(v):
        raise ValueError(f"{v!r}: expected 1-64 letters, digits, '_', '.', '-' (one topic level)")
    return v


class MqttTlsFile(StrictModel):
    ca: str | None = None  # CA bundle of the broker's certificate (default: the system's)
    cert: str | None = None  # client certificate (brokers that authenticate clients by cert)
    key: str | None = None

    @model_validator(mode="after")
    def _pair(self) -> MqttTlsFile:
        if (self.cert is None) != (self.key is None):
            raise ValueError("give both 'cert' and 'key', or neither")
        return self


class MqttFile(StrictModel):
    host: HostName
    port: int | None = Field(None, ge=1, le=65535)  # default 1883, or 8883 with tls
    site: str
    root: str = "rumba"  # first topic level
    username: str | None = None
    password_file: str | None = None  # mode 600, like the HMI token file
    tls: MqttTlsFile | None = None
    qos: int = Field(1, ge=0, le=1)
    keepalive_s: int = Field(30, ge=5, le=3600)
    queue_max: int = Field(1000, ge=10, le=100000)  # beyond: drop-oldest (counted)
    health_interval_s: float = Field(60.0, ge=1, le=86400)
    _s = field_validator("site", "root")(topic_level)

    @model_validator(mode="after")
    def _creds(self) -> MqttFile:
        if (self.username is None) != (self.password_file is None):
            raise ValueError("give both 'username' and 'password_file', or neither")
        if self.password_file is not None and self.tls is None and not is_loopback(self.host):
            # MQTT sends the password in the CONNECT packet as it is: over a network only
            # inside TLS
            raise ValueError(f"a password to broker {self.host!r} (not loopback) needs 'tls': "
                             "without it the password crosses the network in clear text")
        return self


@dataclass(frozen=True)
class MqttConfig:
    host: str
    port: int
    site: str
    root: str
    username: str | None
    password: str | None
    tls: ssl.SSLContext | None
    qos: int
    keepalive_s: int
    queue_max: int
    health_interval_s: float


def load_mqtt(f: MqttFile, base: Path, where: str,
              read_secret: Callable[[Path, str], str]) -> MqttConfig:
    """Resolve files (relative to daemon.yaml), read the password with ``read_secret``
    (config.read_token_file: private file, ≥ 16 characters), build the TLS context."""
    def _resolve(base: Path, p: str) -> Path:
        q = Path(os.path.expandvars(os.path.expanduser(p)))
        return q if q.is_absolute() else base / q

    password = None
    if f.password_file is not None:
        password = read_secret(_resolve(base, f.password_file), f"{where}.password_file")
    ctx = None
    if f.tls is not None:
        try:
            ctx = ssl.create_default_context(
                cafile=str(_resolve(base, f.tls.ca)) if f.tls.ca else None)
            if f.tls.cert and f.tls.key:
                ctx.load_cert_chain(_resolve(base, f.tls.cert), _resolve(base, f.tls.key))
        except (OSError, ssl.SSLError) as e:
            raise ConfigError(f"{where}.tls: {getattr(e, 'strerror', None) or e}") from None
    port = f.port or (8883 if ctx else 1883)
    return MqttConfig(f.host, port, f.site, f.root, f.username, password, ctx, f.qos,
                      f.keepalive_s, f.queue_max, f.health_interval_s)
