"""The machines section of daemon.yaml: its schema (one entry per machine: files, dialect, link,
triggers, tolerances) and the loaded, cross-checked ``MachineSetup`` every session runs with."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from contracts.dialects import DialectName
from contracts.map_job import MapJob, load_map_job
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
from contracts.temperatures import TemperatureChannel, check_address
from contracts.yaml_files import ConfigError, StrictModel
from daemon.hosts import is_loopback
from daemon.machines.tolerances import Limit, Tolerances
from identification.kinematics import Machine
from identification.model import Artefact


class LimitFile(StrictModel):
    warn: float | None = Field(None, gt=0)
    fail: float | None = Field(None, gt=0)
    drift_warn: float | None = Field(None, gt=0)
    drift_fail: float | None = Field(None, gt=0)
    # where these numbers come from, e.g. "ISO 10791-6 K2 acceptance 25 µm" or
    # "1/3 of the 0.10 mm position tolerance": printed beside the limit, never interpreted
    source: str | None = Field(None, min_length=3, max_length=300)

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


class TemperatureLimitFile(StrictModel):
    """A temperature channel's limits (°C): outside [min_c, max_c] or a change over the run
    beyond change_c turns the verdict to WARN with the reason (never FAIL by itself)."""

    min_c: float | None = Field(None, ge=-50, le=150)
    max_c: float | None = Field(None, ge=-50, le=150)
    change_c: float | None = Field(None, gt=0, le=100)

    @model_validator(mode="after")
    def _order(self) -> TemperatureLimitFile:
        if self.min_c is not None and self.max_c is not None and self.min_c >= self.max_c:
            raise ValueError(f"min_c {self.min_c} must be below max_c {self.max_c}")
        return self


class TolerancesFile(StrictModel):
    # what the limits are derived from: the machine's accuracy class or acceptance
    # protocol (ISO 230-1 / ISO 10791-6 tests) and the parts' tolerances; README "Choosing
    # limits"
    basis: str | None = Field(None, min_length=3, max_length=1000)
    links: dict[str, LimitFile] = {}
    default_translation_um: LimitFile | None = None
    default_rotation_urad: LimitFile | None = None
    volumetric_max_um: LimitFile | None = None
    residual_rms_um: float | None = Field(None, gt=0)
    sphere_radius_spread_um: float | None = Field(5.0, gt=0)
    sphere_form_um: float | None = Field(None, gt=0)
    coverage_k: float = Field(2.0, ge=0, le=5)
    run_drift_um: float | None = Field(None, gt=0)
    thermal_drift_um: float | None = Field(None, gt=0)  # fitted TCP drift over a run
    temperatures: dict[str, TemperatureLimitFile] = {}  # per channel name

    def to_tolerances(self) -> Tolerances:
        conv = (lambda x: x.to_limit() if x is not None else None)  # noqa: E731
        return Tolerances({k: v.to_limit() for k, v in self.links.items()},
                          conv(self.default_translation_um), conv(self.default_rotation_urad),
                          conv(self.volumetric_max_um), self.residual_rms_um,
                          self.sphere_radius_spread_um, self.sphere_form_um, self.coverage_k,
                          self.run_drift_um, self.thermal_drift_um,
                          {k: (v.min_c, v.max_c, v.change_c)
                           for k, v in self.temperatures.items()},
                          basis=self.basis or "", sources=self.sources())

    def sources(self) -> dict[str, str]:
        """Each limit's stated source by its key (``links.EX0C``, ``volumetric_max_um`` …)."""
        named = {f"links.{k}": v for k, v in self.links.items()} | {
            "default_translation_um": self.default_translation_um,
            "default_rotation_urad": self.default_rotation_urad,
            "volumetric_max_um": self.volumetric_max_um}
        return {k: v.source for k, v in named.items() if v is not None and v.source}


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
    # temperature channels read at the start, every pose and the end (contracts/temperatures.py)
    temperatures: list[TemperatureChannel] = Field(default_factory=list, max_length=16)
    # a map of the linear axes this machine may run (contracts/map_job.py): placements each a
    # plan and an artefact file, an operator prompt between them; started as a job of its own
    map_job: str | None = None
    _n = field_validator("name")(safe_name)

    @field_validator("temperatures")
    @classmethod
    def _unique_channels(cls, v: list[TemperatureChannel]) -> list[TemperatureChannel]:
        names = [c.name for c in v]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"duplicated temperature channel names {dup}")
        return v

    @field_validator("link")
    @classmethod
    def _link_type(cls, v: dict[str, Any]) -> dict[str, Any]:
        if not isinstance(v.get("transport"), str):
            raise ValueError("link needs a 'transport' (serial, opcua, modbus, linuxcnc)")
        return v


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
    reprobe_max: int = 2  # re-probe rounds of faulty ball visits (daemon/run/reprobe.py)
    operator: str | None = None  # for the report's audit fields
    artefact_file: Any = None  # contracts.setup_files.ArtefactFile (its calibration record)
    temperatures: tuple[TemperatureChannel, ...] = ()  # channels read during a run
    map_job: MapJob | None = None  # the map-job file of daemon.yaml's ``map_job`` (loaded)


def resolve_path(base: Path, p: str) -> Path:
    q = Path(os.path.expandvars(os.path.expanduser(p)))
    return q if q.is_absolute() else (base / q)


def named_file(base: Path, p: str, key: str) -> Path:
    """A file named in daemon.yaml: a missing one is reported under daemon.yaml's key."""
    q = resolve_path(base, p)
    if not q.is_file():
        raise ConfigError(f"{key}: file {str(q)!r} not found")
    return q


def validate_link(link: dict[str, Any], where: str, base: Path) -> Any:
    """The transport section, validated by the drivers' own schema (drivers/<transport>/schema.py);
    relative certificate paths, and a Haas share's folder, are resolved against daemon.yaml's
    directory as every other path of the file (LinuxCNC's program_dir must be absolute: it
    is the control's own path, which the link refuses relative)."""
    from drivers.registry import link_config

    link = dict(link)
    keys = ("certificate", "private_key", "server_certificate") + (
        ("program_dir",) if link.get("transport") == "haas" else ())
    for k in keys:
        if isinstance(link.get(k), str):
            link[k] = str(resolve_path(base, link[k]))
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


def load_machines(entries: list[MachineEntry], base: Path, where: str
                  ) -> dict[str, MachineSetup]:
    """Each machine entry loaded (machine, artefact and plan files relative to ``base``) and
    cross-checked; errors name ``where`` (daemon.yaml's path) and the key."""
    machines: dict[str, MachineSetup] = {}
    for i, m in enumerate(entries):
        key = f"{where}: machines.{i}"
        machine, mfile = load_machine(named_file(base, m.machine, f"{key}.machine"))
        artefact, afile = load_artefact_file(named_file(base, m.artefact, f"{key}.artefact"))
        plan = load_plan(named_file(base, m.plan, f"{key}.plan"))
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
        _check_temperatures(m, key)
        machines[m.name] = MachineSetup(
            m.name, machine, mfile, artefact, plan, m.dialect,
            validate_link(m.link, f"{key}.link", base), m.triggers,
            m.tolerances.to_tolerances(), m.touch_timeout_s, tuple(held),
            m.rerun_interrupted, m.program_targets, m.reprobe_max, operator=m.operator,
            artefact_file=afile, temperatures=tuple(m.temperatures),
            map_job=None if m.map_job is None else
            load_map_job(named_file(base, m.map_job, f"{key}.map_job")))
    return machines


def _check_temperatures(m: MachineEntry, key: str) -> None:
    """Each channel's address suits the run's link (a HAL pin on LinuxCNC, a macro variable of
    the dialect on a DNC line …); a limit names a configured channel."""
    for i, ch in enumerate(m.temperatures):
        try:
            check_address(ch, str(m.link.get("transport")), m.dialect)
        except ValueError as e:
            raise ConfigError(f"{key}.temperatures.{i}.address: {e}") from None
    host = str(m.link.get("host", "127.0.0.1"))
    if (m.temperatures and m.link.get("transport") == "linuxcnc"
            and m.link.get("mode", "remote") == "remote" and not is_loopback(host)
            and any(ch.source == "controller" for ch in m.temperatures)):
        raise ConfigError(f"{key}.temperatures: HAL pins are read with halcmd on the LinuxCNC "
                          f"PC; the link reaches {host}: run rumba there (mode: local or "
                          "linuxcncrsh on 127.0.0.1) or use a transmitter")
    names = {ch.name for ch in m.temperatures}
    for name in m.tolerances.temperatures:
        if name not in names:
            raise ConfigError(f"{key}.tolerances.temperatures.{name}: no temperature channel "
                              f"of that name (configured: {', '.join(sorted(names)) or 'none'})")
