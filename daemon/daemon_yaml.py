"""``daemon.yaml``: the validated schema of the service configuration (unknown keys are errors)
and its loader, which also loads every machine's machine / artefact / plan files.

Every failure is one ``ConfigError`` line naming the file and key, e.g.
``daemon.yaml: machines.0.tolerances.links.EX0Q: not a location error of thesis-wcbxfzyt``.
Relative paths are resolved against the directory of ``daemon.yaml``.
"""

from __future__ import annotations

import ipaddress
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from contracts.result_lines import DialectName
from contracts.setup_files import (
    MachineFile,
    Plan,
    Record,
    check_touch_count,
    load_artefact_file,
    load_machine,
    load_plan,
    safe_name,
)
from contracts.yaml_files import (
    ConfigError,
    StrictModel,
    format_validation,
    read_yaml,
    validate_file,
)
from daemon.judge import Limit, Tolerances
from daemon.mqtt_config import MqttFile
from daemon.notify_config import NotifyFile
from identification.kinematics import Machine
from identification.model import Artefact


class LimitFile(StrictModel):
    warn: float | None = Field(None, gt=0)
    fail: float | None = Field(None, gt=0)
    drift_warn: float | None = Field(None, gt=0)
    drift_fail: float | None = Field(None, gt=0)

    @model_validator(mode="after")
    def _order(self) -> LimitFile:
        if self.warn is not None and self.fail is not None and self.warn > self.fail:
            raise ValueError(f"warn {self.warn} must not exceed fail {self.fail}")
        if (self.drift_warn is not None and self.drift_fail is not None
                and self.drift_warn > self.drift_fail):
            raise ValueError("drift_warn must not exceed drift_fail")
        return self

    def to_limit(self) -> Limit:
        return Limit(self.warn, self.fail, self.drift_warn, self.drift_fail)


class TolerancesFile(StrictModel):
    links: dict[str, LimitFile] = {}
    default_translation_um: LimitFile | None = None
    default_rotation_urad: LimitFile | None = None
    volumetric_max_um: LimitFile | None = None
    residual_rms_um: float | None = Field(None, gt=0)
    sphere_radius_spread_um: float | None = Field(5.0, gt=0)
    sphere_form_um: float | None = Field(None, gt=0)
    coverage_k: float = Field(2.0, ge=0, le=5)
    run_drift_um: float | None = Field(None, gt=0)

    def to_tolerances(self) -> Tolerances:
        conv = (lambda x: x.to_limit() if x is not None else None)  # noqa: E731
        return Tolerances({k: v.to_limit() for k, v in self.links.items()},
                          conv(self.default_translation_um), conv(self.default_rotation_urad),
                          conv(self.volumetric_max_um), self.residual_rms_um,
                          self.sphere_radius_spread_um, self.sphere_form_um, self.coverage_k,
                          self.run_drift_um)


class TriggersFile(StrictModel):
    cnc: bool = True  # the controller's start-of-shift request (if the link supports it)
    hmi: bool = True
    can: bool = True


class MachineEntry(StrictModel):
    name: str
    machine: str  # path to the machine YAML
    artefact: str
    plan: str
    dialect: DialectName
    link: dict[str, Any]  # transport section, validated by drivers.registry
    triggers: TriggersFile = TriggersFile()
    tolerances: TolerancesFile = TolerancesFile()
    touch_timeout_s: float = Field(300.0, gt=0, le=3600)
    # Plan pose indices held out for prediction (Annexe B); default: the plan's 'validate' poses.
    validate_poses: list[int] | None = None
    rerun_interrupted: bool = False  # start a new run at startup if one was interrupted
    # Touch targets: nominal artefact, or the setup estimated by the last PASS run (smaller
    # standoff, faster cycle; a re-mounted artefact then needs one nominal run).
    program_targets: Literal["nominal", "last_good"] = "nominal"
    # A ball visit the outlier test flags (a chip, dirt, a bad trigger) is probed again after
    # the program, its whole pose, up to this many rounds; 0: never (the verdict is ERROR).
    reprobe_max: int = Field(2, ge=0, le=5)
    operator: Record | None = None  # who answers for this machine's checks (on every report)
    _n = field_validator("name")(safe_name)

    @field_validator("link")
    @classmethod
    def _link_type(cls, v: dict[str, Any]) -> dict[str, Any]:
        if not isinstance(v.get("transport"), str):
            raise ValueError("link needs a 'transport' (serial, opcua, modbus, linuxcnc)")
        return v


def is_loopback(host: str) -> bool:
    """Whether the HMI host is a loopback address (or ``localhost``)."""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


class TlsFile(StrictModel):
    cert: str
    key: str


class HmiFile(StrictModel):
    enabled: bool = True
    host: str = "127.0.0.1"
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

    @field_validator("public_origins")
    @classmethod
    def _origins(cls, v: list[str]) -> list[str]:
        from daemon.hmi.limits import normal_origin

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
    url: str | None = None  # sqlite:///path, or postgresql://… (fleet store, daemon/store_pg.py)


class DaemonFile(StrictModel):
    store: StoreFile = StoreFile()
    reports_dir: str = "reports"
    hmi: HmiFile = HmiFile(token_file="hmi.token")
    can_panel: dict[str, Any] | None = None  # validated by drivers.can.panel
    mqtt: MqttFile | None = None  # live results out (daemon/mqtt.py)
    notify: NotifyFile | None = None  # webhook / e-mail notifications (daemon/notify.py)
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
class MachineSetup:
    """Everything one session needs, loaded and cross-checked."""

    name: str
    machine: Machine
    machine_file: MachineFile
    artefact: Artefact
    plan: Plan
    dialect: str
    link: Any  # drivers.registry.LinkConfig (one of the transport schemas)
    triggers: TriggersFile
    tolerances: Tolerances
    touch_timeout_s: float
    validate_poses: tuple[int, ...]
    rerun_interrupted: bool
    program_targets: str = "nominal"
    reprobe_max: int = 2  # re-probe rounds of faulty ball visits (daemon/reprobe.py)
    operator: str | None = None  # for the report's audit fields
    artefact_file: Any = None  # contracts.setup_files.ArtefactFile (its calibration record)


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
    mqtt: Any = None  # daemon.mqtt_config.MqttConfig
    notify: Any = None  # daemon.notify_config.NotifyConfig


def _resolve(base: Path, p: str) -> Path:
    q = Path(os.path.expandvars(os.path.expanduser(p)))
    return q if q.is_absolute() else (base / q)


def _named_file(base: Path, p: str, key: str) -> Path:
    """A file named in daemon.yaml: a missing one is reported under daemon.yaml's key."""
    q = _resolve(base, p)
    if not q.is_file():
        raise ConfigError(f"{key}: file {str(q)!r} not found")
    return q


def read_token_file(path: Path, where: str) -> str:
    """A token file must be private (no group/other permission bits) and ≥ 16 characters."""
    try:
        st = path.stat()
        text = path.read_text(encoding="utf-8").strip()
    except OSError as e:
        raise ConfigError(f"{where}: cannot read token file {path}: {e.strerror}") from None
    if stat.S_IMODE(st.st_mode) & 0o077:
        raise ConfigError(f"{where}: token file {path} is readable by others "
                          f"(mode {stat.S_IMODE(st.st_mode):04o}); chmod 600 it")
    if len(text) < 16:
        raise ConfigError(f"{where}: token in {path} is shorter than 16 characters")
    return text


def _validate_link(link: dict[str, Any], where: str, base: Path) -> Any:
    """The transport section, validated by the drivers' own schema (drivers/<transport>/schema.py);
    relative certificate paths are resolved against daemon.yaml's directory."""
    from drivers.registry import link_config

    link = dict(link)
    for k in ("certificate", "private_key", "server_certificate"):
        if isinstance(link.get(k), str):
            link[k] = str(_resolve(base, link[k]))
    cfg = link_config(link, where)
    for k in ("certificate", "private_key", "server_certificate"):
        p = getattr(cfg, k, None)
        if p is not None and not Path(p).is_file():
            raise ConfigError(f"{where}.{k}: file {p} not found")
    return cfg


def _check_identifiable(machine: Machine, artefact: Artefact, plan: Plan, names: Any,
                        key: str) -> None:
    """A tolerance on a link error the plan cannot identify would never be checked."""
    from identification.identifiability import identifiable_links, nominal_centres

    centres = nominal_centres(machine, artefact, [(p.b_deg, p.c_deg) for p in plan.poses])
    ident = identifiable_links(machine, artefact, centres)
    for name in names:
        if name not in ident.links:
            why = ident.dropped.get(name, "not identifiable")
            raise ConfigError(f"{key}.tolerances.links.{name}: not identifiable with plan "
                              f"{plan.name} (absorbed by {why}); identifiable: "
                              f"{', '.join(ident.links)}")


def load_daemon_config(path: Path | str) -> DaemonConfig:
    path = Path(path)
    df: DaemonFile = validate_file(DaemonFile, path, read_yaml(path))
    base = path.parent
    machines: dict[str, MachineSetup] = {}
    for i, m in enumerate(df.machines):
        key = f"{path}: machines.{i}"
        machine, mfile = load_machine(_named_file(base, m.machine, f"{key}.machine"))
        artefact, afile = load_artefact_file(_named_file(base, m.artefact, f"{key}.artefact"))
        plan = load_plan(_named_file(base, m.plan, f"{key}.plan"))
        check_touch_count(plan, artefact, f"{key}.plan")
        known = set(machine.location_error_names())
        for name in m.tolerances.links:
            if name not in known:
                raise ConfigError(f"{key}.tolerances.links.{name}: not a location error of "
                                  f"{machine.name} (known: {', '.join(sorted(known))})")
        if m.tolerances.links:
            _check_identifiable(machine, artefact, plan, m.tolerances.links, key)
        held = plan.indices("validate") if m.validate_poses is None else m.validate_poses
        bad = [p for p in held if not 0 <= p < len(plan.poses)]
        if bad:
            raise ConfigError(f"{key}.validate_poses: {bad} outside the plan's "
                              f"{len(plan.poses)} poses (0-based)")
        machines[m.name] = MachineSetup(
            m.name, machine, mfile, artefact, plan, m.dialect,
            _validate_link(m.link, f"{key}.link", base), m.triggers,
            m.tolerances.to_tolerances(), m.touch_timeout_s, tuple(held),
            m.rerun_interrupted, m.program_targets, m.reprobe_max, operator=m.operator,
            artefact_file=afile)
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
        token = df.hmi.token or read_token_file(_resolve(base, df.hmi.token_file or ""),
                                                f"{path}: hmi.token_file")
        if df.hmi.tls is not None:
            from daemon.hmi.tls import server_context

            tls = (_resolve(base, df.hmi.tls.cert), _resolve(base, df.hmi.tls.key))
            server_context(*tls, f"{path}: hmi.tls")  # missing, mismatched, encrypted … keys
    store_path, dsn = _resolve(base, df.store.path), None
    if df.store.url is not None:
        from daemon.store_url import parse_store_url

        url = parse_store_url(df.store.url, f"{path}: store.url")
        if url.kind == "sqlite" and "path" in df.store.model_fields_set:
            raise ConfigError(f"{path}: store: give 'path' or a sqlite:/// 'url', not both")
        store_path = _resolve(base, str(url.path)) if url.kind == "sqlite" else store_path
        dsn = url.dsn
    mqtt = None
    if df.mqtt is not None:
        from daemon.mqtt_config import load_mqtt

        mqtt = load_mqtt(df.mqtt, base, f"{path}: mqtt", read_token_file)
    notify = None
    if df.notify is not None:
        from daemon.notify_config import load_notify

        notify = load_notify(df.notify, base, f"{path}: notify", list(machines),
                             read_token_file)
    return DaemonConfig(path, store_path, df.store.synchronous, _resolve(base, df.reports_dir),
                        df.hmi, token, tls, df.can_panel, machines, dsn, mqtt, notify)


def config_from_dict(data: Any, path: Path) -> DaemonFile:
    """Validate only (used by tests and `rumba run --check`)."""
    return validate_file(DaemonFile, path, data)
