"""Machine, artefact and plan files: validated schemas (unknown keys are errors) and loaders.

Every failure raises ``ConfigError`` whose message names the file, the key path and what was
expected, e.g. ``config/machines/x.yaml: axes.B.travel_deg: expected 2 items, got 3``.
"""

from __future__ import annotations

import datetime
import math
import re
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from contracts.result_lines import MAX_RESULT_MM
from contracts.yaml_files import (
    ConfigError,
    StrictModel,
    read_yaml,
    validate_file,
)
from identification.kinematics import Axis, Machine, TopologyError
from identification.model import Artefact, Ball, CalibratedDistance

SAFE_NAME = re.compile(r"\A[A-Za-z0-9_.-]{1,32}\Z")
"""Names that reach G-code (ball ids, machine and plan names) must match this: no spaces,
parentheses, semicolons, quotes or line breaks, so nothing can be injected into a program.
Use ``fullmatch``: with ``match`` and ``$`` a trailing newline would slip through (``\\Z`` also
guards a caller that uses ``match``)."""

MAX_POSES = 2_000
"""Ceiling on the poses of a plan (list or grid; the biggest shipped plan has 175), checked
before a grid is expanded."""
MAX_TOUCHES = 20_000
"""Ceiling on the touches of one program: visits (poses × repeats, + 1 with drift_check) ×
balls × 5 (the biggest shipped plan gives 3 500)."""
MAX_BALLS = 32
"""Ceiling on the balls of an artefact (the shipped ones have 4 or 5)."""




# Every length and angle of a setup file is bounded like a latched value (±1e5 mm or °): a finite
# but absurd number (1e308) would otherwise reach the kinematics and fail deep inside as a
# singular matrix instead of naming the key.
Bounded = Annotated[float, Field(ge=-MAX_RESULT_MM, le=MAX_RESULT_MM)]
# Free text kept for the audit trail (a serial number, a certificate): one printable line.
Record = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[^\x00-\x1f\x7f]+$")]
Vec3 = Annotated[list[Bounded], Field(min_length=3, max_length=3)]
Range2 = Annotated[list[Bounded], Field(min_length=2, max_length=2)]


def _safe_name(v: str) -> str:
    if not SAFE_NAME.fullmatch(v):
        raise ValueError(
            "must be 1-32 characters of letters, digits, '_', '.', '-' (it is written into G-code)"
        )
    return v


# ------------------------------------------------------------------------------------ machine


class AxisFile(StrictModel):
    type: Literal["linear", "rotary"]
    direction: Vec3
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


class ToolFile(StrictModel):
    tip_mm: Vec3 = [0.0, 0.0, 0.0]
    spindle_axis: Vec3 = [0.0, 0.0, 1.0]


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
    _n = field_validator("name")(_safe_name)


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
    gravity: Vec3 | None = None
    serial: Record | None = None  # the machine's serial number, printed on every report (audit)
    _n = field_validator("name")(_safe_name)

    @field_validator("gravity")
    @classmethod
    def _unit_gravity(cls, v: list[float] | None) -> list[float] | None:
        if v is None:
            return v
        n = math.sqrt(sum(x * x for x in v))
        if n < 1e-9:
            raise ValueError("must be a non-zero direction, e.g. [0, 0, -1]")
        return [x / n for x in v]


# ----------------------------------------------------------------------------------- artefact


class BallFile(StrictModel):
    id: str
    position_mm: Vec3
    rod_length_mm: float = Field(gt=0, le=1000)
    ball_diameter_mm: float | None = Field(None, gt=0, le=200)
    rod_diameter_mm: float | None = Field(None, gt=0, le=100)
    _n = field_validator("id")(_safe_name)


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
    _n = field_validator("name")(_safe_name)

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


# --------------------------------------------------------------------------------------- plan


class GridAxis(StrictModel):
    start_deg: Bounded
    stop_deg: Bounded
    step_deg: float = Field(gt=0, le=MAX_RESULT_MM)


class Grid(StrictModel):
    b: GridAxis
    c: GridAxis

    @model_validator(mode="after")
    def _ceiling(self) -> Grid:
        # counted from range / step before anything is expanded (step_deg: 1e-7 must not
        # allocate for half a minute and run out of memory)
        n = _grid_size(self.b) * _grid_size(self.c)
        if n > MAX_POSES:
            raise ValueError(f"the grid gives {n:.4g} poses ({_grid_size(self.b):.4g} b × "
                             f"{_grid_size(self.c):.4g} c), more than the ceiling of "
                             f"{MAX_POSES} poses per plan; use a larger step_deg")
        return self


class PoseFile(StrictModel):
    b_deg: Bounded
    c_deg: Bounded
    role: Literal["estimate", "validate"] = "estimate"


class FeedsFile(StrictModel):
    probe_mm_min: float = Field(300.0, gt=0, le=5000)
    approach_mm_min: float = Field(2000.0, gt=0, le=50000)
    # Two-speed touch (dialects that can repeat a probing move, programs/dialects): locate the
    # surface at this feed, back off, re-touch at probe_mm_min (the latched value). None: one.
    fast_probe_mm_min: float | None = Field(None, gt=0, le=5000)

    @model_validator(mode="after")
    def _fast_above_slow(self) -> FeedsFile:
        if self.fast_probe_mm_min is not None and self.fast_probe_mm_min <= self.probe_mm_min:
            raise ValueError(f"fast_probe_mm_min {self.fast_probe_mm_min:g} must be above "
                             f"probe_mm_min {self.probe_mm_min:g} (or left out: one speed)")
        return self


class PlanFile(StrictModel):
    name: str
    stylus_diameter_mm: float = Field(gt=0, le=50)
    # the stylus stem, checked by the safety check as a cylinder from the tip along the spindle
    stylus_length_mm: float = Field(50.0, gt=0, le=300)
    stem_diameter_mm: float | None = Field(None, gt=0, le=50)  # default: 0.75 × ball diameter
    poses: list[PoseFile] | None = None  # [b_deg, c_deg] entries are read as PoseFile
    grid: Grid | None = None
    feeds: FeedsFile = FeedsFile()
    standoff_mm: float = Field(2.0, gt=0, le=50)
    overtravel_mm: float = Field(2.0, gt=0, le=20)
    clearance_mm: float = Field(10.0, gt=0, le=500)
    dwell_s: float = Field(0.0, ge=0, le=10)
    repeats: int = Field(1, ge=1, le=20)
    # Re-probe the first pose once more at the end of the run: the shift of its ball centres
    # between the two visits is the run's thermal stability (analysis "stability", judged by
    # the health limit run_drift_um). Costs one pose.
    drift_check: bool = False
    _n = field_validator("name")(_safe_name)

    @field_validator("poses", mode="before")
    @classmethod
    def _pose_ceiling(cls, v: Any) -> Any:
        if not isinstance(v, list):
            return v
        if len(v) > MAX_POSES:
            raise ValueError(f"{len(v)} poses, more than the ceiling of {MAX_POSES} per plan")
        # [b, c] → {b_deg, c_deg}: one schema, so errors name poses.<i>.<key>, not union arms
        out = []
        for i, p in enumerate(v):
            if isinstance(p, list):
                if len(p) != 2:
                    raise ValueError(f"pose {i}: expected [b_deg, c_deg], got {len(p)} items")
                p = {"b_deg": p[0], "c_deg": p[1]}
            out.append(p)
        return out

    @model_validator(mode="after")
    def _one_pose_source(self) -> PlanFile:
        if (self.poses is None) == (self.grid is None):
            raise ValueError("give exactly one of 'poses' (list of [b_deg, c_deg]) or 'grid'")
        return self


# -------------------------------------------------------------------------- loaded, in domain


class Plan(StrictModel):
    """A validated plan with its poses expanded."""

    name: str
    stylus_diameter_mm: float
    stylus_length_mm: float = 50.0
    stem_diameter_mm: float | None = None
    poses: list[PoseFile]
    feeds: FeedsFile
    standoff_mm: float
    overtravel_mm: float
    clearance_mm: float
    dwell_s: float
    repeats: int
    drift_check: bool = False

    @property
    def stylus_radius_mm(self) -> float:
        return self.stylus_diameter_mm / 2.0

    @property
    def stem_radius_mm(self) -> float:
        d = self.stem_diameter_mm if self.stem_diameter_mm is not None else \
            0.75 * self.stylus_diameter_mm
        return d / 2.0

    def indices(self, role: str) -> list[int]:
        return [i for i, p in enumerate(self.poses) if p.role == role]


def _grid_size(g: GridAxis) -> float:
    """How many values a grid axis gives, from range / step without expanding it (inf when the
    span overflows)."""
    span = (g.stop_deg - g.start_deg) / g.step_deg
    return float(max(math.floor(span + 1e-9) + 1, 0)) if span < 1e15 else span


def _grid(g: GridAxis) -> list[float]:
    n = int(_grid_size(g))  # bounded by Grid._ceiling
    return [round(g.start_deg + k * g.step_deg, 9) for k in range(n)]


def machine_from_dict(data: Any, path: Path | str = "<machine>") -> tuple[Machine, MachineFile]:
    mf: MachineFile = validate_file(MachineFile, path, data)
    axes = {}
    for letter, a in mf.axes.items():
        travel = a.travel_mm if a.type == "linear" else a.travel_deg
        axes[letter] = Axis(letter, a.type, tuple(a.direction), tuple(a.point_mm or (0, 0, 0)),
                            tuple(travel), a.sign)
    try:
        m = Machine(mf.name, mf.topology, axes, tuple(mf.tool.tip_mm),
                    tuple(np.asarray(mf.tool.spindle_axis) / np.linalg.norm(mf.tool.spindle_axis)))
    except TopologyError as e:
        raise ConfigError(f"{path}: topology/axes: {e}") from None
    extra = set(axes) - set(m.workpiece_chain + m.tool_chain)
    if extra:
        raise ConfigError(f"{path}: axes: {sorted(extra)} not in topology {mf.topology}")
    return m, mf


def load_machine(path: Path | str) -> tuple[Machine, MachineFile]:
    """Load a machine file → (kinematic ``Machine``, validated file with dynamics/keep-outs)."""
    return machine_from_dict(read_yaml(path), path)


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


def plan_from_dict(data: Any, path: Path | str = "<plan>") -> Plan:
    pf: PlanFile = validate_file(PlanFile, path, data)
    if pf.grid is not None:
        poses = [PoseFile(b_deg=b, c_deg=c) for b in _grid(pf.grid.b) for c in _grid(pf.grid.c)]
    else:
        poses = list(pf.poses or [])
    if not poses:
        raise ConfigError(f"{path}: poses: the plan has no pose")
    return Plan(name=pf.name, stylus_diameter_mm=pf.stylus_diameter_mm,
                stylus_length_mm=pf.stylus_length_mm, stem_diameter_mm=pf.stem_diameter_mm,
                poses=poses,
                feeds=pf.feeds, standoff_mm=pf.standoff_mm, overtravel_mm=pf.overtravel_mm,
                clearance_mm=pf.clearance_mm, dwell_s=pf.dwell_s, repeats=pf.repeats,
                drift_check=pf.drift_check)


def touch_count(plan: Plan, artefact: Artefact) -> int:
    """Touches of the program of ``plan`` on ``artefact``: visits × balls × 5."""
    visits = len(plan.poses) * plan.repeats + (1 if plan.drift_check else 0)
    return visits * len(artefact.balls) * 5


def check_touch_count(plan: Plan, artefact: Artefact, where: str) -> None:
    """``ConfigError`` naming ``where`` when the program would exceed MAX_TOUCHES."""
    n = touch_count(plan, artefact)
    if n > MAX_TOUCHES:
        raise ConfigError(
            f"{where}: {n} touches ({len(plan.poses)} poses × {plan.repeats} repeats"
            f"{' + 1 drift check' if plan.drift_check else ''} × {len(artefact.balls)} balls × "
            f"5), more than the ceiling of {MAX_TOUCHES} touches per program")


def load_plan(path: Path | str) -> Plan:
    return plan_from_dict(read_yaml(path), path)
