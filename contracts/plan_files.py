"""Plan files: the validated schema (unknown keys are errors), grid expansion and the loader."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from contracts.result_lines import MAX_RESULT_MM
from contracts.setup_types import MAX_POSES, MAX_TOUCHES, Bounded, safe_name
from contracts.yaml_files import ConfigError, StrictModel, read_yaml, validate_file
from identification.model import Artefact

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
    _n = field_validator("name")(safe_name)

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
