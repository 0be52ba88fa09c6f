"""Machine, artefact and plan files: validated schemas (unknown keys are errors) and loaders.

Plans live in ``plan_files`` and the shared pieces in ``setup_types``; both are re-exported
here, the one import place for setup files.

Every failure raises ``ConfigError`` whose message names the file, the key path and what was
expected, e.g. ``config/machines/x.yaml: axes.B.travel_deg: expected 2 items, got 3``.
"""

from __future__ import annotations

import datetime
import math
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from contracts.controller_kinematics import (
    ControllerKinematics,
    ControllerKinematicsFile,
    controller_kinematics,
)
from contracts.plan_files import (
    FeedsFile,
    Grid,
    GridAxis,
    Plan,
    PlanFile,
    PoseFile,
    check_touch_count,
    load_plan,
    plan_from_dict,
    touch_count,
)
from contracts.result_lines import MAX_RESULT_MM
from contracts.setup_types import (
    MAX_BALLS,
    MAX_POSES,
    MAX_TOUCHES,
    SAFE_NAME,
    Bounded,
    Direction,
    Range2,
    Record,
    Vec3,
    safe_name,
)
from contracts.yaml_files import (
    ConfigError,
    StrictModel,
    read_yaml,
    validate_file,
)
from identification.kinematics import Axis, Machine, TopologyError
from identification.model import Artefact, Ball, CalibratedDistance

# ------------------------------------------------------------------------------------ machine


class AxisFile(StrictModel):
    type: Literal["linear", "rotary"]
    direction: Direction
    point_mm: Vec3 | None = None
    travel_mm: Range2 | None = None
    travel_deg: Range2 | None = None
    sign: Literal[1, -1] = 1

    @model_validator(mode="after")
    def _units(self) -> AxisFile:
        if self.type == "linear":
            if self.travel_deg is not None or self.point_mm is not None:
                raise ValueError("a linear axis takes travel_mm and no point_mm / travel_deg")
            if self.travel_mm is None:
                raise ValueError("travel_mm [min, max] is required for a linear axis")
            travel = self.travel_mm
        else:
            if self.travel_mm is not None:
                raise ValueError("a rotary axis takes travel_deg, not travel_mm")
            if self.travel_deg is None:
                raise ValueError("travel_deg [min, max] is required for a rotary axis")
            travel = self.travel_deg
        if travel[0] >= travel[1]:
            raise ValueError(f"travel minimum {travel[0]} must be below maximum {travel[1]}")
        return self


class ToolBody(StrictModel):
    """A keep-out that moves with the tool: a cylinder around the spindle axis from
    ``from_mm`` to ``to_mm`` above the stylus tip (probe body, spindle nose, head housing); the
    safety check keeps it clear of balls, rods, table and boxes on every move and index."""

    name: str
    from_mm: float = Field(gt=0, le=MAX_RESULT_MM)
    to_mm: float = Field(gt=0, le=MAX_RESULT_MM)
    radius_mm: float = Field(gt=0, le=MAX_RESULT_MM)
    _n = field_validator("name")(safe_name)

    @model_validator(mode="after")
    def _span(self) -> ToolBody:
        if self.to_mm <= self.from_mm:
            raise ValueError(f"to_mm {self.to_mm} must be beyond from_mm {self.from_mm}")
        return self


class ToolFile(StrictModel):
    tip_mm: Vec3 = [0.0, 0.0, 0.0]
    spindle_axis: Direction = [0.0, 0.0, 1.0]
    bodies: list[ToolBody] = []


class DynamicsFile(StrictModel):
    rapid_mm_min: float = Field(20000.0, gt=0, le=200000)
    rotary_rapid_deg_min: float = Field(5400.0, gt=0, le=200000)
    rotary_clamp_s: float = Field(0.5, ge=0, le=30)
    max_feed_mm_min: float = Field(5000.0, gt=0, le=100000)
    max_probe_feed_mm_min: float = Field(1000.0, gt=0, le=10000)


class TableFile(StrictModel):
    """The table (pallet) as a keep-out: a disc of ``radius_mm`` whose top is ``surface_z_mm``
    in the last workpiece frame; nothing of the tool may come below it plus ``clearance_mm``."""

    surface_z_mm: Bounded = 0.0
    radius_mm: float = Field(250.0, gt=0, le=MAX_RESULT_MM)
    clearance_mm: float = Field(5.0, ge=0, le=MAX_RESULT_MM)


class KeepOutBox(StrictModel):
    """An extra keep-out box in the last workpiece frame (a clamp, a fixture)."""

    name: str
    min_mm: Vec3
    max_mm: Vec3
    _n = field_validator("name")(safe_name)


class ProbeRecordFile(StrictModel):
    """The touch probe in the spindle, for the audit block of every report: its
    last qualification (the stylus' effective diameter measured on a reference sphere); the
    diameter the computation uses is the plan's ``stylus_diameter_mm``."""

    model: Record | None = None
    serial: Record | None = None
    qualified_on: datetime.date
    qualified_by: Record | None = None

    @field_validator("qualified_on")
    @classmethod
    def _not_future(cls, v: datetime.date) -> datetime.date:
        if v > datetime.date.today():
            raise ValueError(f"qualified_on {v} is in the future")
        return v


class MachineFile(StrictModel):
    name: str
    topology: str
    axes: dict[Literal["X", "Y", "Z", "A", "B", "C"], AxisFile]
    tool: ToolFile = ToolFile()
    dynamics: DynamicsFile = DynamicsFile()
    table: TableFile = TableFile()
    keep_out: list[KeepOutBox] = []
    # Direction of gravity in the foundation frame (any length, normalised on load), e.g.
    # [0, -1, 0] on a horizontal machine; None: identification.effects.default_gravity guesses.
    gravity: Direction | None = None
    serial: Record | None = None  # the machine's serial number, printed on every report (audit)
    probe: ProbeRecordFile | None = None  # the spindle probe's qualification (report)
    # What the control keeps of its kinematic model and where (compensation write-back)
    controller_kinematics: ControllerKinematicsFile | None = None
    # Rotary positioning repeatability (µrad 1σ per indexation, by rotary axis letter), e.g.
    # from the builder's ISO 230-2 test: the gap diagnosis uses it as given for the per-visit
    # index scatter instead of estimating it from the run.
    rotary_repeatability_urad: dict[Literal["A", "B", "C"],
                                    Annotated[float, Field(ge=0, le=1000)]] | None = None
    _n = field_validator("name")(safe_name)

    @field_validator("gravity")
    @classmethod
    def _unit_gravity(cls, v: list[float] | None) -> list[float] | None:
        if v is None:
            return v
        n = math.sqrt(sum(x * x for x in v))  # not zero: ``Direction``
        return [x / n for x in v]


# ----------------------------------------------------------------------------------- artefact


class BallFile(StrictModel):
    id: str
    position_mm: Vec3
    rod_length_mm: float = Field(gt=0, le=1000)
    ball_diameter_mm: float | None = Field(None, gt=0, le=200)
    rod_diameter_mm: float | None = Field(None, gt=0, le=100)
    _n = field_validator("id")(safe_name)


class DistanceFile(StrictModel):
    balls: Annotated[list[str], Field(min_length=2, max_length=2)]
    distance_mm: float = Field(gt=0, le=MAX_RESULT_MM)
    std_um: float = Field(0.5, gt=0, le=100)


class CalibrationFile(StrictModel):
    """The artefact's calibration certificate (balls, calibrated distances), for the audit
    trail printed on every report; the method itself needs none unless ``distances`` are used."""

    certificate: Record
    date: datetime.date
    laboratory: Record | None = None


class ArtefactFile(StrictModel):
    name: str
    ball_diameter_mm: float = Field(25.4, gt=0, le=200)
    rod_diameter_mm: float = Field(8.0, gt=0, le=100)
    balls: list[BallFile] = Field(min_length=1, max_length=MAX_BALLS)
    distances: list[DistanceFile] = []
    calibration: CalibrationFile | None = None
    _n = field_validator("name")(safe_name)

    @model_validator(mode="after")
    def _ids(self) -> ArtefactFile:
        ids = [b.id for b in self.balls]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"duplicated ball ids {dup}")
        for d in self.distances:
            for b in d.balls:
                if b not in ids:
                    raise ValueError(f"distance refers to unknown ball {b!r} (balls: {ids})")
            if d.balls[0] == d.balls[1]:
                raise ValueError("a calibrated distance needs two different balls")
        return self


def machine_from_dict(data: Any, path: Path | str = "<machine>") -> tuple[Machine, MachineFile]:
    mf: MachineFile = validate_file(MachineFile, path, data)
    axes = {}
    for letter, a in mf.axes.items():
        travel = a.travel_mm if a.type == "linear" else a.travel_deg
        d = np.asarray(a.direction, float)  # an inclined axis may be given to a few digits
        axes[letter] = Axis(letter, a.type, tuple(float(x) for x in d / np.linalg.norm(d)),
                            tuple(a.point_mm or (0, 0, 0)), tuple(travel), a.sign)
    try:
        m = Machine(mf.name, mf.topology, axes, tuple(mf.tool.tip_mm),
                    tuple(np.asarray(mf.tool.spindle_axis) / np.linalg.norm(mf.tool.spindle_axis)))
    except TopologyError as e:
        raise ConfigError(f"{path}: topology/axes: {e}") from None
    extra = set(axes) - set(m.workpiece_chain + m.tool_chain)
    if extra:
        raise ConfigError(f"{path}: axes: {sorted(extra)} not in topology {mf.topology}")
    if mf.controller_kinematics is not None:
        controller_kinematics(mf.controller_kinematics, m, path)  # checked against the machine
    for letter in mf.rotary_repeatability_urad or {}:
        if letter not in m.rotary_axes:
            raise ConfigError(f"{path}: rotary_repeatability_urad.{letter}: not a rotary axis "
                              f"of this machine ({m.rotary_axes})")
    return m, mf


def load_machine(path: Path | str) -> tuple[Machine, MachineFile]:
    """Load a machine file → (kinematic ``Machine``, validated file with dynamics/keep-outs)."""
    return machine_from_dict(read_yaml(path), path)


def load_controller_kinematics(path: Path | str) -> tuple[Machine, ControllerKinematics | None]:
    """The machine and its ``controller_kinematics`` section (None when the file has none)."""
    m, mf = load_machine(path)
    if mf.controller_kinematics is None:
        return m, None
    return m, controller_kinematics(mf.controller_kinematics, m, path)


def artefact_from_dict(data: Any, path: Path | str = "<artefact>") -> Artefact:
    af: ArtefactFile = validate_file(ArtefactFile, path, data)
    balls = tuple(
        Ball(b.id, tuple(b.position_mm), b.ball_diameter_mm or af.ball_diameter_mm,
             b.rod_length_mm, b.rod_diameter_mm or af.rod_diameter_mm)
        for b in af.balls
    )
    dists = tuple(CalibratedDistance(d.balls[0], d.balls[1], d.distance_mm, d.std_um)
                  for d in af.distances)
    return Artefact(af.name, balls, dists)


def load_artefact(path: Path | str) -> Artefact:
    return artefact_from_dict(read_yaml(path), path)


def load_artefact_file(path: Path | str) -> tuple[Artefact, ArtefactFile]:
    """The artefact and its validated file (with the calibration record for reports)."""
    data = read_yaml(path)
    return artefact_from_dict(data, path), validate_file(ArtefactFile, path, data)


__all__ = ["MAX_BALLS", "MAX_POSES", "MAX_TOUCHES", "SAFE_NAME", "ArtefactFile", "AxisFile",
           "BallFile", "Bounded", "CalibrationFile", "ConfigError", "Direction", "DistanceFile",
           "DynamicsFile", "FeedsFile", "Grid", "GridAxis", "KeepOutBox", "MachineFile", "Plan",
           "PlanFile", "PoseFile", "Range2", "Record", "TableFile", "ToolFile", "Vec3",
           "artefact_from_dict", "check_touch_count", "load_artefact", "load_artefact_file",
           "load_controller_kinematics", "load_machine", "load_plan", "machine_from_dict",
           "plan_from_dict", "safe_name", "touch_count"]
