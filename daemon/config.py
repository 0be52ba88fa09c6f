"""``daemon.yaml``: the validated schema of the service configuration (unknown keys are errors)
and its loader, which also loads every machine's machine / artefact / plan files.

Every failure is one ``ConfigError`` line naming the file and key, e.g.
``daemon.yaml: machines.0.tolerances.links.EX0Q: not a location error of thesis-wcbxfzyt``.
Relative paths are resolved against the directory of ``daemon.yaml``.
"""

from __future__ import annotations

import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from contracts.input_files import read_bounded
from contracts.yaml_files import (
    ConfigError,
    HostName,
    StrictModel,
    format_validation,
    read_yaml,
    validate_file,
)
from daemon.hosts import is_loopback, normal_origin
from daemon.machines.setup import MachineEntry, MachineSetup, load_machines, resolve_path
from daemon.mqtt.config import MqttFile
from daemon.notify.config import NotifyFile
from daemon.opcua.config import OpcUaServerFile


class TlsFile(StrictModel):
    cert: str
    key: str


class HmiFile(StrictModel):
    enabled: bool = True
    host: HostName = "127.0.0.1"
    port: int = Field(8470, ge=0, le=65535)  # 0 = any free port (tests, demo)
    token: str | None = Field(None, min_length=16)
    token_file: str | None = None
    allow_remote: bool = False  # must be true to bind anything but loopback
    tls: TlsFile | None = None
    # scheme://name[:port] operators type when it differs from host (a DNS name, a proxy):
    # the Host and Origin checks (DNS-rebinding defence) accept these besides host itself
    public_origins: list[str] = []
    # a verdict older than this is shown as stale (the page says so, in the operator's colours)
    stale_after_h: float = Field(24.0, gt=0, le=8760)
    # Accounts (daemon/hmi/users.py, `rumba users`): people sign in with name and password and
    # act in their role; the token then serves scripts only (Authorization: Bearer)
    users_file: str | None = None

    @field_validator("public_origins")
    @classmethod
    def _origins(cls, v: list[str]) -> list[str]:
        bad = [o for o in v if normal_origin(o.rstrip("/")) is None]
        if bad:
            raise ValueError(f"{bad}: expected http(s)://host[:port], no path")
        return v

    @model_validator(mode="after")
    def _checks(self) -> HmiFile:
        if self.enabled and (self.token is None) == (self.token_file is None):
            raise ValueError("give exactly one of 'token' or 'token_file'")
        if not is_loopback(self.host) and not self.allow_remote:
            raise ValueError(f"host {self.host} is not loopback; set allow_remote: true to "
                             "expose the HMI on the network (and configure tls)")
        return self


class StoreFile(StrictModel):
    path: str = "rumba.sqlite"  # the local journal (in fleet mode: the buffer drained to url)
    synchronous: Literal["FULL", "NORMAL"] = "FULL"
    url: str | None = None  # sqlite:///path, or postgresql://… (fleet store, daemon/store/pg.py)


class DaemonFile(StrictModel):
    store: StoreFile = StoreFile()
    reports_dir: str = "reports"
    hmi: HmiFile = HmiFile(token_file="hmi.token")
    can_panel: dict[str, Any] | None = None  # validated by drivers.can.panel
    mqtt: MqttFile | None = None  # live results out (daemon/mqtt/publisher.py)
    notify: NotifyFile | None = None  # webhook / e-mail notifications (daemon/notify/notifier.py)
    opcua_server: OpcUaServerFile | None = None  # OPC UA results server, off if absent
    aqdef_dir: str | None = None  # an AQDEF (.dfq) file per finished run dropped here
    machines: list[MachineEntry] = Field(min_length=1)

    @model_validator(mode="after")
    def _unique(self) -> DaemonFile:
        names = [m.name for m in self.machines]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"duplicated machine names {dup}")
        return self


# ------------------------------------------------------------------------------ loaded form


@dataclass(frozen=True)
class DaemonConfig:
    path: Path
    store_path: Path
    synchronous: str
    reports_dir: Path
    hmi: HmiFile
    hmi_token: str | None
    hmi_tls: tuple[Path, Path] | None
    can_panel: dict[str, Any] | None
    machines: dict[str, MachineSetup]
    store_dsn: str | None = None  # postgresql://… : the fleet store the journal drains to
    mqtt: Any = None  # daemon.mqtt.config.MqttConfig
    notify: Any = None  # daemon.notify.config.NotifyConfig
    opcua_server: Any = None  # daemon.opcua.config.OpcUaServerConfig
    aqdef_dir: Path | None = None  # the AQDEF drop folder
    users_file: Path | None = None  # hmi.users_file: the HMI accounts


MAX_TOKEN_FILE_BYTES = 4096  # a token is 16 to a few hundred characters


def read_token_file(path: Path, where: str) -> str:
    """A token file must be private (no group/other permission bits) and ≥ 16 characters."""
    try:
        st = path.stat()
        # a regular file of at most 4 KiB: a FIFO would block the start, /dev/zero never end
        text = read_bounded(path, ConfigError, MAX_TOKEN_FILE_BYTES, "token file").decode(
            "utf-8").strip()
    except OSError as e:
        raise ConfigError(f"{where}: cannot read token file {path}: {e.strerror}") from None
    except ConfigError as e:
        raise ConfigError(f"{where}: token file {e}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{where}: token file {path}: not UTF-8 text") from None
    if stat.S_IMODE(st.st_mode) & 0o077:
        raise ConfigError(f"{where}: token file {path} is readable by others "
                          f"(mode {stat.S_IMODE(st.st_mode):04o}); chmod 600 it")
    if len(text) < 16:
        raise ConfigError(f"{where}: token in {path} is shorter than 16 characters")
    return text


def load_daemon_config(path: Path | str) -> DaemonConfig:
    path = Path(path)
    df: DaemonFile = validate_file(DaemonFile, path, read_yaml(path))
    base = path.parent
    machines = load_machines(df.machines, base, str(path))
    if df.can_panel is not None:
        from pydantic import ValidationError

        from drivers.can.schema import CanPanelConfig

        try:
            panel = CanPanelConfig.model_validate(df.can_panel)
        except ValidationError as e:
            raise ConfigError(format_validation(f"{path}: can_panel", e)) from None
        if panel.machine is not None and panel.machine not in machines:
            raise ConfigError(f"{path}: can_panel.machine: {panel.machine!r} is not a "
                              f"configured machine ({', '.join(machines)})")
    token, tls = None, None
    if df.hmi.enabled:
        token = df.hmi.token or read_token_file(resolve_path(base, df.hmi.token_file or ""),
                                                f"{path}: hmi.token_file")
        if df.hmi.tls is not None:
            from daemon.hmi.tls import server_context

            tls = (resolve_path(base, df.hmi.tls.cert), resolve_path(base, df.hmi.tls.key))
            server_context(*tls, f"{path}: hmi.tls")  # missing, mismatched, encrypted … keys
    users_file = None
    if df.hmi.enabled and df.hmi.users_file is not None:
        from daemon.hmi.users import UsersError, read_users

        users_file = resolve_path(base, df.hmi.users_file)
        try:
            read_users(users_file)  # a bad file stops the start here, naming the line
        except UsersError as e:
            raise ConfigError(f"{path}: hmi.users_file: {e}") from None
    store_path, dsn = resolve_path(base, df.store.path), None
    if df.store.url is not None:
        from daemon.store.url import parse_store_url

        url = parse_store_url(df.store.url, f"{path}: store.url")
        if url.kind == "sqlite" and "path" in df.store.model_fields_set:
            raise ConfigError(f"{path}: store: give 'path' or a sqlite:/// 'url', not both")
        store_path = resolve_path(base, str(url.path)) if url.kind == "sqlite" else store_path
        dsn = url.dsn
    mqtt = None
    if df.mqtt is not None:
        from daemon.mqtt.config import load_mqtt

        mqtt = load_mqtt(df.mqtt, base, f"{path}: mqtt", read_token_file)
    notify = None
    if df.notify is not None:
        from daemon.notify.config import load_notify

        notify = load_notify(df.notify, base, f"{path}: notify", list(machines),
                             read_token_file)
    opcua = None
    if df.opcua_server is not None:
        from daemon.opcua.config import load_opcua_server

        opcua = load_opcua_server(df.opcua_server, base, f"{path}: opcua_server",
                                  list(machines), read_token_file)
    return DaemonConfig(path, store_path, df.store.synchronous,
                        resolve_path(base, df.reports_dir), df.hmi, token, tls, df.can_panel,
                        machines, dsn, mqtt, notify, users_file=users_file, opcua_server=opcua,
                        aqdef_dir=None if df.aqdef_dir is None else resolve_path(
                            base, df.aqdef_dir))


def config_from_dict(data: Any, path: Path) -> DaemonFile:
    """Validate only (used by tests and `rumba run --check`)."""
    return validate_file(DaemonFile, path, data)
